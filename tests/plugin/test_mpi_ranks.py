"""Each MPI rank its piece: ``dvr-perception pvbatch --ranks N`` equals the serial run.

``mpiexec -n N pvbatch``: every rank reads its piece of the volume (plus ghost layers) through
ParaView's reader, the ranks walk their bricks in view order and rank 0 measures.  The E terms
equal those of the serial ``dvr-perception pvbatch`` within 1e-5 (in practice exactly), and no
rank holds more than 60 % (2 ranks) / 35 % (4 ranks) of the voxels.  Also the communication
helpers of :mod:`dvr_perception.parallel` over ParaView's ``vtkMultiProcessController``.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest

from dvr_perception.cli import main
from dvr_perception.cli.pvbatch import mpi_command, virtual_display

REPO = Path(__file__).resolve().parents[2]
SIZE = 48
#: The largest share of the voxels one rank may hold (issue 17).
MAX_SHARE = {2: 0.60, 4: 0.35}
_SERIAL: dict = {}


@pytest.fixture(scope="module")
def volumes(shared_data, tmp_path_factory):
    """fuel, neghip and cthead resampled to half its resolution (57 x 128 x 128, uint16)."""
    from dvr_perception.volume import Volume, load_volume, save_volume

    folder = tmp_path_factory.mktemp("cthead_half")
    ct = load_volume(shared_data / "cthead.nhdr")
    half = Volume(
        np.ascontiguousarray(ct.data[::2, ::2, ::2]),
        tuple(2 * s for s in ct.spacing),
        ct.origin,
    )
    path = folder / "cthead_half.nhdr"
    save_volume(half, path)
    return {
        "fuel": (shared_data / "fuel.nhdr", REPO / "state_files" / "fuel.json"),
        "neghip": (shared_data / "neghip.nhdr", REPO / "state_files" / "neghip.json"),
        "cthead_half": (path, REPO / "state_files" / "cthead.json"),
    }


#: A run that hangs fails the test instead of blocking the suite (alone: 10-30 s a run).
TIMEOUT = 300


def _pvbatch(volume, spec, out: Path, ranks: int, *extra: str) -> dict:
    argv = ["pvbatch", str(volume), "--structures", str(spec), "--size", str(SIZE)]
    argv += ["--timeout", str(TIMEOUT), *extra]
    assert main([*argv, "--ranks", str(ranks), "--out", str(out)]) == 0
    return json.loads((out / "result.json").read_text(encoding="utf-8"))


def _serial(name, volumes, tmp_path_factory) -> dict:
    if name not in _SERIAL:
        volume, spec = volumes[name]
        _SERIAL[name] = _pvbatch(volume, spec, tmp_path_factory.mktemp(f"{name}_1"), 1)
    return _SERIAL[name]


#: ParaView's own parallel screenshot of cthead_half deadlocks now and then (3 of 6 runs on
#: 2026-12-03, at 4 and at 2 ranks; never seen with fuel or neghip): rank 0 waits in an
#: all-gather of ``vtkPVRenderViewDataDeliveryManager::RedistributeDataForOrderedCompositing``
#: while the other ranks already wait for the next RMI (ParaView 5.11's ordered compositing,
#: after our filter has finished).  Those cases run without the screenshot
#: (``--no-screenshot``); the measures are what the test checks.
NO_SCREENSHOT = {("cthead_half", 2), ("cthead_half", 4)}


@pytest.mark.slow
# 4 ranks on 2 cores: the ranks waiting for their turn sleep in MPI_Iprobe instead of polling
# (parallel.VTKCommunicator), each rank runs max(1, cores // ranks) numba threads and the
# kernels are compiled before mpiexec starts (ranks.warm_up); under a busy core each 4-rank run
# here took 60-80 s with its serial run, a hang fails after TIMEOUT with the job killed
@pytest.mark.parametrize("ranks", [2, 4])
@pytest.mark.parametrize("name", ["fuel", "neghip", "cthead_half"])
def test_each_rank_reads_its_piece_and_the_measures_equal_the_serial_run(
    mpiexec, volumes, tmp_path, tmp_path_factory, name, ranks
):
    serial = _serial(name, volumes, tmp_path_factory)
    assert "ranks" not in serial
    volume, spec = volumes[name]
    shot = (name, ranks) not in NO_SCREENSHOT
    got = _pvbatch(volume, spec, tmp_path / "out", ranks, *(() if shot else ("--no-screenshot",)))
    for key in ("E_v", "E_s", "E_t"):
        assert got[key] == pytest.approx(serial[key], abs=1e-5), key
    for s, values in serial["structures"].items():
        for key, value in values.items():
            if key == "assigned_share":  # the thickness share, reported, read on each walk:
                continue  # the serial analysis skips behind termination (capped at
                # saturation, D8), the ranks' session builds caches (the exact walk)
            assert got["structures"][s][key] == pytest.approx(value, abs=1e-5, nan_ok=True)
    records = got["ranks"]
    assert [r["rank"] for r in records] == list(range(ranks))
    assert sorted(r["order"] for r in records) == list(range(ranks))
    whole = None
    for r in records:
        x0, x1, y0, y1, z0, z1 = r["extent"]
        assert r["voxels"] == (x1 - x0 + 1) * (y1 - y0 + 1) * (z1 - z0 + 1)
        assert r["peak_rss_mb"] > 0
        cells = np.prod([c1 - c0 for c0, c1 in r["cells"]])
        whole = cells if whole is None else whole + cells
    # the bricks partition the cells; each rank holds at most its share of the voxels
    dims = _dims(volume)
    assert whole == np.prod([d - 1 for d in dims])
    for r in records:
        assert r["voxels"] / np.prod(dims) <= MAX_SHARE[ranks], r
    assert {"image.png", "result.json"} <= set(got["files"])
    assert ("screenshot.png" in got["files"]) == shot


def _dims(path: Path) -> tuple[int, ...]:
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("sizes:"):
            return tuple(int(v) for v in line.split(":")[1].split())
    raise AssertionError(f"{path}: no sizes")


COMM_SCRIPT = """
import json
import numpy as np
from dvr_perception.parallel import VTKCommunicator, communicator, peak_rss_mb

