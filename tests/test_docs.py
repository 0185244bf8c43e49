"""The front page and the manual: README length and links, the README's image and its command.

The manual itself is built by ``make docs`` (``sphinx-build -W``: a broken link, a missing
image or a docstring Sphinx cannot read fails it), which ``make test`` and so CI run.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from dvr_perception.cli import main

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
IMAGE = "docs/images/readme_before_after.png"


def readme() -> str:
    return README.read_text(encoding="utf-8")


def links(text: str) -> list[str]:
    """The targets of the Markdown links and images, without their ``#anchor``."""
    return [t.split("#", 1)[0] for t in re.findall(r"\]\(([^)\s]+)\)", text)]


def test_readme_is_a_front_page():
    assert len(readme().splitlines()) <= 200
    # make demo and make test stay the README's first two commands
    commands = re.findall(r"```bash\n(.*?)```", readme(), flags=re.S)
    first = [ln.split("#")[0].strip() for ln in commands[0].splitlines()][:2]
    assert first == ["make demo", "make test"]


def test_every_readme_link_into_the_repository_resolves():
    local = [t for t in links(readme()) if t and not re.match(r"[a-z]+:", t)]
    assert any(t.startswith("docs/guide/") for t in local)
    missing = [t for t in local if not (REPO / t).exists()]
    assert missing == []


def test_every_manual_page_the_readme_names_is_in_the_manual():
    index = (REPO / "docs" / "index.md").read_text(encoding="utf-8")
    pages = {t for t in links(readme()) if t.startswith("docs/guide/") and t.endswith(".md")}
    assert len(pages) >= 12
    for page in pages:
        assert page.removeprefix("docs/").removesuffix(".md") in index, page


def test_the_plugin_readme_points_to_the_manual():
    text = (REPO / "plugin" / "README.md").read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 12
    assert all((REPO / "plugin" / t).resolve().exists() for t in links(text) if "://" not in t)
    assert "docs/guide/paraview.md" in text


def readme_image_command() -> list[str]:
    """The command the README states beside its image (the one ``make readme-image`` runs)."""
    text = readme()
    assert f"]({IMAGE})" in text
    after = text.split(f"]({IMAGE})", 1)[1][:600]
    command = re.search(r"`(dvr-perception optimize [^`]+)`", after.replace("\n", " "))
    assert command, "the README names the command that makes its image"
    return shlex.split(command.group(1))


def test_the_readme_image_is_made_by_the_make_target_it_names():
    argv = readme_image_command()
    makefile = (REPO / "Makefile").read_text(encoding="utf-8")
    recipe = makefile.split("\nreadme-image:", 1)[1].split("\n\n", 1)[0]
    args = re.search(r"README_IMAGE_ARGS \?= (.*)", makefile).group(1).split()
    assert argv[:2] == ["dvr-perception", "optimize"]
    assert argv[2].endswith("/cthead.nhdr")
    assert "$(DATA)/cthead.nhdr" in recipe
    assert " ".join(args) in " ".join(argv)  # --size 384
    assert f"before_after.png {IMAGE}" in recipe
    assert (REPO / IMAGE).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.slow
@pytest.mark.shared_data
def test_the_readme_image_command_runs(shared_data, tmp_path):
    """The README's command, at a small size, writes the before/after figure it shows."""
    argv = readme_image_command()[1:]
    argv[1] = str(shared_data / "cthead.nhdr")
    argv[argv.index("--size") + 1] = "48"
    argv[argv.index("--out") + 1] = str(tmp_path / "out")
    assert main([*argv, "--max-iter", "2"]) == 0
    png = (tmp_path / "out" / "before_after.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    width, height = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
    assert width > 1.5 * height  # two panels side by side


#: The sections of the README before it became a front page (issue 33), and the manual page
#: that holds each now.
FORMER_README_SECTIONS = {
    "Quick start": "getting_started.md",
    "Install and Python API": "getting_started.md",
    "Running against the shared data": "getting_started.md",
    "Command line": "cli.md",
    "Structure spec": "spec.md",
    "Presets and proposed structures": "spec.md",
    "3D Slicer segmentations (`.seg.nrrd`)": "spec.md",
    "Volume formats and patient orientation": "volumes.md",
    "Conventions": "volumes.md",
    "Large volumes: bricks and `--memory-limit`": "large_volumes.md",
    'GPU back end (`backend="cuda"`)': "gpu.md",
    "Measures": "measures.md",
    "Optimisation": "optimisation.md",
    "PyVista display": "pyvista.md",
    "ParaView plugin": "paraview.md",
    "The DVR Perception toolbar: Apply changes the volume you see": "paraview.md",
    "Web app": "webapp.md",
    "Security": "security.md",
    "Files and limits": "security.md",
    "What works, and what is not done": "status.md",
    "Measured figures": "figures.md",
    "Benchmark report": "benchmarks.md",
}


def test_the_former_readme_sections_are_in_the_manual():
    guide = REPO / "docs" / "guide"
    for heading, page in FORMER_README_SECTIONS.items():
        headings = re.findall(r"^#+ (.*)$", (guide / page).read_text(encoding="utf-8"), re.M)
        assert heading in headings, (heading, page)


def figures_extension():
    """The manual's ``dvr-figures`` extension (``docs/_ext/figures.py``; needs the docs extra)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("figures", REPO / "docs" / "_ext" / "figures.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_figure_tables_are_read_from_the_measured_json(tmp_path):
    import json

    figures = figures_extension()
    acceptance = {
        "engine": {
            "initial": {"E": 1.0, "E_v": 0.5, "E_s": 0.4, "E_t": 0.1, "coverage": 0.9},
            "final": {"E": 0.75, "E_v": 0.25, "E_s": 0.4, "E_t": 0.1, "coverage": 0.8},
            "seconds": 12.0,
            "vtk_frames": 30.0,
            "status": "converged",
            "structures": {},
        }
    }
    path = tmp_path / "acceptance.json"
    path.write_text(json.dumps(acceptance), encoding="utf-8")
    head, rows = figures.optimiser([path])
    assert head[:3] == ["volume", "E", "E_v"]
    assert rows == [["engine", "1.000 → 0.750", "0.500 → 0.250 (-50 %)", "0.400 → 0.400",
                     "0.100 → 0.100", "0.900 → 0.800", "12.0", "30.0", "converged"]]  # fmt: skip
    # every table of the manual reads its committed file, one row per measured item at least
    page = (REPO / "docs" / "guide" / "figures.md").read_text(encoding="utf-8")
    uses = re.findall(r"```\{dvr-figures\} (\S+)\n:file: (\S+)", page)
    assert {kind for kind, _ in uses} == set(figures.RENDERERS)
    for kind, pattern in uses:
        files = sorted(REPO.glob(pattern))
        assert files, pattern
        head, rows = figures.RENDERERS[kind](files)
        assert rows, kind
        assert all(len(r) == len(head) for r in rows), kind
