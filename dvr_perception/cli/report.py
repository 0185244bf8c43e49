"""``dvr-perception report``: regenerate the benchmark report (the paper's Sec. 7 on real data).

The report code is :mod:`dvr_perception.benchmarks` (it ships in the package, an installed
wheel runs it too).  It writes ``REPORT.md``, ``summary.json`` and ``images/`` into ``--out``
(default: the checkout's ``benchmarks/`` folder, or ``./dvr_perception_report`` for an installed
package); ``--quick`` is the reduced form CI runs (128² images).  The acceptance checks are in
``summary.json`` under ``"checks"``; ``--strict`` makes a failed check exit with status 1.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from pathlib import Path

from dvr_perception import _resources
from dvr_perception._files import output_folder
from dvr_perception.cli._common import emit_json
from dvr_perception.errors import DVRInputError

__all__ = ["add_parser", "default_out", "load_benchmarks", "run"]

REPO = Path(__file__).resolve().parents[2]
QUICK_SIZE = 128

EXAMPLE = """examples:
  dvr-perception report --data ../shared/data --out benchmarks
  dvr-perception report --data ../shared/data --out /tmp/report --quick
"""


def default_data() -> Path:
    """``DVR_SHARED_DATA`` if set, else ``<repository>/../shared/data``."""
    env = os.environ.get("DVR_SHARED_DATA")
    return Path(env) if env else REPO.parent / "shared" / "data"


def default_out() -> Path:
    """Return the checkout's ``benchmarks/`` folder, or ``./dvr_perception_report``."""
    root = _resources.checkout_root()
    return root / "benchmarks" if root is not None else Path("dvr_perception_report")


def load_benchmarks():
    """Import and return the report module (:mod:`dvr_perception.benchmarks.report`)."""
    return importlib.import_module("dvr_perception.benchmarks.report")


def add_parser(subparsers, parents) -> None:
    """Register the ``report`` sub-command."""
    p = subparsers.add_parser(
        "report",
        parents=parents,
        help="regenerate the benchmark report (paper experiments, timings, checks)",
        description="Run the paper's experiments on the shared volumes and write the report.",
        epilog=EXAMPLE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--data",
        metavar="DIR",
        default=None,
        help="folder with the shared volumes (default: $DVR_SHARED_DATA or ../shared/data "
        "next to the repository)",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        default=str(default_out()),
        help="output folder for REPORT.md, summary.json and images/ (default: the checkout's "
        "benchmarks/, else ./dvr_perception_report)",
    )
    p.add_argument(
        "--size",
        type=int,
        default=None,
        metavar="N",
        help=f"image size NxN (default 512, or {QUICK_SIZE} with --quick)",
    )
    p.add_argument(
        "--quick",
        action="store_true",
        help=f"reduced form for CI ({QUICK_SIZE}² images, smaller timing sweeps)",
    )
    p.add_argument("--seed", type=int, default=0, help="optimiser seed (default 0)")
    p.add_argument("--strict", action="store_true", help="exit with status 1 if a check fails")
    p.add_argument(
        "--markdown-only",
        action="store_true",
        help="only rewrite OUT/REPORT.md from OUT/summary.json (e.g. after editing "
        "dvr_perception/benchmarks/observations.md); runs no experiment",
    )
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Execute ``report``."""
    size = args.size if args.size is not None else (QUICK_SIZE if args.quick else 512)
    if not 16 <= size <= 4096:
        raise DVRInputError(f"--size: expected an integer in 16..4096, got {size}")
    if args.seed < 0:
        raise DVRInputError(f"--seed: expected an integer >= 0, got {args.seed}")
    if args.markdown_only:
        if not (Path(args.out) / "summary.json").is_file():
            raise DVRInputError(f"--markdown-only: {Path(args.out) / 'summary.json'} not found")
        path = load_benchmarks().rerender(args.out)
        print(f"wrote {path}")
        return 0
    data = Path(args.data) if args.data is not None else default_data()
    missing = [n for n in ("cthead", "engine", "neghip", "lidc_chest")
               if not (data / f"{n}.nhdr").is_file()]  # fmt: skip
    if missing:
        raise DVRInputError(f"--data {data}: missing {', '.join(f'{n}.nhdr' for n in missing)}")
    report = load_benchmarks()
    from dvr_perception.benchmarks.experiments import Config

    def log(msg):
        if args.verbose:
            print(f"dvr-perception: report: {msg}", file=sys.stderr, flush=True)

    cfg = Config(data=data, size=size, quick=bool(args.quick), seed=int(args.seed))
    # staged: an interrupted or failed run leaves the folder as it was; a lock keeps a
    # second run out of it
    with output_folder(args.out) as staged:
        summary = report.build(cfg, staged.path, log=log, final=staged.final)
    out = Path(args.out)
    passed = sum(c["passed"] for c in summary["checks"])
    if args.json:
        emit_json(
            {
                "report": str(out / "REPORT.md"),
                "summary": str(out / "summary.json"),
                "seconds": summary["seconds"],
                "all_passed": summary["all_passed"],
                "checks": [
                    {k: c[k] for k in ("name", "passed", "detail")} for c in summary["checks"]
                ],
            }
        )
    else:
        for c in summary["checks"]:
            print(f"{'pass' if c['passed'] else 'FAIL'}  {c['name']}: {c['detail']}")
        print(
            f"{passed} of {len(summary['checks'])} checks passed; wrote {out / 'REPORT.md'} "
            f"in {summary['seconds']:.0f} s"
        )
    return 1 if args.strict and not summary["all_passed"] else 0