c = communicator()
assert isinstance(c, VTKCommunicator), type(c)
lo, hi = c.allreduce_min_max(-c.rank, 10 * c.rank)
b = c.broadcast({"x": np.arange(5, dtype=np.uint16), "y": np.eye(2)} if c.rank == 0 else None)
# a ring of dicts of arrays (several MB, the size of a 512^2 ray state)
ring = {"st": np.full((200_000, 7), float(c.rank)), "bits": np.arange(3, dtype=np.uint32) + c.rank}
nxt, prv = (c.rank + 1) % c.size, (c.rank - 1) % c.size
if c.rank == 0:
    c.send(ring, nxt)
    got = c.recv(prv)
else:
    got = c.recv(prv)
    c.send(ring, nxt)
records = c.gather({
    "rank": c.rank, "size": c.size, "lo": lo, "hi": hi, "x": b["x"].tolist(),
    "y": b["y"].tolist(), "from": float(got["st"][0, 0]), "st": list(got["st"].shape),
    "bits": got["bits"].tolist(), "rss": peak_rss_mb(),
})
every = c.allgather(c.rank * 2)
if c.rank == 0:
    print("@@RESULT@@ " + json.dumps({"records": records, "every": every}), flush=True)
"""


def test_communicator_over_paraviews_mpi(mpiexec, tmp_path):
    script = tmp_path / "comm.py"
    script.write_text(COMM_SCRIPT, encoding="utf-8")
    env = dict(mpiexec.env)
    cmd = [*mpi_command(2, mpiexec.pvbatch, env), str(mpiexec.pvbatch), "--symmetric", str(script)]
    proc = subprocess.run(
        cmd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        timeout=300,
        check=False,
        cwd=tmp_path,
    )
    got = mpiexec.result(proc)
    assert got["every"] == [0, 2]
    r0, r1 = got["records"]
    for r in (r0, r1):
        assert (r["size"], r["lo"], r["hi"]) == (2, -1.0, 10.0)
        assert r["x"] == [0, 1, 2, 3, 4]
        assert r["y"] == [[1.0, 0.0], [0.0, 1.0]]
        assert r["st"] == [200_000, 7]
        assert r["rss"] > 0
    assert (r0["from"], r0["bits"]) == (1.0, [1, 2, 3])
    assert (r1["from"], r1["bits"]) == (0.0, [0, 1, 2])


def test_ranks_must_match_mpiexec(mpiexec, tmp_path, volumes):
    """pvbatch started without mpiexec but told --ranks 2: one line, exit 2."""
    volume, spec = volumes["neghip"]
    env = dict(mpiexec.env)
    script = REPO / "dvr_perception" / "paraview" / "batch_measure.py"
    argv = [str(volume), "--structures", str(spec), "--ranks", "2", "--out", str(tmp_path)]
    with virtual_display() as display:
        proc = subprocess.run(
            [str(mpiexec.pvbatch), str(script), *argv],
            env=dict(env, DISPLAY=display),
            capture_output=True,
            text=True,
            timeout=300,
            check=False,
        )
    assert proc.returncode == 2, proc.stderr
    assert "--ranks 2: pvbatch runs on 1 MPI rank(s)" in proc.stderr


ABORT_SCRIPT = """
import time
from dvr_perception.errors import DVRInputError
from dvr_perception.parallel import abort_on_error, communicator

