"""``dvr-perception measure``: the paper's three perceptual measures of one rendering.

The command loads its inputs (as ``render`` does), computes the curvature volume (``|H|`` on the
structure boundaries, the structural shape ``v_s``), runs the ray analysis and then the
visibility (Sec. 4.1), shape (Sec. 4.2) and transparency (Sec. 4.3) measures.  It reports
``E_v``, ``E_s`` and ``E_t``, the per-structure shares and perceived transparencies, the layer
relations, the undetermined (region, layer) pairs and the measures' notes.  With
``--out-dir`` it also writes the rendering, the three deviation maps, the visibility
histograms, the region map and ``measures.json`` (the same JSON as ``--json`` prints).
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from dvr_perception._files import output_folder, write_json, write_png
from dvr_perception.cli._backend import add_backend_arg
from dvr_perception.cli._common import (
    add_input_args,
    coverage,
    emit_json,
    load_inputs,
    log,
    log_progress,
)
from dvr_perception.errors import DVRInputError

__all__ = ["FIGURES", "MAX_BINS", "add_parser", "run"]

EXAMPLE = """examples:
  dvr-perception measure phantom --size 256 --json
  dvr-perception measure ../shared/data/engine.nhdr --view=30,20 --out-dir engine_measures
"""

#: Most ``--bins`` (histograms of per-ray opacities on [0, 1]: finer bins say nothing more, and
#: every bin is held per structure and drawn in the figure).
MAX_BINS = 1000

#: Files written into ``--out-dir``, in writing order.
FIGURES = (
    "image.png",
    "visibility_deviation.png",
    "shape_deviation.png",
    "transparency_deviation.png",
    "visibility_histograms.png",
    "regions.png",
    "measures.json",
)


def _positive_int(text: str) -> int:
    text = str(text)
    shown = repr(text) if len(text) <= 20 else f"{text[:15]!r}... ({len(text)} characters)"
    try:
        value = int(text) if len(text.strip()) <= 9 else 0
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(
            f"expected a positive integer below 10^9, got {shown}"
        ) from None
    return value


def add_parser(subparsers, parents) -> None:
    """Register the ``measure`` sub-command."""
    p = subparsers.add_parser(
        "measure",
        parents=parents,
        help="compute the visibility, shape and transparency measures of a rendering",
        description="Render VOLUME with the ray-analysis engine and compute E_v (visibility, "
        "in [0, 2]), E_s (shape, in [0, 1]) and E_t (transparency, >= 0); lower is better.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_input_args(p)
    add_backend_arg(p)
    p.add_argument(
        "--out-dir",
        metavar="DIR",
        help="also write " + ", ".join(FIGURES) + " into DIR (created if needed)",
    )
    p.add_argument(
        "--bins",
        type=_positive_int,
        default=20,
        metavar="N",
        help=f"bins of the visibility histograms on [0, 1] (default 20, at most {MAX_BINS})",
    )
    p.set_defaults(run=run)


def _structures(vis, trans, names) -> dict:
    """Per-structure summary from the visibility and transparency results."""
    out = {}
    for name in names:
        v, t = vis.per_structure[name], trans.per_structure[name]
        out[name] = {
            "visible_share": float(v["visible_share"]),
            "target_share": float(v["target_share"]),
            "assigned_share": float(v["assigned_share"]),
            "perceived_transparency": t["perceived_transparency"],
            "perceived_opacity": t["perceived_opacity"],
            "expected_opacity": float(t["expected_opacity"]),
            "rays": int(v["rays"]),
        }
    return out


def _relations(trans) -> list[dict]:
    """Return the layer relations as a list of ``{a, b, kind, encloser}``."""
    return [
        {"a": a, "b": b, "kind": rel["kind"], "encloser": rel["encloser"]}
        for (a, b), rel in trans.relations.items()
    ]


def _notes(curvature, ray_curvature, vis, shp, trans) -> list[str]:
    """Return the measures' notes, each prefixed with the measure it comes from.

    ``curvature`` is what the analysis was given: the whole ``|H|`` volume (dense, or its
    pages: :class:`~dvr_perception.rays.curvature_field.CurvaturePages`), or a
    :class:`~dvr_perception.rays.curvature_field.CurvatureField` (a bricked analysis, whose
    whole volume is never held); ``ray_curvature`` the analysis' per-ray curvature image.
    """
    notes = []
    held = getattr(curvature, "pages", curvature)  # the dense volume, or its non-zero pages
    if isinstance(held, np.ndarray) and not np.any(held > 0):
        notes.append(
            "shape: the curvature volume is 0 everywhere (no curved structure boundary), so "
            "v_s = 0 and E_s measures only the image variation (silhouettes, shading)"
        )
    elif not np.any(np.asarray(ray_curvature) > 0):
        notes.append(
            "shape: no ray meets a curved structure boundary (the curvature is 0 on every "
            "ray), so v_s = 0 and E_s measures only the image variation (silhouettes, shading)"
        )
    for measure, result in (("visibility", vis), ("shape", shp), ("transparency", trans)):
        notes.extend(f"{measure}: {note}" for note in result.notes)
    return notes


def _check_defined(report: dict) -> None:
    """Fail loudly if a number that the measures define came out NaN or infinite."""
    bad = [key for key in ("E_v", "E_s", "E_t") if not math.isfinite(report[key])]
    for name, entry in report["structures"].items():
        for key in ("visible_share", "target_share", "assigned_share", "expected_opacity"):
            if not math.isfinite(entry[key]):
                bad.append(f"structures.{name}.{key}")
        value = entry["perceived_transparency"]
        if value is not None and not math.isfinite(value):
            bad.append(f"structures.{name}.perceived_transparency")
    if bad:
        raise RuntimeError(f"measure produced non-finite values for {', '.join(bad)}")


def _write_outputs(out_dir: Path, result, vis, shp, trans) -> list[Path]:
    """Write the rendering and the figures (not ``measures.json``) into ``out_dir``."""
    from dvr_perception.cli import _plots

    files = [write_png(out_dir / "image.png", result.image)]
    files.append(
        _plots.save_deviation_map(
            out_dir / "visibility_deviation.png",
            vis.deviation,
            title=f"visibility deviation δ_v (E_v = {vis.E_v:.4f}, range [0, 2])",
            vmin=0.0,
            vmax=2.0,
            mask=vis.nonempty,
            label="δ_v",
        )
    )
    files.append(
        _plots.save_deviation_map(
            out_dir / "shape_deviation.png",
            shp.deviation,
            title=f"shape deviation δ_s (E_s = {shp.E_s:.4f}, range [0, 1])",
            vmin=0.0,
            vmax=1.0,
            mask=shp.nonempty,
            label="δ_s",
        )
    )
    t_max = max(1e-3, float(np.max(trans.deviation, initial=0.0)))
    files.append(
        _plots.save_deviation_map(
            out_dir / "transparency_deviation.png",
            trans.deviation,
            title=f"transparency deviation δ_t (E_t = {trans.E_t:.4f})",
            vmin=0.0,
            vmax=t_max,
            mask=np.asarray(trans.layer_set) != 0,
            label="δ_t",
        )
    )
    files.append(
        _plots.save_visibility_histograms(
            out_dir / "visibility_histograms.png",
            vis.per_structure,
            vis.bin_edges,
            title="per-ray assigned vs visible share over the rays meeting each structure "
            f"(E_v = {vis.E_v:.4f})",
        )
    )
    files.append(
        _plots.save_region_map(
            out_dir / "regions.png",
            trans.region_id,
            trans.regions,
            title=f"sub-regions by layer set ({len(trans.regions)} regions)",
        )
    )
    return files


def run(args: argparse.Namespace) -> int:
    """Execute ``measure``."""
    t_start = time.perf_counter()
    if args.bins > MAX_BINS:
        raise DVRInputError(f"--bins: expected 1 to {MAX_BINS}, got {args.bins}")
    inputs = load_inputs(args)  # validates the options and the spec before anything is written
    if not args.out_dir:
        return _run(args, inputs, t_start, None)
    # the folder is checked and locked before the work; the files appear together at the end
    with output_folder(args.out_dir) as staged:
        return _run(args, inputs, t_start, staged)


def _run(args, inputs, t_start: float, staged) -> int:
    out_dir = None if staged is None else staged.path
    from dvr_perception.measures import all_measures
    from dvr_perception.rays.curvature_field import curvature_source
    from dvr_perception.rays.engine import analyze

    log.info("computing the curvature volume")
    t0 = time.perf_counter()
    curvature = curvature_source(inputs.volume, inputs.spec, progress=log_progress("curvature"))
    t_curv = time.perf_counter() - t0
    log.info("analysing %dx%d rays", inputs.camera.width, inputs.camera.height)
    t0 = time.perf_counter()
    result = analyze(inputs.volume, inputs.spec, inputs.camera, curvature=curvature,
                     progress=log_progress("rays"), backend=args.backend)  # fmt: skip
    t_analysis = time.perf_counter() - t0
    log.info("computing the measures")
    t0 = time.perf_counter()
    vis, shp, trans = all_measures(result, inputs.spec, bins=args.bins)
    t_measures = time.perf_counter() - t0
    report = {
        "volume": inputs.volume_source,
        "spec": inputs.spec_source,
        "size": [inputs.camera.width, inputs.camera.height],
        "E_v": float(vis.E_v),
        "E_s": float(shp.E_s),
        "E_t": float(trans.E_t),
        "coverage": coverage(result),
        "structures": _structures(vis, trans, result.names),
        "relations": _relations(trans),
        "regions": len(trans.regions),
        "undetermined": list(trans.undetermined),
        "notes": _notes(curvature, result.curvature, vis, shp, trans),
        "seconds": None,
        "seconds_load": inputs.load_s,
        "seconds_curvature": t_curv,
        "seconds_analysis": t_analysis,
        "seconds_measures": t_measures,
        "seconds_figures": None,
        "out_dir": None,
        "files": [],
        "camera": inputs.camera.to_dict(),
    }
    _check_defined(report)
    if out_dir is not None:
        log.info("writing figures into %s", out_dir)
        t0 = time.perf_counter()
        files = _write_outputs(out_dir, result, vis, shp, trans)
        report["seconds_figures"] = time.perf_counter() - t0
        report["out_dir"] = str(staged.final)
        report["files"] = [str(staged.final_path(f)) for f in [*files, out_dir / "measures.json"]]
    report["seconds"] = time.perf_counter() - t_start
    if out_dir is not None:
        write_json(out_dir / "measures.json", report)
    if args.json:
        emit_json(report)
        return 0
    _print_summary(report)
    return 0


def _print_summary(report: dict) -> None:
    """Print a short human-readable summary of ``report`` on stdout."""
    w, h = report["size"]
    from dvr_perception.structures.spec import printable

    print(f"measures of {printable(report['volume'])} ({w}x{h}, spec: {printable(report['spec'])})")
    print(
        f"  E_v {report['E_v']:.4f} (visibility, 0..2)   E_s {report['E_s']:.4f} (shape, 0..1)"
        f"   E_t {report['E_t']:.4f} (transparency, >= 0)"
    )
    width = max([len(n) for n in report["structures"]] + [9])
    print(f"  {'structure':<{width}}  visible   target  perceived-alpha  expected-opacity")
    for name, s in report["structures"].items():
        alpha = s["perceived_transparency"]
        alpha_text = "undetermined" if alpha is None else f"{alpha:.3f}"
        print(
            f"  {printable(name):<{width}}  {s['visible_share']:7.3f}  {s['target_share']:7.3f}  "
            f"{alpha_text:>15}  {s['expected_opacity']:16.3f}"
        )
    if report["undetermined"]:
        print(f"  {len(report['undetermined'])} undetermined (region, layer) pair(s)")
    for note in report["notes"]:
        print(f"  note: {note}")
    print(
        f"  seconds: total {report['seconds']:.2f} (analysis {report['seconds_analysis']:.2f}, "
        f"measures {report['seconds_measures']:.2f})"
    )
    for f in report["files"]:
        print(f"  wrote {printable(f)}")
