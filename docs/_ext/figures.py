"""Sphinx directive ``dvr-figures``: tables of measured figures read from committed JSON files.

No figure in the manual is typed by hand: each table is rendered at build time from the JSON
file the measuring command wrote (the page names that command next to the table), so
rerunning the command and rebuilding the manual updates the table.  Usage (MyST)::

    ```{dvr-figures} optimiser
    :file: benchmarks/optimizer_acceptance.json
    ```

The argument names a renderer of :data:`RENDERERS`; ``:file:`` is relative to the repository
root (a glob for renderers that read several files, e.g. ``benchmarks/bench/*.json``).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import ClassVar

from docutils import nodes
from docutils.parsers.rst import Directive, directives
from sphinx.util import logging

REPO = Path(__file__).resolve().parents[2]
LOG = logging.getLogger(__name__)

Rows = tuple[list[str], list[list[str]]]


def _f(x, digits: int = 3) -> str:
    """Format a number (``-`` for a missing one)."""
    if x is None:
        return "-"
    if isinstance(x, bool):
        return "yes" if x else "no"
    if isinstance(x, int):
        return str(x)
    return f"{x:.{digits}f}"


def _arrow(before, after, digits: int = 3) -> str:
    return f"{_f(before, digits)} → {_f(after, digits)}"


def _dims(d: Iterable[int]) -> str:
    return "\N{MULTIPLICATION SIGN}".join(str(int(v)) for v in d)


def optimiser(files: list[Path]) -> Rows:
    """``python -m dvr_perception.optimize.acceptance --out DIR``'s ``acceptance.json``."""
    data = json.loads(files[0].read_text(encoding="utf-8"))
    head = ["volume", "E", "E_v", "E_s", "E_t", "coverage", "seconds", "VTK frames", "status"]
    rows = []
    for name, r in data.items():
        i, f = r["initial"], r["final"]
        ev = f"{_arrow(i['E_v'], f['E_v'])} ({(f['E_v'] / i['E_v'] - 1) * 100:+.0f} %)"
        rows.append([name, _arrow(i["E"], f["E"]), ev, _arrow(i["E_s"], f["E_s"]),
                     _arrow(i["E_t"], f["E_t"]), _arrow(i["coverage"], f["coverage"]),
                     _f(r.get("seconds"), 1), _f(r.get("vtk_frames"), 1),
                     str(r.get("status", ""))])  # fmt: skip
    return head, rows


def optimiser_shares(files: list[Path]) -> Rows:
    """Per structure of ``acceptance.json``: opacity and share of the picture, and why."""
    data = json.loads(files[0].read_text(encoding="utf-8"))
    head = ["volume", "structure", "opacity", "share of the picture", "target", "reason"]
    rows = []
    for name, r in data.items():
        for s, v in r["structures"].items():
            rows.append([name, s, _arrow(v["opacity_before"], v["opacity_after"], 2),
                         f"{v['share_before']:.0%} → {v['share_after']:.0%}",
                         f"{v['target_share']:.0%}", v.get("reason", "")])  # fmt: skip
    return head, rows


_BENCH_KEYS = ("frame_s", "vtk_frame_s", "frame_ratio", "frame_cache_ratio", "render_ratio",
               "reeval_vtk_frames", "measure_s", "measure_total_s",
               "measure_vtk_frames")  # fmt: skip


def bench(files: list[Path]) -> Rows:
    """``dvr-perception bench VOLUME --json`` outputs, one row per file."""
    head = ["volume", "size", *[f"`{k}`" for k in _BENCH_KEYS], "file"]
    rows = []
    for p in files:
        r = json.loads(p.read_text(encoding="utf-8"))
        size = r.get("size")
        rows.append([f"{p.stem} {_dims(r['dims'])}" if "dims" in r else p.stem,
                     _dims(size) if isinstance(size, list) else str(size),
                     *[_f(r.get(k)) for k in _BENCH_KEYS],
                     Path(str(r.get("volume", ""))).name])  # fmt: skip
    return head, rows