c = communicator()
with abort_on_error(c, "abort test"):
    if c.rank == 1:
        raise DVRInputError("rank 1 fails after the ranks started exchanging")
    c.recv(1)  # rank 0 waits for a message rank 1 never sends
print("@@NOT REACHED", flush=True)
"""


def test_an_error_on_one_rank_ends_the_whole_job(mpiexec, tmp_path):
    """Rank 1 raises while rank 0 waits for it: the job ends with one line and status 2."""
    import time

    from dvr_perception.cli.pvbatch import run_job

    script = tmp_path / "abort.py"
    script.write_text(ABORT_SCRIPT, encoding="utf-8")
    env = dict(mpiexec.env)
    cmd = [*mpi_command(2, mpiexec.pvbatch, env), str(mpiexec.pvbatch), "--symmetric", str(script)]
    t0 = time.perf_counter()
    proc = run_job(cmd, env, 120, "abort test")
    assert time.perf_counter() - t0 < 100
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert "@@NOT REACHED" not in proc.stdout
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("dvr-perception: error:")]
    assert lines == [
        "dvr-perception: error: abort test (rank 1): rank 1 fails after the ranks started "
        "exchanging"
    ]


def test_a_job_over_its_timeout_is_killed_with_a_clear_error(mpiexec, tmp_path):
    """``run_job`` kills mpiexec and every rank (its process group) after the timeout."""
    from dvr_perception.cli.pvbatch import run_job

    script = tmp_path / "hang.py"
    script.write_text("import time\ntime.sleep(600)\n", encoding="utf-8")
    env = dict(mpiexec.env)
    cmd = [*mpi_command(2, mpiexec.pvbatch, env), str(mpiexec.pvbatch), "--symmetric", str(script)]
    with pytest.raises(RuntimeError, match=r"hang test did not finish within 20 s \(--timeout\)"):
        run_job(cmd, env, 20, "hang test")
    left = subprocess.run(["pgrep", "-f", str(script)], capture_output=True, text=True)
    assert left.stdout.strip() == "", f"ranks left running: {left.stdout}"
