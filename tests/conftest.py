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
