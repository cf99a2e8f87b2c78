"""Sweeps: one base config times factors and seeds, run in parallel, aggregated and reported.

``run`` (the sweep itself), ``factors`` (the factor table of a sweep file), ``zones`` (per-zone
aggregation), ``report`` and ``study_report`` (the HTML report and its study figures).
"""
