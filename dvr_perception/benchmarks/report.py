"""Regenerate the benchmark report: ``REPORT.md``, ``summary.json`` and ``images/``.

Run from the repository root (the report goes into its ``benchmarks/`` folder)::

    dvr-perception report --data ../shared/data --out benchmarks            # 512² (minutes)
    dvr-perception report --data ../shared/data --out /tmp/r --quick        # CI form, 128²
    python -m dvr_perception.benchmarks.report --data ../shared/data --out benchmarks

The experiments are those of the paper's Sec. 7
(:mod:`~dvr_perception.benchmarks.experiments`).  The acceptance checks
(:mod:`~dvr_perception.benchmarks.checks`) are computed from the measured numbers and
recorded in ``summary.json`` under ``"checks"``; nothing is hard-coded.  The hand-written
observations of the images (``benchmarks/observations.md`` in the package, one ``### key``
section per
experiment) are inserted verbatim: they describe the images of the last full run someone
looked at, and say so.
"""
# ruff: noqa: RUF001  (the report text uses ×, α, – and → on purpose)

from __future__ import annotations

import argparse
import os
import platform
import re
import sys
import time
from dataclasses import asdict
from datetime import datetime, timezone
from pathlib import Path

from dvr_perception._files import atomic_path, write_json
from dvr_perception.benchmarks import checks, experiments, figures
from dvr_perception.benchmarks.experiments import Config

__all__ = ["PAPER", "build", "main", "render_markdown", "rerender"]

HERE = Path(__file__).resolve().parent
OBSERVATIONS = HERE / "observations.md"

#: The paper's own figures (Sec. 7), quoted.
PAPER = {
    "hardware": "Pentium Core2Duo 6400, 2 GB RAM, NVIDIA GeForce 7600GTS",
    "iteration_s": 0.2,
    "total_s": 10.0,
    "size": 512,
    "chest_dims": "384×384×240",
    "iterations_per_step": "usually converge within 10 iterations in each step",
}


def _machine() -> dict:
    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        import vtk

        vtk_version = vtk.vtkVersion.GetVTKVersion()
    except Exception:  # VTK version is decoration only
        vtk_version = "?"
    import numba

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "numba_threads": int(numba.get_num_threads()),
        "python": platform.python_version(),
        "vtk": vtk_version,
    }


