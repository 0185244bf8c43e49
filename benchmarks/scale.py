"""Time and memory against volume size, and ParaView's MPI ranks (issue 17): ``scale.json``.

Run as ``python -m benchmarks.scale --data ../shared/data --out benchmarks/scale.json``
(``make scale``).  Every figure comes from a separate process, so each peak RSS is that run's
own (its ``VmHWM``):

* **sizes** - cthead at every other voxel, as stored, and up-sampled (linear interpolation,
  :func:`dvr_perception.volume.resample.upsample`) by 2×2×2 and 2×2×4 (512 × 512 × 452, the
  size of a clinical CT): ``dvr-perception bench --optimize`` (frame, VTK's frame, curvature,
  one optimisation, peak RSS) and ``dvr-perception optimize`` end to end (wall time and peak
  RSS of the whole command, figures written);
* **ranks** - ``dvr-perception pvbatch VOLUME --ranks N`` for N = 1, 2, 4 on the largest
  size: wall time, E terms, and per rank its extent, voxels and peak RSS (``result.json``).

On a 2-core machine 4 ranks share 2 cores: the figures show what is bounded by memory per
rank (it falls with N), not a speed-up.  the report code
(``dvr_perception.benchmarks.report``) renders ``scale.json`` into the report's performance section.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
#: (label, up-sampling factors x, y, z; None: every other voxel)
SIZES = (("cthead /2", None), ("cthead", (1, 1, 1)), ("cthead up 2,2,2", (2, 2, 2)),
         ("cthead up 2,2,4", (2, 2, 4)))  # fmt: skip
RANKS = (1, 2, 4)


def _hwm_mb(pid: int) -> float:
    """Return the peak RSS so far (``VmHWM``, MB; its own memory since ``exec``), or 0."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
    except OSError:
        pass
    return 0.0


def _run(argv: list[str], *, cwd=REPO, timeout: float = 3600.0) -> dict:
    """Run ``argv``; return its wall time, peak RSS (MB), exit code, stdout and stderr's end.

    The peak is the process's ``VmHWM`` read every 20 ms while it runs (a high-water mark,
    so the last reading holds the peak up to then).  Not ``wait4``'s ``ru_maxrss``: that
    also counts the parent's memory the child shared between fork and ``exec``.
    """
    t0 = time.perf_counter()
    peak = 0.0
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        p = subprocess.Popen(argv, cwd=cwd, stdout=out, stderr=err, text=True)
        deadline = t0 + timeout
        while True:
            peak = max(peak, _hwm_mb(p.pid))  # zombie or gone: 0, the maximum stays
            if p.poll() is not None:
                break
            if time.perf_counter() > deadline:
                p.kill()
                p.wait()
                break
            time.sleep(0.02)
        wall = time.perf_counter() - t0
        out.seek(0)
        err.seek(0)
        return {"rc": p.returncode, "wall_s": wall, "peak_rss_mb": peak, "stdout": out.read(),
                "stderr": err.read()[-2000:]}  # fmt: skip


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-c", "from dvr_perception.cli import main; raise SystemExit(main())",
            *args]  # fmt: skip


def _volumes(data: Path, folder: Path) -> list[tuple[str, Path]]:
    """Write the sized volumes into ``folder``; ``[(label, path)]``."""
    from dvr_perception.volume import Volume, load_volume, save_volume
    from dvr_perception.volume.resample import upsample

    ct = load_volume(data / "cthead.nhdr")
    out = []
    for label, factors in SIZES:
        if factors is None:
            vol = Volume(np.ascontiguousarray(ct.data[::2, ::2, ::2]),
                         tuple(2 * s for s in ct.spacing), ct.origin)  # fmt: skip
        else:
            vol = ct if factors == (1, 1, 1) else upsample(ct, factors)
        path = folder / f"cthead_{'x'.join(map(str, vol.dims))}.nhdr"
        save_volume(vol, path)
        out.append((label, path))
    return out


