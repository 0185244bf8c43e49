"""The paper's experiments (Sec. 7, Figs. 7-11) on the shared volumes, and the timings.

Each ``run_*`` function returns a plain dict (numbers and names, JSON-ready) plus the images
the report draws, under the key ``"_images"`` (NumPy arrays;
:mod:`~dvr_perception.benchmarks.report` strips them before writing ``summary.json``).
Every term is measured at the user's image size with
the public measures on a fresh :func:`~dvr_perception.rays.engine.analyze` (curvature volume
included), not taken from the optimiser's own records, which are at its reduced
optimisation resolution.
"""

from __future__ import annotations

import colorsys
import inspect
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from dvr_perception import _resources
from dvr_perception._timing import median_time as _median_time
from dvr_perception.benchmarks import checks
from dvr_perception.measures import covered_transmittance, shape, transparency, visibility
from dvr_perception.optimize import optimize
from dvr_perception.optimize.core import OBJECTIVES
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze
from dvr_perception.structures.io import load_spec
from dvr_perception.structures.spec import Lighting, Structure
from dvr_perception.volume.io import load_volume
from dvr_perception.volume.volume import Volume

__all__ = [
    "STATE_FILES",
    "Config",
    "run_equalisation",
    "run_objectives",
    "run_performance",
    "run_pipeline",
    "run_saturation",
    "run_shape",
    "spec_after_stages",
]

#: The objective ``optimize()`` uses by default (its signature's).
DEFAULT_OBJECTIVE = inspect.signature(optimize).parameters["objective"].default
STATE_FILES = _resources.state_files_dir()
TERMS = ("E_v", "E_s", "E_t")
#: Stage -> the term it leads (paper, Sec. 5).
LEAD = {"opacity": "E_v", "lighting": "E_s", "colour": "E_t"}
#: Importance ratios of the visibility-equalisation experiment (paper, Fig. 7).
RATIOS = ((0.2, 0.8), (0.5, 0.5), (0.8, 0.2))
#: Target compositions of E_v the equalisation runs under (decision D1): importance x
#: presence (the optimiser's default, checked) and the paper-literal thickness (shown beside).
#: No coverage floor: under D1 fading raises E_v by itself.
COMPOSITIONS = ("importance", "thickness")
#: Rendering opacity of both structures in the equalisation experiment's original image:
#: opaque, the inner structure occluded (the paper's original DVRI, "the bones were
#: occluded"), one original for every ratio (the ratio sets the target only).  Under D1 the
#: target is the composition of the rendering *at the importances*, so a start there starts
#: at (nearly) the optimum: cthead 0.2/0.8 E_v 0.196 against 0.194 at the best opacities of
#: a grid, and the stage rightly finds nothing to do.
EQUALISATION_START_OPACITY = 1.0
#: The lighting stage of the Fig. 8 experiment leads shape alone (decision D4).
SHAPE_WEIGHTS = (0.0, 1.0, 0.0)
#: The least decrease of E_s the Fig. 8 experiment must show (relative).
SHAPE_GAIN = 0.05
#: Datasets of the objective comparison (full default pipeline, both objectives).
OBJECTIVE_DATASETS = ("engine", "cthead", "lidc_chest")
#: Outer-layer saturations of the colour experiment (paper, Fig. 9), in percent.
SATURATIONS = (100, 75, 50, 25)


