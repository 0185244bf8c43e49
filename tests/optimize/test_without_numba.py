"""Without numba the whole pipeline (engine, measures, optimiser) still runs, in numpy/Python."""

from __future__ import annotations

import json
import subprocess
import sys

SCRIPT = """
import json, sys
sys.modules["numba"] = None  # any "import numba" now raises ImportError
from dvr_perception.optimize import optimize
from dvr_perception.rays.camera import Camera
from dvr_perception.structures import make_phantom
vol, spec = make_phantom(size=24)
cam = Camera.from_view(vol.bounds, width=16, height=16)
res = optimize(vol, spec, cam, stages=("opacity",), max_iter=1, resolution=16)
print(json.dumps({"before": res.initial["E"], "after": res.final["E"], "status": res.status,
                  "numba_loaded": sys.modules.get("numba") is not None}))
"""


def test_optimize_runs_without_numba():
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=600, check=False
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["numba_loaded"] is False
    assert 0.0 <= out["after"] <= out["before"] + 1e-9  # never worse than the start
