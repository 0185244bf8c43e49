"""Bricked analysis equals the whole-volume one (issue 31), and the bricks sit below engine."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from dvr_perception.measures.combined import all_measures
from dvr_perception.rays import bricks
from dvr_perception.rays.camera import Camera
from dvr_perception.rays.curvature import curvature_volume
from dvr_perception.rays.engine import analyze, reevaluate
from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
from dvr_perception.volume.volume import Volume

pytest.importorskip("numba")

RAYS = Path(bricks.__file__).parent

#: Every buffer the measures read.
BUFFERS = ("rgba", "image", "accumulated", "visible", "assigned", "present", "curvature",
           "importance_accumulated")  # fmt: skip
TERMS = {"E_v": "visibility", "E_s": "shape", "E_t": "transparency"}


def _imports(path: Path) -> set[str]:
    """Every module ``path`` imports, at module level or inside functions."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


def test_the_bricked_walk_does_not_import_the_engine():
    """bricks.py and the shared helpers below it never import engine (no import cycle)."""
    got = _imports(RAYS / "bricks.py")
    assert "dvr_perception.rays._walk_setup" in got  # the shared helpers come from below
    for name in ("bricks.py", "_walk_setup.py"):
        got = _imports(RAYS / name)
        assert "dvr_perception.rays.engine" not in got, name
    assert "dvr_perception.rays.bricks" not in _imports(RAYS / "_walk_setup.py")
    # engine imports the bricked walk only inside its dispatcher, never at module level
    tree = ast.parse((RAYS / "engine.py").read_text())
    top = {
        n.module
        for n in tree.body
        if isinstance(n, ast.ImportFrom) and n.module
    } | {f"{n.module}.{a.name}" for n in tree.body if isinstance(n, ast.ImportFrom)
         for a in n.names}  # fmt: skip
    assert "dvr_perception.rays.bricks" not in top
    assert "dvr_perception.rays.bricks" in _imports(RAYS / "engine.py")


def _labelled():
    """A 30 x 34 x 38 volume: a shell (by intensity), a slab and a ball (by label).

    The shell's intensity 100 fills the box between radii; the slab (label 2, intensity
    160) and the ball (label 3, intensity 60 - inside the shell's range is avoided) are
    labelled voxels; the data are smoothed a little so that the normals vary.
    """
    from scipy import ndimage

    z, y, x = np.mgrid[0:30, 0:34, 0:38].astype(np.float32)
    r = np.sqrt(((x - 18.5) / 16) ** 2 + ((y - 16.5) / 15) ** 2 + ((z - 14.5) / 13) ** 2)
    data = np.where((r > 0.75) & (r < 0.95), 100.0, 10.0).astype(np.float32)
    labels = np.zeros(data.shape, np.uint8)
    labels[8:22, 6:27, 12:17] = 2  # a slab through the middle
    labels[(x - 24) ** 2 + (y - 18) ** 2 + (z - 15) ** 2 < 30] = 3  # a ball beside it
    data[labels == 2] = 160.0
    data[labels == 3] = 220.0
    data = ndimage.gaussian_filter(data, 0.8)
    vol = Volume(np.rint(data).astype(np.uint8), labels=labels, name="labelled")
    spec = StructureSpec(
        (
            Structure("shell", 0.3, (0.9, 0.8, 0.6), range=(70.0, 130.0)),
            Structure("slab", 0.6, (0.2, 0.6, 1.0), label=2),
            Structure("ball", 0.9, (1.0, 0.3, 0.2), label=3),
        ),
        rendering=RenderSettings(shade=True),
    )
    return vol, spec


@pytest.fixture(scope="module")
def scene():
    vol, spec = _labelled()
    return vol, spec, curvature_volume(vol, spec)[0]


def _members(vol, spec) -> list[np.ndarray]:
    """Per structure, the (z, y, x) voxel indices that belong to it."""
    d = vol.data
    return [
        np.argwhere(vol.labels == s.label) if s.label is not None
        else np.argwhere((d >= s.range[0]) & (d <= s.range[1]) & (vol.labels == 0))
        for s in spec.structures
    ]  # fmt: skip


def _max_diff(a, b) -> float:
    return max(
        float(np.abs(getattr(a, f).astype(np.float64) - getattr(b, f).astype(np.float64)).max())
        for f in BUFFERS
    )


def _terms(analysis, spec) -> dict:
    m = all_measures(analysis, spec)
    return {t: float(getattr(getattr(m, r), t)) for t, r in TERMS.items()}


#: Three brick sizes (cells z, y, x): the first cuts every structure into several bricks.
SIZES = ((5, 6, 7), (11, 17, 13), (29, 20, 37))