@dataclass(frozen=True)
class Config:
    """What to run: data folder, image size, reduced (CI) form, seed and sweep sizes."""

    data: Path
    size: int = 512
    quick: bool = False
    seed: int = 0

    @property
    def image_sizes(self) -> tuple[int, ...]:
        """Image sizes of the performance sweep (the last is ``size``)."""
        if self.quick:
            return (max(32, self.size // 2), max(48, (3 * self.size) // 4), self.size)
        return (max(64, self.size // 4), max(96, self.size // 2), self.size)

    @property
    def stage_time_sizes(self) -> tuple[int, ...]:
        """The two sizes at which per-stage times are tabulated (256 and 512 in full form)."""
        return self.image_sizes[1:]

    @property
    def volume_factors(self) -> tuple[int, ...]:
        """Down-sampling factors of the volume-size sweep (1 = the full volume)."""
        return (4, 2, 1)

    @property
    def volume_sweep_size(self) -> int:
        """Image size of the volume-size sweep."""
        return self.image_sizes[1]


# -- datasets and cameras -----------------------------------------------------------------------
def load(cfg: Config, name: str):
    """Return ``(volume, spec)`` of a shared dataset with its preset in ``state_files/``."""
    return load_volume(Path(cfg.data) / f"{name}.nhdr"), load_spec(STATE_FILES / f"{name}.json")


def camera_for(volume: Volume, spec, size: int) -> Camera:
    """Return the preset's view (azimuth, elevation, zoom) at ``size`` x ``size`` pixels."""
    az, el, zoom = spec.view or (0.0, 0.0, 1.0)
    return Camera.from_view(
        volume.bounds, azimuth=az, elevation=el, zoom=zoom, width=size, height=size
    )


def downsample(volume: Volume, factor: int) -> Volume:
    """Every ``factor``-th voxel along each axis (spacing scaled, so the bounds barely change)."""
    if factor == 1:
        return volume
    data = np.ascontiguousarray(volume.data[::factor, ::factor, ::factor])
    spacing = tuple(float(s) * factor for s in volume.spacing)
    return Volume(data, spacing=spacing, origin=volume.origin, name=f"{volume.name}/{factor}")


def measure(volume, spec, cam, curv, composition="importance") -> dict:
    """Render ``spec`` and compute the three measures; return terms, shares and images.

    ``S`` is Eq. 13 per pixel with unit weights: the mean over the rays that carry assigned
    opacity of ``(d_v + d_s + d_t)^2`` (the measures' deviation images), as the optimiser's.
    """
    # enclosers re-walked without a cache (D7); the thickness composition reads the exact walk
    a = analyze(volume, spec, cam, curvature=curv, exact=composition == "thickness")
    vis = visibility(a, spec, composition=composition)
    shp = shape(a, spec)
    trn = transparency(a, spec)
    plain = transparency(a, spec, enclosure="plain")  # the paper's ring, shown beside
    rays = np.asarray(a.assigned).sum(axis=0) > 0
    per_ray = (
        np.asarray(vis.deviation, float)
        + np.where(shp.nonempty, shp.deviation, 0.0)
        + np.asarray(trn.deviation, float)
    )[rays]
    per = vis.per_structure
    return {
        "E_v": float(vis.E_v),
        "E_s": float(shp.E_s),
        "E_t": float(trn.E_t),
        "E_t_plain": float(plain.E_t),
        "S": float(np.mean(per_ray**2)) if per_ray.size else 0.0,
        "visible_share": {n: float(v["visible_share"]) for n, v in per.items()},
        "target_share": {n: float(v["target_share"]) for n, v in per.items()},
        "assigned_share": {n: float(v["assigned_share"]) for n, v in per.items()},
        "perceived_transparency": {
            n: v["perceived_transparency"] for n, v in trn.per_structure.items()
        },
        "perceived_transparency_plain": {
            n: v["perceived_transparency"] for n, v in plain.per_structure.items()
        },
        "coverage": float(np.mean(a.accumulated[vis.nonempty])) if vis.nonempty.any() else 0.0,
        "_images": {
            "image": np.asarray(a.image, np.float32),
            "dv": np.asarray(vis.deviation),
            "dv_mask": np.asarray(vis.nonempty),
            "ds": np.asarray(shp.deviation),
            "ds_mask": np.asarray(shp.nonempty),
            "v_s": np.asarray(shp.v_s),
            "v_i": np.asarray(shp.v_i),
            "dt": np.asarray(trn.deviation),
            "dt_plain": np.asarray(plain.deviation),
            "dt_mask": np.asarray(trn.layer_set) != 0,
        },
    }


def public(d: dict) -> dict:
    """``d`` without its ``_images``."""
    return {k: v for k, v in d.items() if not k.startswith("_")}


def apply_params(spec, params: dict):
    """Apply a stage's ``params_after`` (``Stage.describe`` format) to ``spec``."""
    out = []
    for s in spec.structures:
        changes = {}
        if s.name in params.get("opacity", {}):
            changes["opacity"] = float(params["opacity"][s.name])
        if s.name in params.get("lighting", {}):
            changes["lighting"] = Lighting(
                **{k: float(v) for k, v in params["lighting"][s.name].items()}
            )
        if s.name in params.get("color", {}):
            changes["colour"] = tuple(float(c) for c in params["color"][s.name])
        out.append(replace(s, **changes))
    rendering = spec.rendering
    if "light_direction" in params:
        light = tuple(float(v) for v in params["light_direction"])
        rendering = replace(rendering, light_direction=light)
    return replace(spec, structures=tuple(out), rendering=rendering)


def spec_after_stages(spec, result) -> list:
    """Return the spec after each stage of ``result`` as returned (undone stages change nothing)."""
    specs, cur = [], spec
    for rec in result.stages:
        if rec.accepted:  # an unchanged stage's params_after are its params_before
            cur = apply_params(cur, rec.params_after)
        specs.append(cur)
    return specs


def _stage_record(rec) -> dict:
    lead = LEAD.get(rec.name)
    return {
        "name": rec.name,
        "accepted": bool(rec.accepted),
        "message": rec.message,
        "iterations": int(rec.iterations),
        "evaluations": int(rec.evaluations),
        "seconds": float(rec.seconds),
        "seconds_per_iteration": float(rec.seconds) / max(int(rec.iterations), 1),
        "converged": bool(rec.converged),
        "lead": lead,
        "opt_resolution_lead_before": float(rec.terms_before[lead]) if lead else None,
        "opt_resolution_lead_after": float(rec.terms_after[lead]) if lead else None,
        "params_after": rec.params_after,
    }


def _timed_optimize(volume, spec, cam, curv, cfg, **kw):
    t0 = time.perf_counter()
    res = optimize(volume, spec, cam, seed=cfg.seed, curvature=curv, **kw)
    return res, time.perf_counter() - t0


# -- Fig. 7: visibility equalisation ------------------------------------------------------------
def _two_structures(name: str, spec):
    """Return the outer/inner pair of the equalisation experiment (cthead or engine)."""
    by = {s.name: s for s in spec.structures}
    if name == "cthead":
        return by["skin"], by["bone"]
    if name == "engine":
        lo = by["light metal"].range[0]
        hi = by["dense metal"].range[1]
        block = Structure(
            "block",
            0.5,
            by["light metal"].colour,
            range=(lo, hi),
            edge=0.1,
            lighting=by["light metal"].lighting,
        )
        return block, by["inserts"]
    raise ValueError(f"no equalisation pair for {name!r}")


def _equalise(volume, spec, cam, curv, cfg, composition) -> dict:
    """One opacity-stage run under ``composition``; terms and shares before and after."""
    res, seconds = _timed_optimize(
        volume, spec, cam, curv, cfg, stages=("opacity",), composition=composition
    )
    before = measure(volume, spec, cam, curv, composition)
    after = measure(volume, res.spec, cam, curv, composition)
    return {
        "composition": composition,
        "target": [before["target_share"][n] for n in spec.names],
        "opacity_found": {s.name: float(s.render_opacity) for s in res.spec.structures},
        "before": before,
        "after": after,
        "seconds": seconds,
        "stage": _stage_record(res.stages[0]),
        "result_spec": res.spec,
    }


def run_equalisation(cfg: Config, name: str) -> dict:
    """Stage 1 alone (opacity) on an outer/inner pair at the three importance ratios.

    Each ratio starts from the same original (:data:`EQUALISATION_START_OPACITY`) and runs
    under both target compositions of ``E_v`` (:data:`COMPOSITIONS`), without a coverage
    floor (D1).  The checks are on the default (importance x presence): the
    visible shares move toward its target shares, and ``E_v`` falls.
    """
    volume, full = load(cfg, name)
    outer, inner = _two_structures(name, full)
    base = replace(full, structures=(outer, inner))
    cam = camera_for(volume, full, cfg.size)
    curv, _ = curvature_volume(volume, base)
    runs, out_checks = [], []
    for w_out, w_in in RATIOS:
        spec = replace(
            base,
            structures=(
                replace(outer, importance=w_out, opacity=EQUALISATION_START_OPACITY),
                replace(inner, importance=w_in, opacity=EQUALISATION_START_OPACITY),
            ),
        )
        by = {c: _equalise(volume, spec, cam, curv, cfg, c) for c in COMPOSITIONS}
        main = by[COMPOSITIONS[0]]
        before, after, names = main["before"], main["after"], spec.names
        label = f"{name} {w_out:g}/{w_in:g}"
        out_checks.append(
            checks.moves_toward(
                f"equalisation {label}: visible shares move toward the target shares "
                "(importance x presence)",
                [before["visible_share"][n] for n in names],
                [after["visible_share"][n] for n in names],
                main["target"],
            )
        )
        out_checks.append(
            checks.lowered(f"opacity stage lowers E_v: {label}", before["E_v"], after["E_v"])
        )
        runs.append(
            {
                "importance": {names[0]: w_out, names[1]: w_in},
                "composition": dict(zip(names, main["target"], strict=True)),
                "thickness_composition": dict(zip(names, by["thickness"]["target"], strict=True)),
                "distance_to_ratio": [
                    checks.share_distance([r["visible_share"][n] for n in names], [w_out, w_in])
                    for r in (before, after)
                ],
                **{k: main[k] for k in ("opacity_found", "before", "after", "seconds", "stage")},
                "result_spec": main["result_spec"],
                "thickness": {k: v for k, v in by["thickness"].items() if k != "result_spec"},
            }
        )
    return {
        "dataset": name,
        "dims": list(volume.dims),
        "size": cfg.size,
        "structures": list(base.names),
        "compositions": list(COMPOSITIONS),
        "start_opacity": EQUALISATION_START_OPACITY,
        "runs": runs,
        "checks": out_checks,
    }


# -- Fig. 8: shape enhancement ------------------------------------------------------------------
def run_shape(cfg: Config, start_spec, name: str = "cthead") -> dict:
    """Stage 2 alone (lighting) on the equalised skin/bone head; E_s and the lighting found.

    The stage runs with weights :data:`SHAPE_WEIGHTS` (0, 1, 0): shape isolated as in the
    paper's Fig. 8 (decision D4); the check asks for at least :data:`SHAPE_GAIN` less ``E_s``.
    """
    volume, full = load(cfg, name)
    cam = camera_for(volume, full, cfg.size)
    curv, _ = curvature_volume(volume, start_spec)
    res, seconds = _timed_optimize(
        volume, start_spec, cam, curv, cfg, stages=("lighting",), weights=SHAPE_WEIGHTS
    )
    before, after = measure(volume, start_spec, cam, curv), measure(volume, res.spec, cam, curv)

    def lighting(spec):
        return {
            s.name: {
                k: float(getattr(s.lighting, k))
                for k in ("ambient", "diffuse", "specular", "specular_power")
            }
            for s in spec.structures
        }

    return {
        "dataset": name,
        "dims": list(volume.dims),
        "size": cfg.size,
        "opacity": {s.name: float(s.render_opacity) for s in start_spec.structures},
        "lighting_before": lighting(start_spec),
        "lighting_after": lighting(res.spec),
        "light_before": list(start_spec.rendering.light_direction),
        "light_after": [float(v) for v in res.spec.rendering.light_direction],
        "weights": list(SHAPE_WEIGHTS),
        "before": before,
        "after": after,
        "seconds": seconds,
        "stage": _stage_record(res.stages[0]),
        "checks": [
            checks.lowered(
                f"lighting stage lowers E_s: {name} skin/bone by at least {SHAPE_GAIN:.0%} "
                "(weights 0, 1, 0)",
                before["E_s"],
                after["E_s"],
                margin=SHAPE_GAIN * before["E_s"],
            )
        ],
    }


# -- Fig. 9: colour saturation and perceived transparency ---------------------------------------
def with_saturation(colour, fraction: float):
    """``colour`` with its HSV saturation set to ``fraction`` (hue and value kept)."""
    h, _, v = colorsys.rgb_to_hsv(*colour)
    return tuple(float(c) for c in colorsys.hsv_to_rgb(h, float(fraction), v))


def run_saturation(cfg: Config, name: str = "neghip", outer: str = "diffuse lobes") -> dict:
    """Measure the outer layer's perceived transparency at 100/75/50/25 % saturation.

    Two readings per setting: the paper's Fig. 9 one, TAP of the outer layer over what it
    covers seen with and without it (:func:`~dvr_perception.measures.covered_transmittance`),
    and the ``E_t`` measure's area-weighted ``alpha_t`` (Eq. 8 for overlapping layers).  Also
    runs the colour stage alone from the preset (does it lower ``E_t``?).
    """
    volume, spec = load(cfg, name)
    cam = camera_for(volume, spec, cfg.size)
    curv, _ = curvature_volume(volume, spec)
    series = []
    for pct in SATURATIONS:
        s = replace(
            spec,
            structures=tuple(
                replace(x, colour=with_saturation(x.colour, pct / 100)) if x.name == outer else x
                for x in spec.structures
            ),
        )
        m = measure(volume, s, cam, curv)
        tap = covered_transmittance(analyze(volume, s, cam, curvature=curv), s, outer)
        series.append(
            {
                "saturation_percent": pct,
                "color": [
                    float(c) for c in next(x.colour for x in s.structures if x.name == outer)
                ],
                "perceived_transparency": m["perceived_transparency"],
                "outer_transparency": m["perceived_transparency"][outer],
                "outer_transparency_plain": m["perceived_transparency_plain"][outer],
                "E_t_plain": m["E_t_plain"],
                "outer_tap": None if tap.reason else tap.alpha,
                "outer_tap_pixels": tap.pixels,
                "E_t": m["E_t"],
                "E_v": m["E_v"],
                "_images": m["_images"],
            }
        )
    xs = [p["saturation_percent"] for p in series]
    tap_monotone = checks.monotone(
        f"saturation series, TAP ({name}): the TAP transparency of '{outer}' over what it "
        "covers falls as its saturation falls (paper, Fig. 9: 'based on the TAP')",
        xs,
        [p["outer_tap"] for p in series],
        increasing=True,
    )
    monotone = checks.monotone(
        f"saturation series ({name}): perceived transparency of '{outer}' (E_t measure, Eq. 8) "
        "falls as its saturation falls",
        xs,
        [p["outer_transparency"] for p in series],
        increasing=True,
    )
    res, seconds = _timed_optimize(volume, spec, cam, curv, cfg, stages=("colour",))
    before, after = measure(volume, spec, cam, curv), measure(volume, res.spec, cam, curv)
    return {
        "dataset": name,
        "dims": list(volume.dims),
        "size": cfg.size,
        "outer": outer,
        "expected_opacity": {x.name: float(x.target_opacity) for x in spec.structures},
        "series": series,
        "colour_stage": {
            "before": before,
            "after": after,
            "seconds": seconds,
            "color_after": {x.name: [float(c) for c in x.colour] for x in res.spec.structures},
            "stage": _stage_record(res.stages[0]),
        },
        "checks": [
            tap_monotone,
            monotone,
            checks.lowered(f"colour stage lowers E_t: {name}", before["E_t"], after["E_t"]),
        ],
    }


# -- Figs. 10-11: the full pipeline -------------------------------------------------------------
def run_pipeline(cfg: Config, name: str, objective: str | None = None) -> dict:
    """All three stages; the image and all three terms after each stage.

    ``objective``: the optimiser's (``None``: its default).
    """
    volume, spec = load(cfg, name)
    cam = camera_for(volume, spec, cfg.size)
    t0 = time.perf_counter()
    curv, _ = curvature_volume(volume, spec)
    curvature_s = time.perf_counter() - t0
    kw = {} if objective is None else {"objective": objective}
    res, seconds = _timed_optimize(volume, spec, cam, curv, cfg, **kw)
    specs = [spec, *spec_after_stages(spec, res)]
    labels = ["original", *(f"after {r.name}" for r in res.stages)]
    steps = [
        measure(volume, s, cam, curv) | {"label": lab} for s, lab in zip(specs, labels, strict=True)
    ]
    out_checks = []
    for i, rec in enumerate(res.stages):
        lead = LEAD[rec.name]
        changed = rec.accepted and rec.params_after != rec.params_before
        out_checks.append(
            checks.lowered_or_declined(
                f"{rec.name} stage lowers {lead} or keeps no change (D4): {name} (full pipeline)",
                steps[i][lead],
                steps[i + 1][lead],
                changed,
            )
        )
    return {
        "dataset": name,
        "dims": list(volume.dims),
        "size": cfg.size,
        "structures": list(spec.names),
        "steps": steps,
        "stages": [_stage_record(r) for r in res.stages],
        "objective": objective or DEFAULT_OBJECTIVE,
        "initial": {k: float(res.initial[k]) for k in (*TERMS, "E", "S")},
        "final": {k: float(res.final[k]) for k in (*TERMS, "E", "S")},
        "seconds": seconds,
        "curvature_s": curvature_s,
        "nfev": int(res.nfev),
        "message": res.message,
        "final_spec": res.spec,
        "checks": out_checks,
    }


def run_objectives(cfg: Config) -> dict:
    """Run the full default pipeline under both objectives (decision D4) on each dataset.

    Returns ``{"runs": {dataset: {objective: pipeline}}}``; the pipelines of the default
    objective are those of the report's pipeline section (their checks included there).
    """
    runs = {
        name: {obj: run_pipeline(cfg, name, obj) for obj in OBJECTIVES}
        for name in OBJECTIVE_DATASETS
    }
    return {"default": DEFAULT_OBJECTIVE, "runs": runs}


# -- performance --------------------------------------------------------------------------------
def _vtk_frame(volume, spec, cam) -> float | None:
    from dvr_perception.errors import DVRInputError
    from dvr_perception.rays.vtk_reference import time_vtk_frames

    try:
        return float(time_vtk_frames(volume, spec, cam, frames=3))
    except DVRInputError:  # VTK cannot render here: the table shows a dash
        return None


def _time_point(volume, spec, cam, curv, cfg, *, optimise=True) -> dict:
    analyze(volume, spec, cam, curvature=curv)  # warm (numba compiled once per process)
    repeat = 2 if cfg.quick else 3
    frame_s = _median_time(lambda: analyze(volume, spec, cam, curvature=curv), repeat)
    vtk_s = _vtk_frame(volume, spec, cam)
    point = {
        "size": [cam.width, cam.height],
        "dims": list(volume.dims),
        "voxels": int(np.prod(volume.dims)),
        "frame_s": frame_s,
        "vtk_frame_s": vtk_s,
        "frame_ratio": frame_s / vtk_s if vtk_s else None,
    }
    if optimise:
        res, seconds = _timed_optimize(volume, spec, cam, curv, cfg)
        point["optimize_s"] = seconds
        point["optimize_vtk_frames"] = seconds / vtk_s if vtk_s else None
        point["iterations"] = int(res.nit)
        point["stages"] = [
            {k: v for k, v in _stage_record(r).items() if k != "params_after"} for r in res.stages
        ]
    return point


def run_performance(cfg: Config) -> dict:
    """Frame and optimisation times against image size and volume size (and VTK's frame).

    Image sizes: lidc_chest (the paper's chest stand-in) and, in the full form, engine; volume
    sizes: engine down-sampled (the reduced form times frames and the curvature volume only,
    no optimisation).
    """
    names = ("lidc_chest",) if cfg.quick else ("lidc_chest", "engine")
    out = {"image_size": {}, "volume_size": {}, "curvature_s": {}}
    for name in names:
        volume, spec = load(cfg, name)
        t0 = time.perf_counter()
        curv, _ = curvature_volume(volume, spec)
        out["curvature_s"][name] = time.perf_counter() - t0
        out["image_size"][name] = [
            _time_point(volume, spec, camera_for(volume, spec, n), curv, cfg)
            for n in cfg.image_sizes
        ]
    # the paper evaluates every iteration on the whole image: the same without image sampling
    out["full_resolution"] = {}
    if not cfg.quick:
        volume, spec = load(cfg, names[0])
        curv, _ = curvature_volume(volume, spec)
        points = []
        for n in cfg.stage_time_sizes:
            cam = camera_for(volume, spec, n)
            res, seconds = _timed_optimize(volume, spec, cam, curv, cfg, resolution=n)
            points.append(
                {
                    "size": [n, n],
                    "optimize_s": seconds,
                    "iterations": int(res.nit),
                    "stages": [
                        {k: v for k, v in _stage_record(r).items() if k != "params_after"}
                        for r in res.stages
                    ],
                    "final": {k: float(res.final[k]) for k in (*TERMS, "E")},
                    "initial": {k: float(res.initial[k]) for k in (*TERMS, "E")},
                }
            )
        out["full_resolution"][names[0]] = points
    name = "engine"
    volume, spec = load(cfg, name)
    points = []
    for f in cfg.volume_factors:
        small = downsample(volume, f)
        t0 = time.perf_counter()
        curv, _ = curvature_volume(small, spec)
        curvature_s = time.perf_counter() - t0
        cam = camera_for(small, spec, cfg.volume_sweep_size)
        point = _time_point(small, spec, cam, curv, cfg, optimise=not cfg.quick)
        point["factor"] = f
        point["curvature_s"] = curvature_s
        points.append(point)
    out["volume_size"][name] = points
    return out
