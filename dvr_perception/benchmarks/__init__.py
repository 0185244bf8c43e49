"""The benchmark report of ``dvr_perception`` (issue 8): the paper's experiments on real data.

It ships in the package, so ``dvr-perception report`` works from an installed wheel too; the
repository's ``benchmarks/`` folder holds the last report (``REPORT.md``, ``summary.json``,
``images/``) and the developer tools that need a checkout (``scale.py``, ``cross_env.py``).

``dvr-perception report`` (or ``python -m dvr_perception.benchmarks.report``) regenerates
``REPORT.md``,
``summary.json`` and ``images/`` (see :mod:`dvr_perception.benchmarks.report`).
"""
