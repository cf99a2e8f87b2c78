"""The comparison report: runs side by side (e.g. TLR vs VSR, paper Figs. 13-16), ``coloc report A B --out C``."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable

import matplotlib

from couplers.publish import check_target
from experiments.report.figures import _fig_rmse_time, _fig_traffic
from experiments.report.html import (
    _esc,
    _figure_html,
    _fmt,
    _method_stats_rows,
    _page,
    _run_label,
    _table,
    _what_was_run,
)
from experiments.report.load import _EST_COLS, _Run, _load_run, _read_parquet, _summary_from_estimates
from experiments.report.output import _atomic_publish
from experiments.report.parallel import run_jobs
from experiments.report.run import write_run_report
from experiments.report.styles import _RC, _RUN_LINESTYLES, _sorted_labels, method_label


# --------------------------------------------------------------------------- #
# Comparison report
# --------------------------------------------------------------------------- #


def write_comparison_report(run_dirs: list[Path], out_dir: Path, *,
                            build_missing: bool = True, force: bool = False, workers: int = 1) -> Path:
    """Compare runs side by side (e.g. TLR vs VSR); writes ``out_dir/report.html`` and figures.

    Runs keep the order given (the first is drawn with continuous lines, the second
    dashed, ...).  When ``build_missing`` is true, a run without ``report.html`` gets one
    so the links work.  ``workers``: processes drawing the figures, as in :func:`write_run_report`.
    """
    run_dirs = [Path(d) for d in run_dirs]
    out_dir = Path(out_dir)
    if not run_dirs:
        raise ValueError("write_comparison_report needs at least one run directory")
    # Only an empty folder or an earlier comparison is written into (``force``: any folder).
    check_target(out_dir, ("report",), force=force, replaces_folder=False)
    if build_missing:
        for d in run_dirs:
            if not (d / "report.html").exists():
                write_run_report(d, workers=workers)
    runs = [_load_run(d, need_areas=False) for d in run_dirs]
    for r in runs:  # per-area tables come from summary.json; compute only if it lacks them
        if not r.summary.get("methods"):
            est = _read_parquet(r.run_dir / "estimates.parquet", _EST_COLS)
            if est is not None:
                r.summary["methods"] = _summary_from_estimates(est)

    what = " ".join(_what_was_run(r) for r in runs)

    def figure_jobs(figdir: Path) -> list[tuple[float, Callable[[], str]]]:
        """The figures as ``(weight, draw)`` jobs; each draws its PNG and returns its HTML block."""

        def traffic() -> str:
            _fig_traffic(runs, figdir / "compare_traffic.png")
            return _figure_html(
                "compare_traffic.png", "Traffic over time per run (paper Figs. 13-15)",
                "One line per run (colour and line style per run, see legend), one point per "
                "5-minute interval: exit flow, mean vehicles in the network, mean queue (halting "
                "vehicles) and stop time per km. How to read: with similar exit flow, a run with "
                "more vehicles and queues inside the network (e.g. traffic lights) offers denser "
                "cooperation.", what=what)

        def rmse_time() -> str:
            width = _fig_rmse_time(runs, figdir / "compare_rmse_time.png")
            styles = ", ".join(f"{_esc(_run_label(r, runs))}: {_ls_name(k)}"
                               for k, r in enumerate(runs))
            return _figure_html(
                "compare_rmse_time.png", "Accuracy over time per run (paper Fig. 16)",
                f"Position (a) and velocity (b) RMSE over vehicles per {width} s bin; colour is the "
                f"method, line style the run ({styles}); green lines with triangles are feature "
                "RMSE of cooperative methods. How to read: compare the same colour across line "
                "styles to see how traffic control changes each method's accuracy.", what=what)

        jobs: list[tuple[float, Callable[[], str]]] = []
        if any(r.traffic is not None and len(r.traffic) for r in runs):
            jobs.append((2.0, traffic))
        if any(r.estimates is not None and len(r.estimates) for r in runs):
            jobs.append((2.0, rmse_time))
        return jobs

    def build(tmp: Path) -> None:
        with matplotlib.rc_context(_RC):
            blocks = run_jobs(figure_jobs(tmp / "figures"), workers)
        (tmp / "report.html").write_text(_comparison_html(runs, out_dir, blocks), encoding="utf-8")

    return _atomic_publish(out_dir, build, kind="report", force=force, field="--out")


def _ls_name(k: int) -> str:
    return ["continuous", "dashed", "dotted", "dash-dotted"][k % len(_RUN_LINESTYLES)]


def _relpath(target: Path, start: Path) -> str:
    return Path(os.path.relpath(Path(target).resolve(), Path(start).resolve())).as_posix()


def _comparison_html(runs: list[_Run], out_dir: Path, blocks: list[str]) -> str:
    parts: list[str] = []
    parts.append("<h2>Runs</h2>")
    rows = []
    for k, r in enumerate(runs):
        link = _relpath(r.run_dir / "report.html", out_dir)
        rows.append([f'<a href="{_esc(link)}">{_esc(_run_label(r, runs))}</a>', _esc(r.control or "–"),
                     _esc(r.summary.get("seed", r.seed)), _esc(_ls_name(k)),
                     _esc(r.summary.get("sumo_version", "–")), _esc(r.summary.get("git", "–"))])
    parts.append(_table(["run (per-run report)", "control", "seed", "line style", "SUMO", "git"], rows,
                        left_cols=2))
    for r in runs:
        for n in r.notes:
            parts.append(f'<p class="note">{_esc(r.name)}: {_esc(n)}</p>')

    # Overall accuracy: one row per (run, method).
    parts.append("<h2>Accuracy summary</h2>")
    rows = []
    for r in runs:
        for row in _method_stats_rows(r.methods, r.summary):
            rows.append([_esc(_run_label(r, runs))] + row)
    parts.append("<p>From each run's <code>summary.json</code>: position and velocity RMSE, median and 95th "
                 "percentile of the position error, the mean and median 2-D position NEES (2 and 1.39 when the "
                 "reported covariance matches the errors; larger: overconfident), the share of samples inside "
                 "the reported 95 % ellipse (95 % when consistent) and the estimator's wall-clock time.</p>")
    parts.append(_table(["run", "method", "RMSE pos [m]", "RMSE vel [m/s]", "p50 pos [m]", "p95 pos [m]",
                         "NEES mean", "NEES median", "inside 95 % [%]", "time [s]"], rows, left_cols=2))

    # Per-area p95: one column per (run, method).
    cols = [(r, m) for r in runs for m in r.methods]
    by_area = {(id(r), m): (((r.summary.get("methods") or {}).get(m) or {}).get("by_area") or {})
               for r, m in cols}
    areas = _sorted_labels(a for d in by_area.values() for a in d)
    parts.append("<h2>95th percentile position error per area [m]</h2>")
    if areas:
        header = ["area"] + [f"{_esc(_run_label(r, runs))}<br>{_esc(method_label(m))}" for r, m in cols]
        rows = [[_esc(a)] + [_fmt((by_area[(id(r), m)].get(a) or {}).get("p95_pos_m")) for r, m in cols]
                for a in areas]
        parts.append(_table(header, rows))
    else:
        parts.append("<p>No per-area statistics.</p>")

    parts.extend(_nees_zone_html(runs))

    # Infrastructure mode: all methods on the covered vehicle-steps, per run and area, side by side.
    cov_runs = [r for r in runs if r.summary.get("within_rsu_coverage")]
    if cov_runs:
        parts.append("<h2>Within RSU coverage: position RMSE / p95 [m] per area</h2>"
                     "<p>Vehicle-steps within V2I range of a road-side unit only (the same rows for "
                     "every method of a run).</p>")
        ccols = [(r, m) for r in cov_runs for m in r.methods
                 if m in (r.summary["within_rsu_coverage"].get("methods") or {})]
        blocks_ = {(id(r), m): r.summary["within_rsu_coverage"]["methods"][m] for r, m in ccols}
        careas = _sorted_labels(a for b in blocks_.values() for a in (b.get("by_area") or {}))
        header = ["area"] + [f"{_esc(_run_label(r, runs))}<br>{_esc(method_label(m))}" for r, m in ccols]

        def cell(b):
            return "–" if not b else f"{_fmt(b.get('rmse_pos_m'))} / {_fmt(b.get('p95_pos_m'))}"

        rows = [["all"] + [cell(blocks_[(id(r), m)]) for r, m in ccols]]
        rows += [[_esc(a)] + [cell((blocks_[(id(r), m)].get("by_area") or {}).get(a)) for r, m in ccols]
                 for a in careas]
        parts.append(_table(header, rows))

    traffic_rows = []
    for r in runs:
        t = r.summary.get("traffic") or {}
        if t:
            traffic_rows.append([_esc(_run_label(r, runs))] + [
                _fmt(t.get(k), 2) for k in ("exit_flow_vph", "mean_vehicles", "mean_queue",
                                            "stop_time_s_per_km")])
    if traffic_rows:
        parts.append("<h2>Traffic summary</h2>")
        parts.append(_table(["run", "exit flow [veh/h]", "mean vehicles", "mean queue", "stop time [s/km]"],
                            traffic_rows))

    parts.append("<h2>Figures</h2>")
    parts.extend(blocks if blocks else ["<p>No figures (missing input files).</p>"])
    title = "coloc comparison: " + " vs ".join(_run_label(r, runs) for r in runs)
    return _page(title, "\n".join(parts))


def _nees_zone_html(runs: list[_Run]) -> list[str]:
    """Consistency per GNSS zone, one column per (run, method): summary.json ``nees_pos.by_zone`` (mean /
    median NEES / % inside the 95 % ellipse); nothing when no run has per-zone NEES."""
    cols = [(r, m) for r in runs for m in r.methods]
    blocks = {(id(r), m): ((((r.summary.get("methods") or {}).get(m) or {}).get("nees_pos") or {})
                           .get("by_zone") or {}) for r, m in cols}
    zones = _sorted_labels(z for b in blocks.values() for z in b)
    if not zones:
        return []

    def cell(b) -> str:
        if b is None:
            return "–"
        if not isinstance(b, dict):  # summaries written before the block had its median and share
            return _fmt(b)
        inside = b.get("inside_95")
        return (f"{_fmt(b.get('mean'))} / {_fmt(b.get('median'))} / "
                f"{_fmt(None if inside is None else 100.0 * inside, 1)}")

    header = ["zone"] + [f"{_esc(_run_label(r, runs))}<br>{_esc(method_label(m))}" for r, m in cols]
    rows = [[_esc(z)] + [cell(blocks[(id(r), m)].get(z)) for r, m in cols] for z in zones]
    return ["<h2>Consistency per GNSS zone: mean / median NEES / inside 95 % [%]</h2>",
            "<p>The 2-D position NEES of each run's vehicle-steps in a zone (after the warm-up), from "
            "<code>summary.json</code> <code>nees_pos.by_zone</code>; 2 / 1.39 / 95 % for a consistent "
            "method.</p>",
            _table(header, rows)]