def scale(files: list[Path]) -> Rows:
    """``make scale``'s ``benchmarks/scale.json``: time and memory against volume size."""
    data = json.loads(files[0].read_text(encoding="utf-8"))
    head = ["volume", "dims", "frame s", "frame ratio", "render ratio", "optimise s",
            "optimise VTK frames", "peak RSS MB", "optimize end to end s",
            "its peak MB"]  # fmt: skip
    rows = [[r["label"], _dims(r["dims"]), _f(r.get("frame_s")), _f(r.get("frame_ratio"), 2),
             _f(r.get("render_ratio"), 2), _f(r.get("optimize_s"), 1),
             _f(r.get("optimize_vtk_frames"), 1), _f(r.get("peak_rss_mb"), 0),
             _f(r.get("optimize_e2e_s"), 1), _f(r.get("optimize_e2e_peak_rss_mb"), 0)]
            for r in data["sizes"]]  # fmt: skip
    return head, rows


def scale_ranks(files: list[Path]) -> Rows:
    """Tabulate the MPI runs of ``benchmarks/scale.json``: E terms and memory per rank."""
    data = json.loads(files[0].read_text(encoding="utf-8"))
    head = ["ranks", "volume", "wall s", "E_v", "E_s", "E_t", "voxels per rank",
            "peak RSS MB per rank"]  # fmt: skip
    rows = []
    for r in data.get("ranks") or []:
        per = r.get("per_rank") or []
        rows.append([str(r["ranks"]), r["volume"], _f(r.get("wall_s"), 1),
                     *[_f(r["E"].get(k), 4) for k in ("E_v", "E_s", "E_t")],
                     " / ".join(str(q["voxels"]) for q in per) or "-",
                     " / ".join(_f(q.get("peak_rss_mb"), 0) for q in per) or "-"])  # fmt: skip
    return head, rows


def cuda(files: list[Path]) -> Rows:
    """``python -m benchmarks.cuda_check --out FILE``: seconds per step, cuda and numba."""
    head = ["volume", "dims", "image", "step", "cuda s", "numba s", "numba / cuda", "equal"]
    rows = []
    for p in files:
        data = json.loads(p.read_text(encoding="utf-8"))
        for name, fr in data["frames"].items():
            eq = data.get("equal", {}).get(name, {}).get("passed")
            cu, nb = fr.get("cuda", {}), fr.get("numba", {})
            for step in ("frame", "measure", "measure_new_camera", "render"):
                c, n = cu.get(step), nb.get(step)
                ratio = _f(n / c, 1) if c and n else "-"
                rows.append([name, _dims(fr["dims"]), _dims(fr["size"]), step, _f(c, 4),
                             _f(n, 4), ratio, _f(eq)])  # fmt: skip
        for key, run in data.items():
            if key.startswith("optimize_"):
                cu, nb = run.get("cuda", {}), run.get("numba", {})
                c, n = cu.get("seconds"), nb.get("seconds")
                same = cu.get("E_final") == nb.get("E_final") if cu and nb else None
                rows.append([key.removeprefix("optimize_"), "", "", "whole optimisation",
                             _f(c, 2), _f(n, 2), _f(n / c, 2) if c and n else "-",
                             _f(same)])  # fmt: skip
    return head, rows


def threads(files: list[Path]) -> Rows:
    """``python -m benchmarks.thread_scaling``: seconds against numba threads."""
    data = json.loads(files[0].read_text(encoding="utf-8"))
    head = ["threads", "frame s", "measure s", "render s"]
    rows = [[k, _f(v["frame"]), _f(v["measure"]), _f(v["render"])]
            for k, v in sorted(data["threads"].items(), key=lambda kv: int(kv[0]))]  # fmt: skip
    return head, rows


