"""The benchmark report of ``dvr_perception`` (issue 8): the paper's experiments on real data.

``python -m benchmarks.report`` or ``dvr-perception report`` regenerates ``REPORT.md``,
``summary.json`` and ``images/`` (see :mod:`benchmarks.report`).
"""
