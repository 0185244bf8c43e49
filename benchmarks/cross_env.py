"""ParaView's E terms against the venv's on the shared volumes (issue 18.5): a table.

Run as ``python -m benchmarks.cross_env --data ../shared/data --size 256 --out xenv.jsonl``.
For every ``*.nhdr`` in ``--data`` with its preset spec ``state_files/NAME.json``, at the
preset's view and at ``--view`` (default 60,20), it runs ``dvr-perception measure --json`` (this
venv) and ``dvr-perception pvbatch --json --no-screenshot`` (ParaView's pvbatch, numpy 1.24),
writes one JSON line per scene (both E triples and ``dE`` = |ParaView - venv| per term) and
prints a Markdown table with the largest |dE| per term.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TERMS = ("E_v", "E_s", "E_t")


def _run(cmd: list[str], env: dict) -> dict:
    """Run one ``dvr-perception`` command; return its E terms (or the error it printed)."""
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=REPO, check=False)
    try:
        out = json.loads(proc.stdout.strip().splitlines()[-1])
        return {k: out[k] for k in TERMS}
    except (IndexError, KeyError, ValueError):
        return {"error": (proc.stdout + proc.stderr)[-500:]}


def measure(data: Path, size: int, view: str, out: Path, pattern: str = "*.nhdr") -> list[dict]:
    """Measure every volume in ``data`` at the preset's view and ``view``; return the rows."""
    env = dict(
        os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])
    )
    cli = [sys.executable, "-c", "from dvr_perception.cli import main; raise SystemExit(main())"]
    rows = []
    with out.open("w") as fh, tempfile.TemporaryDirectory() as tmp:
        for path in sorted(data.glob(pattern)):
            spec = REPO / "state_files" / f"{path.stem}.json"
            for v in (None, view):
                args = [str(path), "--structures", str(spec), "--size", str(size), "--json"]
                args += [f"--view={v}"] if v else []
                row = {"volume": path.stem, "view": v or "preset"}
                row["venv"] = _run([*cli, "measure", *args], env)
                pv_out = str(Path(tmp) / f"{path.stem}_{v}")
                pv = [*cli, "pvbatch", *args, "--no-screenshot", "--out", pv_out]
                row["pv"] = _run(pv, env)
                if "error" not in row["venv"] and "error" not in row["pv"]:
                    row["dE"] = {k: abs(row["pv"][k] - row["venv"][k]) for k in TERMS}
                fh.write(json.dumps(row) + "\n")
                fh.flush()
                rows.append(row)
    return rows


def table(rows: list[dict]) -> str:
    """Return the Markdown table of ``rows`` and the largest |dE| per term."""
    lines = [
        "| volume | view | E_v | E_s | E_t | abs dE_v | abs dE_s | abs dE_t |",
        "|---|---|---|---|---|---|---|---|",
    ]
    worst = dict.fromkeys(TERMS, 0.0)
    for r in rows:
        if "dE" not in r:
            lines.append(f"| {r['volume']} | {r['view']} | failed: {r} |")
            worst = dict.fromkeys(TERMS, float("nan"))
            continue
        e, d = r["venv"], r["dE"]
        worst = {k: max(worst[k], d[k]) for k in TERMS}
        lines.append(
            f"| {r['volume']} | {r['view']} | "
            + " | ".join(f"{e[k]:.6f}" for k in TERMS)
            + " | "
            + " | ".join(f"{d[k]:.1e}" for k in TERMS)
            + " |"
        )
    lines.append("max |dE|: " + ", ".join(f"{k} {worst[k]:.1e}" for k in TERMS))
    return "\n".join(lines)


def main(argv=None) -> int:
    """Parse the options, measure, print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--view", default="60,20", help="the second view (A,E[,Z])")
    parser.add_argument("--out", type=Path, default=Path("cross_env.jsonl"))
    parser.add_argument("--volumes", default="*.nhdr", help="file pattern in --data")
    parser.add_argument("--table", action="store_true", help="only print the table of --out")
    args = parser.parse_args(argv)
    if args.table:
        rows = [json.loads(line) for line in args.out.read_text().splitlines() if line]
    else:
        rows = measure(args.data, args.size, args.view, args.out, args.volumes)
    print(table(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