def renderer(files: list[Path]) -> Rows:
    """``make renderer-figures``: SSIM of our image against VTK's and the PyVista display."""
    runs = [json.loads(line) for line in files[0].read_text(encoding="utf-8").splitlines()
            if line.strip()]  # fmt: skip
    modes = {"--no-shade": "vs VTK CPU mapper, unshaded", "--shade": "shaded",
             "--against plotter": "PyVista display (per-structure lighting)"}  # fmt: skip
    table: dict[tuple[str, str], dict[str, str]] = {}
    for run in runs:
        r = run["result"]
        key = (Path(str(r["volume"])).stem, f"{run['view'].replace(',', '/')}")
        table.setdefault(key, {})[run["mode"]] = _f(r.get("ssim"), 3)
    head = ["volume", "view az/el", *modes.values()]
    rows = [[v, view, *[cells.get(m, "-") for m in modes]] for (v, view), cells in table.items()]
    return head, rows


def report_checks(files: list[Path]) -> Rows:
    """Tabulate the acceptance checks of ``dvr-perception report``'s ``summary.json``."""
    data = json.loads(files[0].read_text(encoding="utf-8"))
    head = ["check", "passed", "detail"]
    return head, [[c["name"], _f(c["passed"]), c.get("detail", "")] for c in data["checks"]]


RENDERERS: dict[str, Callable[[list[Path]], Rows]] = {
    "optimiser": optimiser,
    "optimiser-shares": optimiser_shares,
    "bench": bench,
    "scale": scale,
    "scale-ranks": scale_ranks,
    "cuda": cuda,
    "threads": threads,
    "report-checks": report_checks,
    "renderer": renderer,
}


def _table(head: list[str], rows: list[list[str]]) -> nodes.table:
    table = nodes.table(classes=["dvr-figures"])
    group = nodes.tgroup(cols=len(head))
    table += group
    group.extend(nodes.colspec(colwidth=1) for _ in head)

    def row(cells, header=False):
        r = nodes.row()
        for c in cells:
            entry = nodes.entry()
            text = str(c)
            if text.startswith("`") and text.endswith("`"):
                entry += nodes.paragraph("", "", nodes.literal(text=text.strip("`")))
            else:
                entry += nodes.paragraph(text=text)
            r += entry
        return r

    thead = nodes.thead()
    thead += row(head, header=True)
    tbody = nodes.tbody()
    tbody.extend(row(r) for r in rows)
    group += thead
    group += tbody
    return table


class FiguresDirective(Directive):
    """``dvr-figures KIND`` with ``:file: PATH-OR-GLOB``: a table read from measured JSON."""

    required_arguments = 1
    option_spec: ClassVar[dict] = {"file": directives.unchanged_required}
    has_content = False

    def run(self):
        """Read the files and return the table and a line naming them."""
        kind = self.arguments[0]
        pattern = self.options.get("file", "")
        env = self.state.document.settings.env
        if kind not in RENDERERS:
            raise self.error(f"dvr-figures: unknown kind {kind!r} (one of {sorted(RENDERERS)})")
        files = sorted(REPO.glob(pattern))
        if not files:
            raise self.error(f"dvr-figures: no file matches {pattern!r}")
        for p in files:
            env.note_dependency(str(p))
        try:
            head, rows = RENDERERS[kind](files)
        except (KeyError, ValueError, TypeError) as exc:
            raise self.error(f"dvr-figures {kind}: cannot read {pattern}: {exc!r}") from exc
        caption = nodes.paragraph(classes=["dvr-figures-source"])
        caption += nodes.Text("Read at build time from ")
        caption += nodes.literal(text=", ".join(str(p.relative_to(REPO)) for p in files))
        caption += nodes.Text(".")
        return [_table(head, rows), caption]


def setup(app):
    """Register the ``dvr-figures`` directive."""
    app.add_directive("dvr-figures", FiguresDirective)
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
