"""Shared fixtures.

Tests that need ``../shared/data`` use the ``shared_data`` fixture: it skips on a developer
machine without the data but *fails* under ``CI=true``, where a skip would hide a regression.
Tests that render with VTK use ``vtk_can_render`` with the same policy.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
IN_CI = os.environ.get("CI", "").lower() in ("1", "true", "yes")
# backend="auto" stays on the CPU in the tests, also on a machine with a GPU: many compare
# analyses bit for bit, which a GPU's fused multiply-add need not keep; the CUDA back end's
# own tests ask for backend="cuda" (tests/rays/test_cuda_sim.py)
os.environ.setdefault("DVR_PERCEPTION_NO_CUDA", "1")


def _missing(reason: str) -> None:
    if IN_CI:
        pytest.fail(f"required under CI=true: {reason}")
    pytest.skip(reason)


def shared_data_path() -> Path:
    """Where the shared datasets live (``DVR_SHARED_DATA`` or ``<repo>/../shared/data``)."""
    env = os.environ.get("DVR_SHARED_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


@pytest.fixture(scope="session")
def shared_data() -> Path:
    """Directory holding the shared ``*.nhdr`` + ``*.raw`` volumes."""
    path = shared_data_path()
    if not (path / "MANIFEST.md").is_file():
        _missing(f"shared data not found at {path}")
    return path


@pytest.fixture(scope="session")
def vtk_can_render() -> bool:
    """True when VTK can render off-screen; skips (fails under CI) otherwise."""
    from dvr_perception._vtk import can_render

    ok, why = can_render()
    if not ok:
        _missing(why)
    return True


def _shell_scene(shade: bool, inner: float = 8.5):
    """A faint shell (label 1) around two blobs of different grey: an encloser over contrast.

    24^3 labels: the shell between radii ``inner`` and 10.5, a light and a dark box inside.
    """
    import numpy as np

    from dvr_perception.structures.spec import RenderSettings, Structure, StructureSpec
    from dvr_perception.volume.volume import Volume

    n = 24
    z, y, x = np.mgrid[:n, :n, :n].astype(float) - (n - 1) / 2
    r = np.sqrt(x * x + y * y + z * z)
    lab = np.zeros((n, n, n), np.uint8)
    lab[(r > inner) & (r < 10.5)] = 1
    lab[(np.abs(z) < 4) & (np.abs(y) < 4) & (x > -6) & (x < -1)] = 2
    lab[(np.abs(z) < 4) & (np.abs(y) < 4) & (x > 1) & (x < 6)] = 3
    data = (lab * 40 + 10).astype(np.uint8)
    spec = StructureSpec(
        (
            Structure("shell", 0.3, (0.9, 0.8, 0.7), label=1),
            Structure("light", 1.0, (0.9, 0.9, 0.9), label=2),
            Structure("dark", 1.0, (0.2, 0.2, 0.3), label=3),
        ),
        rendering=RenderSettings(shade=shade),
    )
    return Volume(data, labels=lab), spec


@pytest.fixture
def shell_scene():
    """``shell_scene(shade, inner=8.5)``: (volume, spec) of a shell around two blobs."""
    return _shell_scene


def _noisy_blobs(shape=(18, 30, 26), spacing=(1.0, 1.0, 2.0), seed=3, labels=False):
    """Two soft balls and a slab, with noise (boundaries cross brick and page edges)."""
    import numpy as np

    from dvr_perception.volume.volume import Volume

    rng = np.random.default_rng(seed)
    z, y, x = np.mgrid[: shape[0], : shape[1], : shape[2]].astype(np.float64)
    z = z * spacing[2] / spacing[0]
    f = 1000 / (1 + np.exp((np.sqrt((z - 14) ** 2 + (y - 12) ** 2 + (x - 10) ** 2) - 8) / 1.5))
    f += 2000 / (1 + np.exp((np.sqrt((z - 20) ** 2 + (y - 20) ** 2 + (x - 18) ** 2) - 5) / 1.2))
    f += 300 * (y > 25)
    f += rng.normal(0, 20, shape)
    lab = None
    if labels:  # a label ball
        lab = (np.sqrt((z - 10) ** 2 + (y - 18) ** 2 + (x - 6) ** 2) < 6).astype(np.uint8) * 3
    return Volume(np.clip(f, 0, 4000).astype(np.uint16), spacing=spacing, labels=lab)


@pytest.fixture
def noisy_blobs():
    """``noisy_blobs(shape=, spacing=, seed=, labels=False)``: a uint16 volume of soft blobs."""
    return _noisy_blobs
