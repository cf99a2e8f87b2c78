"""Run and comparison reports (HTML + PNG figures) computed from run files only.

A run directory holds ``config.toml``, ``estimates.parquet``, ``traffic.parquet``,
``summary.json`` and optionally ``features.parquet`` and ``association.parquet``
(columns in ``docs/outputs.md``).  :func:`write_run_report` turns one such directory into
``report.html`` plus ``figures/*.png``; :func:`write_comparison_report` compares
several runs (e.g. TLR vs VSR, paper Figs. 13-16).

Everything is read back from the files, never from the in-memory state of a
run, so ``coloc report DIR`` rebuilds the same report a run wrote.  Output is
deterministic (fixed styles, sorted methods/areas, PNGs without software/date
metadata; the same bytes whether the figures are drawn in one process or split between
forked workers, :mod:`experiments.report.parallel`) and written atomically
(:func:`couplers.publish.publish_members`).
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

from experiments.report.compare import write_comparison_report  # noqa: E402
from experiments.report.run import write_run_report  # noqa: E402

__all__ = [
    "write_run_report",
    "write_comparison_report",
]