def test_the_smallest_bricks_cut_every_structure(scene):
    vol, spec, _ = scene
    small = np.array(SIZES[0])
    for s, idx in zip(spec.structures, _members(vol, spec), strict=True):
        assert len(idx) > 20, s.name  # the structure is there
        owners = {tuple(v) for v in np.minimum(idx, np.array(vol.data.shape) - 2) // small}
        assert len(owners) >= 4, s.name  # its voxels lie in several bricks


@pytest.mark.parametrize("view", [(30.0, 20.0, False), (-135.0, -35.0, True)])
def test_bricked_equals_whole_at_three_brick_sizes(scene, view):
    """Every buffer the measures read and every E term within 1e-6, shaded, with curvature."""
    vol, spec, curv = scene
    cam = Camera.from_view(vol.bounds, width=40, height=36, azimuth=view[0], elevation=view[1])
    if view[2]:
        cam = Camera(cam.position, cam.focal_point, cam.view_up, parallel_projection=True,
                     parallel_scale=24.0, width=40, height=36)  # fmt: skip
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    assert whole.stats.get("bricks", 0) == 0  # the whole volume at once
    assert (whole.visible.reshape(3, -1).max(axis=1) > 0.05).all()  # every structure seen
    assert whole.curvature.max() > 0.0
    e_whole = _terms(whole, spec)
    measured = analyze(vol, spec, cam, curvature=curv, build_cache=False)
    ops = (0.2, 0.9, 0.5)
    for size in SIZES:
        parts = analyze(vol, spec, cam, curvature=curv, brick=size, build_cache=True)
        assert parts.stats["bricks"] == len(bricks.split(vol.data.shape, size)) > 1
        assert _max_diff(whole, parts) <= 1e-6, size
        assert np.array_equal(whole.cache.count, parts.cache.count)
        e_parts = _terms(parts, spec)
        for t in TERMS:
            assert abs(e_whole[t] - e_parts[t]) <= 1e-6, (size, t)
        # what ``measure`` analyses (no cache), and a re-evaluation of the bricked cache
        part_m = analyze(vol, spec, cam, curvature=curv, build_cache=False, brick=size)
        assert _max_diff(measured, part_m) <= 1e-6, size
        assert _max_diff(reevaluate(whole.cache, opacities=ops),
                         reevaluate(parts.cache, opacities=ops)) <= 1e-6  # fmt: skip
    # the image alone (rays stop at early termination): the same pixels
    render = analyze(vol, spec, cam, build_cache=False, occlusion_free=False)
    for size in SIZES:
        got = analyze(vol, spec, cam, build_cache=False, occlusion_free=False, brick=size)
        assert np.abs(got.rgba - render.rgba).max() <= 1e-6
        assert np.abs(got.visible - render.visible).max() <= 1e-6
        if size == SIZES[0]:  # bricks behind every ray's termination are not walked
            assert 0 < got.stats["bricks"] < len(bricks.split(vol.data.shape, size))


def test_kept_curvature_pieces_follow_their_array(scene):
    """A whole-volume curvature array's pieces are kept between analyses, for that array only."""
    vol, spec, curv = scene
    cam = Camera.from_view(vol.bounds, width=32, height=32, azimuth=60.0, elevation=15.0)
    bricks._MEMO.pop(vol, None)
    first = analyze(vol, spec, cam, curvature=curv, build_cache=False, brick=SIZES[1])
    assert len(bricks._MEMO[vol]["curvature"]) == len(bricks.split(vol.data.shape, SIZES[1]))
    other = (curv * 2.0).astype(np.float32)  # another array: its own pieces
    got = analyze(vol, spec, cam, curvature=other, build_cache=False, brick=SIZES[1])
    want = analyze(vol, spec, cam, curvature=other, build_cache=False)
    assert np.abs(got.curvature - want.curvature).max() <= 1e-6
    assert got.curvature.max() > 1.5 * first.curvature.max() > 0.0
    bricks._MEMO.pop(vol, None)


def test_a_lazily_shaded_bricked_cache_reevaluates_as_the_whole_one(scene):
    """Entries behind termination are shaded when compositing can first reach them."""
    from dvr_perception.rays._numba_kernels import _UNSET

    vol, spec, curv = scene
    cam = Camera.from_view(vol.bounds, width=36, height=36, azimuth=-70.0, elevation=30.0)
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    parts = analyze(vol, spec, cam, curvature=curv, brick=SIZES[0], build_cache=True)
    z = parts.cache.lazy
    assert z["fill"] is not None  # the codes are kept: shaded lazily
    unset = int(np.count_nonzero(parts.cache.shading[:, 0] == _UNSET))
    assert 0 < unset < len(parts.cache.lut)  # the walk shaded what it composited, only that
    no_curv = int(np.count_nonzero(parts.cache.curvature < 0.0))
    assert 0 < no_curv <= unset  # the curvature pieces are kept: their lookups lazy too
    steps = [
        {"opacities": (1.0, 1.0, 1.0)},  # reaches less: nothing new to shade
        {"opacities": (0.05, 0.3, 0.02)},  # reaches further back
        {"light_direction": (0.5, -0.4, 0.75)},  # every entry's shading anew, lazily
        {"opacities": (0.01, 0.01, 0.01), "light_direction": (0.5, -0.4, 0.75)},
    ]
    for kw in steps:
        a, b = reevaluate(whole.cache, **kw), reevaluate(parts.cache, **kw)
        assert _max_diff(a, b) <= 1e-6, kw
        assert b.visible.sum() > 0.0
    left = int(np.count_nonzero(parts.cache.shading[:, 0] == _UNSET))
    assert left < unset  # the low opacities reached entries the walk had not shaded
    assert int(np.count_nonzero(parts.cache.curvature < 0.0)) < no_curv


def test_a_later_bricked_analysis_leaves_an_earlier_cache_alone(scene):
    """The bricks' entries go through reused memory; the merged cache is the analysis's own."""
    vol, spec, curv = scene
    cams = [Camera.from_view(vol.bounds, width=30, height=30, azimuth=a, elevation=10.0)
            for a in (20.0, 200.0)]  # fmt: skip
    first = analyze(vol, spec, cam := cams[0], curvature=curv, brick=SIZES[1], build_cache=True)
    lut = first.cache.lut.copy()
    analyze(
        vol, spec, cams[1], curvature=curv, brick=SIZES[1], build_cache=True
    )  # reuses the memory
    analyze(vol, spec, cams[1], curvature=curv, brick=SIZES[0], build_cache=True)
    assert np.array_equal(first.cache.lut, lut)
    whole = analyze(vol, spec, cam, curvature=curv, build_cache=True)
    ops = (0.6, 0.1, 0.3)
    assert _max_diff(reevaluate(whole.cache, opacities=ops),
                     reevaluate(first.cache, opacities=ops)) <= 1e-6  # fmt: skip