def _code_version() -> str:
    """``git`` commit of the checkout the package runs from, and whether it has local changes."""
    import subprocess

    import dvr_perception

    root = Path(dvr_perception.__file__).resolve().parents[1]
    try:
        head = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout
        dirty = subprocess.run(
            ["git", "-C", str(root), "status", "--porcelain", "--", "dvr_perception"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return f"package at {root} (not a git checkout)"
    return f"git {head.strip()}" + (
        " with uncommitted changes in dvr_perception/" if dirty.strip() else ""
    )


def _plain(obj):
    """Drop ``_images`` and turn specs into their JSON dicts (for ``summary.json``)."""
    from dvr_perception.structures.io import spec_to_dict
    from dvr_perception.structures.spec import StructureSpec

    if isinstance(obj, StructureSpec):
        return spec_to_dict(obj)
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items() if not str(k).startswith("_")}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    return obj


def _log(msg: str) -> None:
    print(f"report: {msg}", file=sys.stderr, flush=True)


def build(cfg: Config, out, *, log=_log, final=None) -> dict:
    """Run every experiment, write the figures, ``summary.json`` and ``REPORT.md`` into ``out``.

    ``final``: the folder the files end up in when ``out`` is a staging folder (its
    ``scale.json`` goes into the report).  Returns the summary (what ``summary.json`` holds).
    """
    out = Path(out)
    images = out / "images"
    images.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    timings, results = {}, {}

    def step(key, fn, *args):
        log(f"{key} ...")
        t0 = time.perf_counter()
        value = fn(*args)
        timings[key] = time.perf_counter() - t0
        log(f"{key}: {timings[key]:.1f} s")
        results[key] = value
        return value

    eq_cthead = step("equalisation_cthead", experiments.run_equalisation, cfg, "cthead")
    eq_engine = step("equalisation_engine", experiments.run_equalisation, cfg, "engine")
    start = eq_cthead["runs"][0]["result_spec"]  # skin/bone at 0.2/0.8, equalised
    shp = step("shape_cthead", experiments.run_shape, cfg, start)
    sat = step("saturation_neghip", experiments.run_saturation, cfg)
    objectives = step("objectives", experiments.run_objectives, cfg)
    pipes = [objectives["runs"][n][objectives["default"]] for n in ("engine", "lidc_chest")]
    perf = step("performance", experiments.run_performance, cfg)

    log("figures ...")
    files = {
        "equalisation_cthead": figures.equalisation_figure(
            images / "equalisation_cthead.png", eq_cthead
        ),
        "equalisation_engine": figures.equalisation_figure(
            images / "equalisation_engine.png", eq_engine
        ),
        "equalisation_shares": figures.shares_figure(
            images / "equalisation_shares.png", [eq_cthead, eq_engine]
        ),
        "shape_cthead": figures.shape_figure(images / "shape_cthead.png", shp),
        "objectives": figures.objectives_figure(images / "objectives.png", objectives),
        "saturation_neghip": figures.saturation_figure(images / "saturation_neghip.png", sat),
        "performance": figures.performance_figure(images / "performance.png", perf),
    }
    for p in pipes:
        key = f"pipeline_{p['dataset']}"
        files[key] = figures.pipeline_figure(images / f"{key}.png", p)

    all_checks = [c for r in (eq_cthead, eq_engine, shp, sat, *pipes) for c in r["checks"]]
    summary = {
        "command": "dvr-perception report --data DATA --out OUT"
        + (f" --size {cfg.size}" if cfg.size != 512 else "")
        + (" --quick" if cfg.quick else ""),
        "generated_utc": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "config": {**asdict(cfg), "data": str(cfg.data)},
        "machine": _machine(),
        "code": _code_version(),
        "seconds": time.perf_counter() - t_start,
        "experiment_seconds": timings,
        "all_passed": checks.all_passed(all_checks),
        "checks": all_checks,
        "paper": PAPER,
        "images": {k: os.path.relpath(v, out) for k, v in files.items()},
        "equalisation": [_plain(eq_cthead), _plain(eq_engine)],
        "shape": _plain(shp),
        "saturation": _plain(sat),
        "pipeline": [_plain(p) for p in pipes],
        "objectives": _objectives_table(objectives),
        "performance": perf,
    }
    write_json(out / "summary.json", summary)
    scale_dir = out if final is None else final  # a staged run: scale.json is in the folder
    text = render_markdown(_with_scale(summary, scale_dir), read_observations())
    with atomic_path(out / "REPORT.md") as tmp:
        tmp.write_text(text, encoding="utf-8")
    log(f"wrote {out / 'REPORT.md'} ({summary['seconds']:.0f} s)")
    return summary


def _objectives_table(comparison: dict) -> dict:
    """Return the objective comparison for ``summary.json``.

    Per dataset and objective: the terms and shares of the original and final image, the
    stages' messages, the opacities found and the time.
    """
    out = {"default": comparison["default"], "runs": {}}
    for name, by in comparison["runs"].items():
        out["runs"][name] = {
            obj: {
                "original": _plain(p["steps"][0]),
                "final": _plain(p["steps"][-1]),
                "stages": [
                    {k: st[k] for k in ("name", "accepted", "message", "iterations")}
                    for st in p["stages"]
                ],
                "opacity": {s.name: float(s.render_opacity) for s in p["final_spec"].structures},
                "seconds": p["seconds"],
            }
            for obj, p in by.items()
        }
    return out


def rerender(out) -> Path:
    """Rewrite ``out/REPORT.md`` from ``out/summary.json`` and the current observations."""
    import json

    out = Path(out)
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    with atomic_path(out / "REPORT.md") as tmp:
        tmp.write_text(render_markdown(_with_scale(summary, out), read_observations()),
                       encoding="utf-8")  # fmt: skip
    return out / "REPORT.md"


def _with_scale(summary: dict, out: Path) -> dict:
    """``summary`` with ``out/scale.json`` (``python -m benchmarks.scale``) when there is one."""
    import json

    path = Path(out) / "scale.json"
    if not path.is_file():
        return summary
    return {**summary, "scale": json.loads(path.read_text(encoding="utf-8"))}


def read_observations(path=OBSERVATIONS) -> dict:
    """``{key: text}`` from the ``### key`` sections of the hand-written observations file."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError:
        return {}
    parts = re.split(r"^### +(\S+)\s*$", text, flags=re.M)
    return {parts[i]: parts[i + 1].strip() for i in range(1, len(parts) - 1, 2)}


# -- Markdown -----------------------------------------------------------------------------------
def _f(v, nd=3) -> str:
    if v is None:
        return "–"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def _s(v) -> str:
    """Seconds, with a sensible number of digits."""
    if v is None:
        return "–"
    return f"{v:.3f}" if v < 1 else f"{v:.2f}" if v < 10 else f"{v:.1f}"


def _table(header, rows) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return [*lines, ""]


def _observed(obs: dict, key: str) -> list[str]:
    text = obs.get(key)
    if not text:
        return ["*No hand-written observation for these images yet.*", ""]
    return [
        "**What the images show** (written by hand after looking at the images of the "
        "full run; `benchmarks/observations.md`):",
        "",
        text,
        "",
    ]


def _shares(run, key) -> str:
    share = run[key]["visible_share"]
    tot = sum(share.values()) or 1.0
    return " / ".join(f"{v / tot:.2f}" for v in share.values())


def _norm(comp) -> str:
    if not comp:
        return "–"
    tot = sum(comp.values()) or 1.0
    return " / ".join(f"{v / tot:.2f}" for v in comp.values())


def _comp(run) -> str:
    return _norm(run["composition"])


def _paper_rows(s: dict) -> list[list[str]]:
    eq = {e["dataset"]: e for e in s["equalisation"]}
    c = eq["cthead"]["runs"][0]
    rows = [
        [
            "Fig. 7 visibility equalisation, importance 0.2/0.8",
            "carp 256×256×512, skin/bone: overall deviation lowered, bones revealed "
            "according to the importance ratio (no numbers given)",
            f"cthead skin/bone: E_v {c['before']['E_v']:.3f} → {c['after']['E_v']:.3f}; "
            f"visible shares {_shares(c, 'before')} → {_shares(c, 'after')} (target shares, "
            f"importance × presence, {_comp(c)}); engine block/inserts: E_v "
            f"{eq['engine']['runs'][0]['before']['E_v']:.3f} → "
            f"{eq['engine']['runs'][0]['after']['E_v']:.3f}",
            "carp unavailable. The shares move toward the target shares of D1 (importance × "
            "presence per ray, times A_imp): the bare ratio only where both structures lie "
            "on the same rays",
        ]
    ]
    shp = s["shape"]
    la = shp["lighting_after"]
    rows.append(
        [
            "Fig. 8 shape enhancement (lighting)",
            "CT head 128×128×231: shape-measure value reduced; large specular highlight "
            "(small exponent) found for the large smooth skin",
            f"cthead 256×256×113: E_s {shp['before']['E_s']:.3f} → {shp['after']['E_s']:.3f};"
            " specular power "
            + ", ".join(f"{n} {v['specular_power']:.0f}" for n, v in la.items())
            + "; specular "
            + ", ".join(f"{n} {v['specular']:.2f}" for n, v in la.items()),
            "different CT head; the stage keeps the lit side facing the viewer and a brightness "
            "guard (see notes)",
        ]
    )
    sat = s["saturation"]
    for key, what, prefix in (
        ("outer_tap", "TAP transparency (Fig. 9 reading)", "saturation series, TAP"),
        ("outer_transparency", "E_t measure's α_t (Eq. 8)", "saturation series ("),
    ):
        series = ", ".join(f"{p['saturation_percent']} %: {_f(p.get(key))}" for p in sat["series"])
        mono = next((ch for ch in sat["checks"] if ch["name"].startswith(prefix)), None)
        if mono is None:  # a summary written before this check existed
            continue
        rows.append(
            [
                "Fig. 9 outer-layer saturation 100/75/50/25 %",
                "neghip 64³: perceived transparency of the outer layer decreased with the "
                "saturation (inner structures less visible), derived 'based on the TAP'",
                f"neghip: {what} of '{sat['outer']}' {series}",
                "agrees (monotone)" if mono["passed"] else f"does not agree: {mono['detail']}",
            ]
        )
    paper_pipeline = {
        "engine": (
            "Fig. 10",
            "engine 256×256×128: interior and exterior visibility balanced, semi-transparent "
            "layers, features better preserved after lighting (no numbers given)",
        ),
        "lidc_chest": (
            "Fig. 11",
            "CT chest 384×384×240: structures more distinguishable, details better preserved "
            "(no numbers given)",
        ),
    }
    for p in s["pipeline"]:
        st = p["steps"]
        fig, claim = paper_pipeline.get(p["dataset"], ("–", "–"))
        rows.append(
            [
                f"{fig} full pipeline, {p['dataset']}",
                claim,
                " → ".join(f"({x['E_v']:.3f}, {x['E_s']:.3f}, {x['E_t']:.3f})" for x in st)
                + " as (E_v, E_s, E_t) per stage",
                "lidc_chest 256×256×133 stands in for the CT chest"
                if p["dataset"] == "lidc_chest"
                else "same dataset as the paper",
            ]
        )
    perf = s["performance"]["image_size"]
    chest = perf.get("lidc_chest", [])
    if chest:
        big = chest[-1]
        per_it = max(st["seconds_per_iteration"] for st in big["stages"])
        its = sum(st["iterations"] for st in big["stages"])
        rows += [
            [
                f"time per iteration, chest, {big['size'][0]}²",
                f"0.2 s ({PAPER['chest_dims']}, 512², GPU)",
                f"{_s(per_it)} s (slowest stage; lidc_chest {'×'.join(map(str, big['dims']))}, "
                "CPU)",
                "our iterations evaluate at the optimiser's 96-px resolution (image sampling)",
            ],
            [
                f"whole optimisation, chest, {big['size'][0]}²",
                "10 s",
                f"{_s(big['optimize_s'])} s ({its} iterations; ray analysis at full size "
                "included, curvature volume excluded)",
                "",
            ],
        ]
    for p in s["performance"].get("full_resolution", {}).get("lidc_chest", []):
        if p["size"][0] != s["config"]["size"]:
            continue
        per_it = max(st["seconds_per_iteration"] for st in p["stages"])
        rows.append(
            [
                f"same, without image sampling (every evaluation at {p['size'][0]}²)",
                "0.2 s per iteration, 10 s in all",
                f"{_s(per_it)} s per iteration (slowest stage), {_s(p['optimize_s'])} s in all "
                f"({p['iterations']} iterations)",
                "CPU, no GPU; numba ray re-compositing and the three measures per evaluation",
            ]
        )
    pipes = s["pipeline"]
    conv = ", ".join(
        f"{p['dataset']} {st['name']} {'yes' if st['converged'] else 'no'} ({st['iterations']} it.)"
        for p in pipes
        for st in p["stages"]
    )
    rows.append(
        [
            "iterations per stage",
            PAPER["iterations_per_step"],
            f"max_iter 5 per stage (default); converged: {conv}",
            "",
        ]
    )
    rows.append(
        [
            "hardware",
            PAPER["hardware"],
            f"{s['machine']['cpu']}, "
            f"{s['machine']['cores']} cores, no GPU (shared with other jobs)",
            "",
        ]
    )
    return rows


def _mb(v) -> str:
    return "–" if v is None else f"{v:,.0f}"


def _scale_section(scale: dict | None, obs: dict) -> list[str]:
    """Time and memory against volume size, and MPI ranks (``scale.json``, issue 17)."""
    if not scale:
        return []
    n = scale["size"]
    L = ["### 5b. Real-size volumes and MPI ranks", ""]
    L += [
        f"`python -m benchmarks.scale` ({scale['when']}, {scale['cpus']} cores, image {n}²; "
        "each figure from its own process, peak RSS of that process). cthead at every other "
        "voxel, as stored and up-sampled; volumes above 64 M voxels are analysed in bricks "
        "(`--memory-limit`, default half the RAM). `bench`: one frame of ours (full "
        "analysis) and of VTK's CPU ray caster, the curvature, one default optimisation; "
        "`optimize`: the whole command with its figures.",
        "",
    ]
    rows = [
        [r["label"], "×".join(map(str, r.get("dims", []))), _f((r.get("voxels") or 0) / 1e6, 1),
         _s(r.get("curvature_s")), _f(r.get("curvature_vtk_frames"), 1), _s(r.get("frame_s")),
         _s(r.get("vtk_frame_s")), _s(r.get("optimize_s")), _f(r.get("optimize_vtk_frames"), 1),
         _mb(r.get("peak_rss_mb")), _s(r.get("optimize_e2e_s")),
         _mb(r.get("optimize_e2e_peak_rss_mb"))]
        for r in scale["sizes"]
    ]  # fmt: skip
    L += _table(["volume", "dims", "M voxels", "curvature s", "in VTK frames", "our frame s",
                 "VTK frame s", "optimise s", "in VTK frames", "bench peak MB",
                 "`optimize` s", "`optimize` peak MB"], rows)  # fmt: skip
    rows = []
    whole = {r["volume"]: r.get("voxels") for r in scale["sizes"]}
    for r in scale.get("ranks", []):
        per = r.get("per_rank", [])
        share = [p["voxels"] for p in per]
        total = whole.get(r["volume"]) or max(sum(share), 1)
        rows.append([
            r["ranks"], _s(r["wall_s"]),
            " / ".join(f"{100 * v / total:.0f} %" for v in share) if share else "–",
            " / ".join(_mb(p.get("peak_rss_mb")) for p in per) if per else "–",
            " ".join(f"{k} {v:.5f}" for k, v in (r.get("E") or {}).items() if v is not None)
            or r.get("error", "")[-120:],
        ])  # fmt: skip
    if rows:
        name = scale["ranks"][0]["volume"]
        L += [f"**MPI ranks** (`dvr-perception pvbatch --ranks N` on {name}; a rank's voxels, "
              "ghost layers included, against the whole volume's)", ""]  # fmt: skip
        L += _table(["ranks", "wall s", "voxels per rank", "peak MB per rank", "E terms"], rows)
    L += _observed(obs, "scale")
    return L


def render_markdown(s: dict, obs: dict | None = None) -> str:
    """Return the report text of a summary (and the hand-written observations)."""
    obs = obs or {}
    cfg = s["config"]
    n = cfg["size"]
    L = [
        "# Benchmark report: the paper's experiments on real data",
        "",
        f"Generated {s['generated_utc']} by `{s['command']}` in {s['seconds']:.0f} s "
        f"({'reduced CI form' if cfg['quick'] else 'full form'}, {n}×{n} images, seed "
        f"{cfg['seed']}). Machine: {s['machine']['cpu']}, {s['machine']['cores']} cores "
        f"(numba threads {s['machine']['numba_threads']}), VTK {s['machine']['vtk']}, "
        f"Python {s['machine']['python']}; code: {s.get('code', '?')}. Everything below "
        "(numbers, tables, images) is "
        'regenerated by that command; only the "What the images show" paragraphs are '
        "written by hand (`dvr_perception/benchmarks/observations.md`).",
        "",
        "Terms are measured at the image size above on a fresh rendering with the public "
        "measures (`dvr_perception.measures`); lower is better. E_v in [0, 2], E_s in [0, 1), "
        "E_t ≥ 0.",
        "",
        "## Checks",
        "",
        f"All passed: **{'yes' if s['all_passed'] else 'no'}** "
        f"({sum(c['passed'] for c in s['checks'])} of {len(s['checks'])}).",
        "",
    ]
    L += _table(
        ["check", "result", "numbers"],
        [[c["name"], "pass" if c["passed"] else "**FAIL**", c["detail"]] for c in s["checks"]],
    )
    L += ["## The paper's numbers and ours", ""]
    L += _table(["experiment", "paper", "ours", "note"], _paper_rows(s))
    L += _observed(obs, "paper")

    # 1. equalisation
    L += ["## 1. Visibility equalisation (paper Fig. 7)", ""]
    L += [
        "The carp is not available; the cthead skin/bone pair and the engine's block "
        "(90–180) / inserts (190–255) stand in. Only the opacity stage runs, without a "
        "coverage floor (decision D1: fading raises E_v by itself), once under each target "
        "composition of E_v: **importance** (importance × presence, the default; the checks "
        "are on it) and **thickness** (assigned / Σ assigned, the paper-literal reading). Per "
        "ratio: the rendering before (the original: both structures at opacity "
        f"{s['equalisation'][0].get('start_opacity', 'importance')}, the inner one occluded, "
        "one original for every ratio as in the paper's figure; under D1 the target is the "
        "composition of the rendering at the importances, so starting there starts at the "
        "optimum), after under each composition, "
        "and the visibility deviation δ_v (importance target; grey: empty rays).",
        "",
        "*Target share* is the image-wide share of each structure in the target opacity "
        "α_o = c · A_imp (Σ_r α_o(s, r) over the structures' sum, decision D6): it is what "
        "the visibility measure aims the visible opacity at, ray by ray, and the target of the "
        "check. Shares are written outer / inner; E_v and the shares after are each under "
        "their own composition.",
        "",
    ]
    for e in s["equalisation"]:
        rows = []
        for r in e["runs"]:
            t = r.get("thickness")
            rows.append(
                [
                    " / ".join(f"{v:g}" for v in r["importance"].values()),
                    _comp(r),
                    _norm(r.get("thickness_composition")),
                    " / ".join(f"{v:.3f}" for v in r["opacity_found"].values()),
                    _shares(r, "before"),
                    _shares(r, "after"),
                    "–" if t is None else _shares(t, "after"),
                    f"{r['before']['E_v']:.3f} → {r['after']['E_v']:.3f}",
                    "–" if t is None else f"{t['before']['E_v']:.3f} → {t['after']['E_v']:.3f}",
                    f"{r['before']['coverage']:.3f} → {r['after']['coverage']:.3f}",
                    _s(r["seconds"]),
                ]
            )
        names = " / ".join(e["structures"])
        L += [f"**{e['dataset']}** ({'×'.join(map(str, e['dims']))}): {names}", ""]
        L += _table(
            [
                "importance",
                "target shares (importance)",
                "target shares (thickness)",
                "opacity found (importance)",
                "visible before",
                "after (importance)",
                "after (thickness)",
                "E_v (importance)",
                "E_v (thickness)",
                "coverage (importance)",
                "s",
            ],
            rows,
        )
        img = s["images"]["equalisation_" + e["dataset"]]
        L += [f"![{e['dataset']} equalisation]({img})", ""]
        L += _observed(obs, f"equalisation_{e['dataset']}")
    L += [
        f"![visible shares vs importance]({s['images']['equalisation_shares']})",
        "",
        "Share of the inner structure in the image-wide visible opacity before and after "
        "(under each composition), against its importance ratio and its target shares.",
        "",
    ]
    L += _observed(obs, "equalisation_shares")

    # 2. shape
    shp = s["shape"]
    L += ["## 2. Shape enhancement (paper Fig. 8)", ""]
    L += [
        "cthead skin/bone after the 0.2/0.8 equalisation above, then the lighting stage alone "
        f"with weights {tuple(shp.get('weights', (1, 1, 1)))} (shape isolated as in the paper, "
        "decision D4). "
        f"E_s {shp['before']['E_s']:.4f} → {shp['after']['E_s']:.4f} "
        f"({_s(shp['seconds'])} s). Light direction (camera coordinates) "
        f"{[round(v, 3) for v in shp['light_before']]} → "
        f"{[round(v, 3) for v in shp['light_after']]}.",
        "",
    ]
    rows = [
        [
            name,
            *(
                f"{b[k]:.2f} → {shp['lighting_after'][name][k]:.2f}"
                for k in ("ambient", "diffuse", "specular", "specular_power")
            ),
        ]
        for name, b in shp["lighting_before"].items()
    ]
    L += _table(["structure", "ambient", "diffuse", "specular", "specular power"], rows)
    L += [f"![shape]({s['images']['shape_cthead']})", ""]
    L += _observed(obs, "shape_cthead")

    # 3. saturation
    sat = s["saturation"]
    L += ["## 3. Colour and transparency (paper Fig. 9)", ""]
    L += [
        f"neghip with the outer layer '{sat['outer']}' at saturation 100/75/50/25 % (HSV "
        "saturation set to that fraction; hue and value kept; everything else as the preset). "
        'The paper: "the perceived transparency of '
        "the outer layer decreased with the saturation; thus, the overlapped inner structures "
        'became less visible", and "based on the TAP, we can derive the perceived transparency" '
        "— read here as: the outer layer's TAP transparency falls as the saturation falls "
        "(100 → 25 %). Two readings are given: **TAP** = `dvr_perception.measures."
        "covered_transmittance`, the Michelson contrast of the pixels where the outer layer "
        "covers another layer, over the contrast of the same pixels rendered without it (Eq. 7; "
        "the check of this experiment); **α_t** = the `E_t` measure's perceived transparency "
        "(`dvr_perception.measures.transparency`, area-weighted over the regions where it is "
        "determined; Eq. 8 blends Metelli with TAP there, and Metelli keeps the physical "
        "transmittance, so it need not follow the TAP).",
        "",
    ]
    names = list(sat["series"][0]["perceived_transparency"])
    rows = [
        [
            f"{p['saturation_percent']} %",
            "(" + ", ".join(f"{c:.2f}" for c in p["color"]) + ")",
            _f(p.get("outer_tap")),
            *(_f(p["perceived_transparency"][k]) for k in names),
            _f(p.get("outer_transparency_plain")),
            _f(p["E_t"], 4),
            _f(p.get("E_t_plain"), 4),
        ]
        for p in sat["series"]
    ]
    L += _table(
        [
            "saturation",
            "outer colour",
            "TAP outer",
            *(f"α_t {k}" for k in names),
            "α_t outer (plain view)",
            "E_t",
            "E_t (plain view)",
        ],
        rows,
    )
    L += [
        '**plain view** = the paper-literal reading of an enclosing layer (`enclosure="plain"`: '
        "TAP against the layer's own ring); the default (decision D7) reads an encloser against "
        "what it covers re-composited without it, counting only the contrast it transmits.",
        "",
    ]
    cs = sat["colour_stage"]
    L += [
        "Expected opacities (1 − α_t wanted): "
        + ", ".join(f"{k} {v:.2f}" for k, v in sat["expected_opacity"].items())
        + f". The colour stage alone on the preset: E_t {cs['before']['E_t']:.4f} → "
        f"{cs['after']['E_t']:.4f} ({cs['stage']['message']}); colours after: "
        + ", ".join(
            f"{k} ({', '.join(f'{c:.2f}' for c in v)})" for k, v in cs["color_after"].items()
        )
        + ".",
        "",
        f"![saturation series]({s['images']['saturation_neghip']})",
        "",
    ]
    L += _observed(obs, "saturation_neghip")

    # 4. pipeline
    L += ["## 4. Full pipeline (paper Figs. 10–11)", ""]
    L += [
        "All three stages with the presets of `state_files/` and the optimiser's defaults "
        f"(objective `{s.get('objectives', {}).get('default', 'mean')}`, no coverage floor). "
        "Terms after each stage, measured "
        "at the image size (the stage records of the optimiser are at its 96-px optimisation "
        "resolution and are not used here). A stage undone by the optimiser's final check "
        "changes nothing.",
        "",
    ]
    for p in s["pipeline"]:
        rows = [
            [
                st["label"],
                f"{st['E_v']:.4f}",
                f"{st['E_s']:.4f}",
                f"{st['E_t']:.4f}",
                _f(st.get("E_t_plain"), 4),
                f"{st['coverage']:.3f}",
            ]
            for st in p["steps"]
        ]
        L += [
            f"**{p['dataset']}** ({'×'.join(map(str, p['dims']))}; {', '.join(p['structures'])}"
            f"): {_s(p['seconds'])} s, {p['nfev']} evaluations; {p['message']}",
            "",
        ]
        L += _table(["image", "E_v", "E_s", "E_t", "E_t (plain view)", "coverage"], rows)
        srows = [
            [
                st["name"],
                "kept" if st["accepted"] else "undone",
                st["message"],
                st["iterations"],
                st["evaluations"],
                _s(st["seconds"]),
            ]
            for st in p["stages"]
        ]
        L += _table(["stage", "kept", "message", "iterations", "evaluations", "s"], srows)
        img = s["images"]["pipeline_" + p["dataset"]]
        L += [f"![{p['dataset']} pipeline]({img})", ""]
        L += _observed(obs, f"pipeline_{p['dataset']}")

    L += _objectives_section(s, obs)

    # 5. performance
    perf = s["performance"]
    L += ["## 5. Performance", ""]
    L += [
        "Our frame is one full `analyze` (ray analysis with the re-evaluation cache and the "
        "per-pixel structure buffers, not just an image); VTK's is a warm frame of "
        "`vtkFixedPointVolumeRayCastMapper` (CPU) on the same view and size. The optimisation "
        "is one default `optimize` call (3 stages, max_iter 5, evaluations at 96 px, the "
        "curvature volume passed in). Times are wall-clock on a machine shared with other "
        "jobs: expect ±50 %.",
        "",
    ]
    rows = []
    for name, points in perf["image_size"].items():
        for p in points:
            rows.append(
                [
                    name,
                    f"{p['size'][0]}²",
                    _s(p["frame_s"]),
                    _s(p["vtk_frame_s"]),
                    _f(p["frame_ratio"], 2),
                    _s(p["optimize_s"]),
                    _f(p["optimize_vtk_frames"], 1),
                    p["iterations"],
                ]
            )
    big = [
        f"{name} {p['optimize_s']:.2f} s = {p['optimize_vtk_frames']:.1f} VTK frames"
        for name, points in perf["image_size"].items()
        for p in points
        if p["size"][0] == n and p.get("optimize_vtk_frames") is not None
    ]
    if big:
        L += [
            f"**Whole default optimisation at {n}²** (ray analyses at full size included, "
            "curvature volume excluded), in warm VTK CPU frames of the same view and size "
            "(target ≤ 25): " + "; ".join(big) + ".",
            "",
        ]
    L += ["**Against image size**", ""]
    L += _table(
        [
            "volume",
            "image",
            "our frame s",
            "VTK frame s",
            "ratio",
            "optimise s",
            "in VTK frames",
            "iterations",
        ],
        rows,
    )
    rows = []
    for name, points in perf["image_size"].items():
        for p in points:
            if p["size"][0] not in cfg_stage_sizes(cfg):
                continue
            for st in p["stages"]:
                rows.append(
                    [
                        name,
                        f"{p['size'][0]}²",
                        st["name"],
                        st["iterations"],
                        st["evaluations"],
                        _s(st["seconds"]),
                        _s(st["seconds_per_iteration"]),
                    ]
                )
    for name, points in perf.get("full_resolution", {}).items():
        for p in points:
            for st in p["stages"]:
                rows.append(
                    [
                        name,
                        f"{p['size'][0]}² (evaluated at {p['size'][0]}²)",
                        st["name"],
                        st["iterations"],
                        st["evaluations"],
                        _s(st["seconds"]),
                        _s(st["seconds_per_iteration"]),
                    ]
                )
    L += ["**Per stage** (evaluations at the optimiser's 96 px unless stated)", ""]
    L += _table(
        ["volume", "image", "stage", "iterations", "evaluations", "stage s", "s / iteration"], rows
    )
    full = perf.get("full_resolution", {})
    if full:
        L += [
            "Without image sampling (`optimize(..., resolution=N)`: every evaluation on the "
            "whole N×N image, as the paper's timing presumably is): "
            + "; ".join(
                f"{name} {p['size'][0]}²: {_s(p['optimize_s'])} s whole run, E "
                f"{p['initial']['E']:.3f} → {p['final']['E']:.3f}"
                for name, points in full.items()
                for p in points
            )
            + ".",
            "",
        ]
    else:
        L += ["(The runs without image sampling are left out of the reduced form.)", ""]
    rows = []
    for name, points in perf["volume_size"].items():
        for p in points:
            rows.append(
                [
                    f"{name} /{p['factor']}",
                    "×".join(map(str, p["dims"])),
                    f"{p['voxels'] / 1e6:.2f} M",
                    _s(p["curvature_s"]),
                    _s(p["frame_s"]),
                    _s(p["vtk_frame_s"]),
                    _f(p["frame_ratio"], 2),
                    _s(p.get("optimize_s")),
                ]
            )
    L += ["**Against volume size** (every n-th voxel)", ""]
    L += _table(
        [
            "volume",
            "dims",
            "voxels",
            "curvature s",
            "our frame s",
            "VTK frame s",
            "ratio",
            "optimise s",
        ],
        rows,
    )
    L += [f"![performance]({s['images']['performance']})", ""]
    L += _observed(obs, "performance")
    L += _scale_section(s.get("scale"), obs)
    L += ["## Where we differ from the paper, and why", ""]
    notes = "*See the notes in `dvr_perception/benchmarks/observations.md`.*"
    L += [obs.get("differences", notes), ""]
    L += ["## Experiment run times", ""]
    L += _table(["experiment", "s"], [[k, _s(v)] for k, v in s["experiment_seconds"].items()])
    return "\n".join(L).rstrip() + "\n"


def _objectives_section(s: dict, obs: dict) -> list[str]:
    """Section 4b: the full pipeline under the image-mean E and under Eq. 13 (D4)."""
    comp = s.get("objectives")
    if not comp:
        return []
    L = ["## 4b. Objectives: image-mean E against Eq. 13's least squares", ""]
    L += [
        "The full default pipeline under both objectives of `optimize(objective=...)`: "
        "**mean** (every stage minimises the image-mean E = w · (E_v, E_s, E_t), its lead "
        "term boosted) and **least_squares** (Eq. 13: the mean over the rays of "
        "(w · (δ_v, δ_s, δ_t))², the same boost). Both never raise their own objective at "
        "the user's resolution. S is Eq. 13 per pixel with unit weights, measured on the "
        f"final image. Default: **{comp['default']}**.",
        "",
    ]
    rows = []
    for name, by in comp["runs"].items():
        first = next(iter(by.values()))["original"]
        names = list(first["visible_share"])
        rows.append([name, "original", *_objective_cells(first, names), "–"])
        for obj, r in by.items():
            changed = [st["name"] for st in r["stages"] if st["message"].startswith("improved")]
            kept = ", ".join(changed) or "none"
            rows.append([name, obj, *_objective_cells(r["final"], names), kept])
    L += _table(
        ["volume", "image", "E_v", "E_s", "E_t", "S", "coverage", "visible shares",
         "target shares", "stages that changed"],
        rows,
    )  # fmt: skip
    L += [f"![objectives]({s['images']['objectives']})", ""]
    L += _observed(obs, "objectives")
    return L


def _objective_cells(t: dict, names) -> list[str]:
    share = ", ".join(f"{n} {t['visible_share'][n]:.2f}" for n in names)
    target = ", ".join(f"{n} {t['target_share'][n]:.2f}" for n in names)
    cells = [f"{t[k]:.4f}" for k in ("E_v", "E_s", "E_t", "S")]
    return [*cells, f"{t['coverage']:.3f}", share, target]


def cfg_stage_sizes(cfg: dict) -> tuple[int, ...]:
    """Return the per-stage table's sizes for a config dict (as :attr:`Config.stage_time_sizes`)."""
    return Config(data=Path(cfg["data"]), size=cfg["size"], quick=cfg["quick"]).stage_time_sizes


def main(argv=None) -> int:
    """``python -m dvr_perception.benchmarks.report``: the options of ``dvr-perception report``."""
    prog = "python -m dvr_perception.benchmarks.report"
    p = argparse.ArgumentParser(prog=prog, description=__doc__)
    p.add_argument("--data", default=os.environ.get("DVR_SHARED_DATA", "../shared/data"))
    p.add_argument("--out", default="benchmarks")
    p.add_argument("--size", type=int, default=None)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--strict", action="store_true", help="exit 1 when a check fails")
    p.add_argument(
        "--markdown-only",
        action="store_true",
        help="only rewrite OUT/REPORT.md from OUT/summary.json (after editing observations.md)",
    )
    args = p.parse_args(argv)
    if args.markdown_only:
        rerender(args.out)
        return 0
    size = args.size or (128 if args.quick else 512)
    summary = build(Config(data=Path(args.data), size=size, quick=args.quick), args.out)
    for c in summary["checks"]:
        print(f"{'pass' if c['passed'] else 'FAIL'}  {c['name']}: {c['detail']}")
    return 1 if args.strict and not summary["all_passed"] else 0


if __name__ == "__main__":
    sys.exit(main())