def measure_sizes(volumes, spec: Path, size: int, scratch: Path, log) -> list[dict]:
    """``bench --optimize`` and ``optimize`` end to end per volume."""
    rows = []
    for label, path in volumes:
        log(f"bench --optimize {path.name}")
        b = _run(_cli("bench", str(path), "--structures", str(spec), "--size", str(size),
                      "--repeat", "1", "--optimize", "--json"))  # fmt: skip
        bench = json.loads(b["stdout"]) if b["rc"] == 0 else {"error": b["stderr"]}
        log(f"optimize {path.name}")
        o = _run(_cli("optimize", str(path), "--structures", str(spec), "--size", str(size),
                      "--out", str(scratch / f"opt_{path.stem}")))  # fmt: skip
        keep = ("dims", "load_s", "curvature_s", "frame_s", "vtk_frame_s", "frame_ratio",
                "render_ratio", "optimize_s", "optimize_vtk_frames", "curvature_vtk_frames",
                "peak_rss_mb", "error")  # fmt: skip
        row = {"label": label, "volume": path.name, **{k: bench[k] for k in keep if k in bench}}
        row["voxels"] = int(np.prod(row["dims"])) if "dims" in row else None
        row["optimize_e2e_s"] = o["wall_s"] if o["rc"] == 0 else None
        row["optimize_e2e_peak_rss_mb"] = o["peak_rss_mb"] if o["rc"] == 0 else None
        if o["rc"] != 0:
            row["optimize_error"] = o["stderr"]
        rows.append(row)
        log(json.dumps({k: row.get(k) for k in ("label", "frame_s", "optimize_e2e_s",
                                                 "optimize_e2e_peak_rss_mb")}))  # fmt: skip
    return rows


def measure_ranks(path: Path, spec: Path, size: int, ranks, scratch: Path, log) -> list[dict]:
    """``pvbatch --ranks N`` on ``path``."""
    rows = []
    for n in ranks:
        log(f"pvbatch --ranks {n} {path.name}")
        out = scratch / f"pv_{n}"
        r = _run(_cli("pvbatch", str(path), "--structures", str(spec), "--size", str(size),
                      "--ranks", str(n), "--out", str(out)))  # fmt: skip
        row = {"ranks": n, "volume": path.name, "wall_s": r["wall_s"]}
        if r["rc"] != 0:
            row["error"] = r["stderr"]
        else:
            res = json.loads((out / "result.json").read_text(encoding="utf-8"))
            row["E"] = {k: res.get(k) for k in ("E_v", "E_s", "E_t")}
            row["per_rank"] = res.get("ranks", [])
        rows.append(row)
    return rows


def main(argv=None) -> int:
    """Write ``scale.json``."""
    p = argparse.ArgumentParser(prog="python -m benchmarks.scale", description=__doc__)
    p.add_argument("--data", default=str(REPO.parent / "shared" / "data"))
    p.add_argument("--out", default=str(REPO / "benchmarks" / "scale.json"))
    p.add_argument("--size", type=int, default=512, help="image size (default 512)")
    p.add_argument("--ranks", default=",".join(map(str, RANKS)), help="MPI ranks (1,2,4)")
    p.add_argument("--no-mpi", action="store_true", help="skip the pvbatch runs")
    args = p.parse_args(argv)
    from dvr_perception._files import write_json

    def log(msg):
        print(f"scale: {msg}", file=sys.stderr, flush=True)

    spec = REPO / "state_files" / "cthead.json"
    with tempfile.TemporaryDirectory(prefix="dvr_scale_") as tmp:
        scratch = Path(tmp)
        volumes = _volumes(Path(args.data), scratch)
        sizes = measure_sizes(volumes, spec, args.size, scratch, log)
        ranks = []
        if not args.no_mpi:
            counts = [int(n) for n in args.ranks.split(",")]
            ranks = measure_ranks(volumes[-1][1], spec, args.size, counts, scratch, log)
    report = {"size": args.size, "cpus": os.cpu_count(), "sizes": sizes, "ranks": ranks,
              "when": time.strftime("%Y-%m-%d %H:%M")}  # fmt: skip
    write_json(args.out, report)
    log(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
