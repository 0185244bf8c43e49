"""How often ParaView aborts with "bad X server connection" on a private Xvfb (JSON out).

Launches ``mpiexec -n RANKS pvbatch`` on a tiny rendering N times on one display from
:func:`dvr_perception.cli.xdisplay.virtual_display`, once with the server as the app starts it
(``-noreset``) and, with ``--compare``, once with a stock server (which resets when its last
client leaves and refuses the clients connecting meanwhile).  Needs ParaView, Open MPI and
Xvfb (``make paraview-setup``)::

    .venv/bin/python -m benchmarks.xdisplay_stress --launches 40 --compare

Measured here (session 16), two ranks: a stock server aborted 3 and 8 launches of 40 (and 2 of
6), one with ``-noreset`` 0 of 40 each time.
"""

from __future__ import annotations

import argparse
import json
import random
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from dvr_perception.cli import xdisplay
from dvr_perception.cli.pvbatch import find_paraview, mpi_command, paraview_env

_SCRIPT = """from paraview.simple import Render, SaveScreenshot, Show, Sphere
Sphere()
Show()
Render()
SaveScreenshot({png!r}, ImageResolution=[64, 64])
"""


def stress(launches: int, ranks: int, *, reset: bool) -> dict:
    """Launch the rendering ``launches`` times on one display; count the failed launches."""
    args = xdisplay._SERVER_ARGS
    if reset:  # a stock server: without -noreset
        xdisplay._SERVER_ARGS = tuple(a for a in args if a != "-noreset")
    try:
        with tempfile.TemporaryDirectory(prefix="dvr-xstress-") as tmp:
            script = Path(tmp) / "render.py"
            script.write_text(_SCRIPT.format(png=str(Path(tmp) / "out.png")), encoding="utf-8")
            pvbatch = find_paraview("pvbatch")
            env = paraview_env()
            prefix = mpi_command(ranks, pvbatch, env) if ranks > 1 else []
            failed = x_aborts = 0
            t0 = time.perf_counter()
            with xdisplay.virtual_display(rng=random.Random(1)) as display:
                env["DISPLAY"] = display
                for _ in range(launches):
                    proc = subprocess.run(
                        [*prefix, str(pvbatch), str(script)],
                        env=env,
                        capture_output=True,
                        text=True,
                        check=False,
                    )
                    failed += proc.returncode != 0
                    x_aborts += "bad X server connection" in proc.stderr
    finally:
        xdisplay._SERVER_ARGS = args
    return {
        "server": "stock (resets)" if reset else "-noreset",
        "ranks": ranks,
        "launches": launches,
        "failed": failed,
        "x_aborts": x_aborts,
        "seconds": round(time.perf_counter() - t0, 1),
    }


def main(argv=None) -> int:
    """Run the stress test and print one JSON object per server."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--launches", type=int, default=40)
    parser.add_argument("--ranks", type=int, default=2)
    parser.add_argument("--compare", action="store_true", help="also run a stock server")
    args = parser.parse_args(argv)
    runs = [False, True] if args.compare else [False]
    for reset in runs:
        print(json.dumps(stress(args.launches, args.ranks, reset=reset)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
