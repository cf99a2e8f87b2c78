"""The run report: ``report.html`` and ``figures/*.png`` of one run folder (``coloc report DIR``)."""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import matplotlib

from experiments.report.figures import (
    _fig_cdf,
    _fig_map,
    _fig_nees_time,
    run_placeholders,
    _fig_rmse_time,
    _fig_track,
    _fig_traffic,
    _resolve_net_files,
)
from experiments.report.html import (
    _association_table,
    _by_table,
    _esc,
    _figure_html,
    _fmt,
    _method_cell,
    _method_stats_rows,
    _nees_zone_table,
    _page,
    _table,
    _what_was_run,
)
from experiments.report.load import _Run, _load_run
from experiments.report.output import _atomic_publish
from experiments.report.parallel import run_jobs
from experiments.report.styles import _RC


# --------------------------------------------------------------------------- #
# Run report
# --------------------------------------------------------------------------- #


def write_run_report(run_dir: Path, *, workers: int = 1, force: bool = False) -> Path:
    """Write ``run_dir/figures/*.png`` and ``run_dir/report.html`` from the run's files.

    ``workers``: processes drawing the figures (:func:`experiments.report.parallel.run_jobs`; the
    same bytes with any number). ``coloc report`` uses two when it may run on two cores; the default
    draws in this process (e.g. at the end of ``coloc run``, possibly inside a sweep's worker).
    ``force``: a file in the way that coloc did not write is kept aside rather than refused."""
    run_dir = Path(run_dir)
    run = _load_run(run_dir)
    analysis = run.summary.get("analysis") or {}
    if analysis.get("warmup_s"):
        run.notes.append(f"Scored after a warm-up of {analysis['warmup_s']:g} s: the statistics and CDFs use the "
                         f"estimates with t >= {analysis['scored_from_s']:g} s (estimates.parquet keeps every row; "
                         "the time curves show the warm-up)." if analysis.get("warmup_start") != "traffic" else
                         "SUMO drove the warm-up alone: sensing and estimation start at that time).")

    def build(tmp: Path) -> None:
        figdir = tmp / "figures"
        with matplotlib.rc_context(_RC):
            figs = _run_figures(run, figdir, workers)
        (tmp / "report.html").write_text(_run_html(run, figs), encoding="utf-8")

    return _atomic_publish(run_dir, build, kind="run", force=force)


@dataclass(frozen=True)
class _Drawn:
    """What drawing one figure gives the page: its HTML blocks, notes and warnings (picklable, so a
    worker process can send it back)."""

    blocks: tuple[str, ...] = ()
    notes: tuple[str, ...] = ()
    warnings: tuple[str, ...] = ()


def _run_figures(run: _Run, figdir: Path, workers: int = 1) -> list[str]:
    """Draw the figures (in ``workers`` processes); returns HTML <figure> blocks in display order."""
    drawn = run_jobs(_figure_jobs(run, figdir), workers)
    blocks: list[str] = []
    for d in drawn:
        blocks.extend(d.blocks)
        run.notes.extend(d.notes)
        for w in d.warnings:
            warnings.warn(w, stacklevel=2)
    return blocks


def _figure_jobs(run: _Run, figdir: Path) -> list[tuple[float, Callable[[], _Drawn]]]:
    """The figures to draw as ``(weight, draw)`` jobs in display order; the weight is about the
    figure's drawing time (its panels; a CDF panel has a legend and 1001-point curves)."""
    jobs: list[tuple[float, Callable[[], _Drawn]]] = []
    what = _what_was_run(run)
    stand_in = run_placeholders(run)  # zones / areas that are a default layout, not derived from data
    est = run.digest  # experiments.report.digest.EstimateDigest
    has_est = est is not None and len(est) > 0

    tr = run.traffic
    if tr is not None and len(tr):
        def traffic() -> _Drawn:
            _fig_traffic([run], figdir / "traffic.png")
            return _Drawn((_figure_html(
                "traffic.png", "Traffic over time (paper Figs. 13-15)",
                "From <code>traffic.parquet</code>, one point per aggregation interval (5 min) at its "
                "midpoint: exit flow (vehicles leaving the network per hour), mean number of vehicles "
                "in the network, mean queue (mean number of halting vehicles) and stop time per km "
                "travelled. How to read: higher queue and stop time mean more platooning at junctions "
                "(denser V2V cooperation) but longer exposure to poor-GNSS zones.", what=what),))
        jobs.append((2.0, traffic))

    files = None
    try:
        files = _resolve_net_files(run)
    except Exception as exc:  # malformed scenario.toml: report it, keep the rest of the report
        run.notes.append(f"map skipped: {exc!r}")
    if files:
        def map_() -> _Drawn:
            try:
                counts = _fig_map(run, files, figdir / "map.png")
            except Exception as exc:
                (figdir / "map.png").unlink(missing_ok=True)
                return _Drawn(notes=(f"map skipped: {exc!r}",),
                              warnings=(f"coloc report: map skipped for {run.run_dir}: {exc!r}",))
            return _Drawn((_figure_html(
                "map.png", "Scenario map (paper Figs. 12 and 17a)",
                "Net lanes (thin grey lines, internal junction lanes omitted), GNSS zones as "
                "translucent fills (legend: zone name and position accuracy σp), analysis areas "
                "as dashed outlines labelled with their number (the CDFs below are per area), and "
                f"static features as red triangles. {counts['lanes']} lanes, {counts['zones']} "
                f"zone polygons, {counts['areas']} areas, {counts['features']} features"
                + (f", {counts['buildings']} building footprints (dark grey)" if counts["buildings"] else "") + ". "
                "Coordinates are SUMO net metres, equal aspect."
                + "".join(f" The {k} are {_esc(v)}." for k, v in stand_in.items()), what=what),))
        jobs.append((2.0, map_))

    if not has_est:
        return jobs

    def rmse_time() -> _Drawn:
        width = _fig_rmse_time([run], figdir / "rmse_time.png")
        feat = run.features is not None and len(run.features) > 0
        return _Drawn((_figure_html(
            "rmse_time.png", "Accuracy over time (paper Fig. 16)",
            f"Root-mean-square error over all vehicles and all time steps inside each {width} s bin, "
            "plotted at the bin midpoint: (a) vehicle position RMSE, (b) velocity RMSE, one line per "
            "method" + (" ; green lines with triangles are the RMSE of the feature position estimates "
                        "of each cooperative method (from <code>features.parquet</code>)" if feat else "")
            + ". How to read: lower is better; the gap between GNSS and a cooperative method is the "
            "cooperative gain at that time of the traffic evolution.", what=what),))
    jobs.append((2.0, rmse_time))

    if "nees" in est.columns:
        def nees_time() -> _Drawn:
            width = _fig_nees_time(run, figdir / "nees_time.png")
            return _Drawn((_figure_html(
                "nees_time.png", "Consistency over time",
                f"(a) Mean 2-D position NEES e<sup>T</sup>P<sup>-1</sup>e over all vehicles inside each {width} s "
                "bin (e: the position error, P: the position covariance the method reports, from "
                "<code>var_px</code>, <code>var_py</code>, <code>cov_pxy</code>); (b) the share of those samples "
                "whose true position lies inside the reported 95 % ellipse (NEES at most 5.99). The grey band is "
                "the warm-up the statistics do not score. How to read: a consistent method stays near 2 and 95 % "
                "(dashed lines); above 2 and below 95 %, its covariance claims more accuracy than it has.",
                what=what),))
        jobs.append((2.0, nees_time))

    if "area" in est.columns:
        def cdf_area() -> _Drawn:
            if not _fig_cdf(run, "area", figdir / "cdf_area.png", "area"):
                return _Drawn()
            return _Drawn((_figure_html(
                "cdf_area.png", "Position error CDF per analysis area (paper Fig. 17b)",
                "Empirical CDF of the Euclidean position error of all (vehicle, time) samples "
                "whose true position lies in the area, one subplot per area and one line per "
                "method (drawn from 1001 exact quantiles). The dot and dotted line mark the 95th "
                "percentile, also given in the legend; each panel's title gives its sample count n and "
                "its share of all samples. How to read: a curve further left is "
                "better; compare p95 between methods within one area."
                + (" The areas are a default grid over the net's bounding box, not derived from data: "
                   "they split the net by position only." if "areas" in stand_in else ""), what=what),))
        jobs.append((_cdf_weight(est, "area"), cdf_area))
    if "zone" in est.columns:
        def cdf_zone() -> _Drawn:
            if not _fig_cdf(run, "zone", figdir / "cdf_zone.png", "zone"):
                return _Drawn()
            return _Drawn((_figure_html(
                "cdf_zone.png", "Position error CDF per GNSS zone",
                "Same as the per-area CDF, but grouping samples by the GNSS zone of the vehicle's "
                "true position (zones differ in GNSS σp and σv). The dot marks the 95th "
                "percentile; each panel's title gives its sample count n and its share of all samples. "
                + ("How to read: the zones are a default layout (concentric rectangles over the net's "
                   "bounding box, worst class in the centre), not derived from buildings: the panels show "
                   "how each method copes with the zone's GNSS σp, not where this city's GNSS degrades; a "
                   "cooperative method should flatten the difference." if "zones" in stand_in else
                   "How to read: GNSS degrades from open-sky to built-up zones; a "
                   "cooperative method should flatten that difference."), what=what),))
        jobs.append((_cdf_weight(est, "zone"), cdf_zone))
    rep = run.config.get("report") or {}
    areas = [str(a) for a in (rep.get("track_areas") or [rep.get("track_area", "5")])]
    control = str((run.config.get("scenario") or {}).get("control", "")).upper()
    paper_fig = "Fig. 19" if control == "VSR" else "Fig. 18"
    # The labels present, from the column's distinct values (not a Python string per row: 1.77M on an hour).
    present = set(est.labels.get("area", []))
    for area in areas:
        if not ({"err_along", "err_cross"} <= set(est.columns) and area in present):
            continue
        name = "track_errors.png" if len(areas) == 1 else f"track_errors_area_{_file_part(area)}.png"

        def track(area: str = area, name: str = name) -> _Drawn:
            w = _fig_track(run, area, figdir / name)
            return _Drawn((_figure_html(
                name, f"Along-track and cross-track accuracy in area {area} (paper {paper_fig})",
                f"RMSE of the signed position error component along the true heading (top) and across "
                f"it (bottom), over all vehicles in area {_esc(area)} within each {w:g} s bin, one line "
                "per method. How to read: periodic GNSS error follows the traffic-light cycle (vehicles "
                "averaging while stopped); cross-track below about 1 m is what lane-level services need.",
                what=what),))
        jobs.append((2.0, track))
    return jobs


def _cdf_weight(est, col: str) -> float:
    """A CDF figure's weight: one per panel (label)."""
    return 0.5 + float(len(est.labels.get(col, [])))


def _file_part(label: str) -> str:
    """An area label as part of a file name (letters, digits, '-', '_' kept)."""
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in label)


def _coverage_html(methods: list[str], cov: dict) -> str:
    """Infrastructure mode: all methods on the vehicle-steps within V2I range of an RSU (the same rows
    for every method), overall and per area, and the covered vehicle-steps per RSU."""
    ms = [m for m in methods if m in (cov.get("methods") or {})]
    rows = []
    for m in ms:
        b = cov["methods"][m]
        st = b.get("stats") or {}
        note = ", ".join(f"{k.replace('_', ' ')} {v}" for k, v in st.items()) or "–"
        rows.append([_method_cell(m), _fmt(b.get("rmse_pos_m")), _fmt(b.get("p95_pos_m")), _fmt(b.get("n")),
                     _esc(note)])
    html = ["<h2>Within RSU coverage</h2>",
            "<p>Every method on the vehicle-steps within V2I range of a road-side unit only "
            "(<code>covered</code> in estimates.parquet; the same rows for every method). Outside "
            "coverage the infrastructure methods report their internal GNSS tracker.</p>",
            _table(["method", "RMSE pos [m]", "p95 pos [m]", "n", "method counters"], rows),
            "<h3>Within RSU coverage, per analysis area</h3>",
            _by_table(ms, {"methods": cov["methods"]}, "by_area", "area")]
    per_rsu = cov.get("rsu_vehicle_steps") or {}
    if per_rsu:
        html.append("<h3>Covered vehicle-steps per RSU</h3>"
                    + _table(["RSU", "vehicle-steps"], [[_esc(k), _fmt(v)] for k, v in per_rsu.items()]))
    return "\n".join(html)


def _run_html(run: _Run, blocks: list[str]) -> str:
    s = run.summary
    parts: list[str] = []
    kind = str((run.config.get("scenario") or {}).get("kind", "sumo"))
    meta = [("run", run.name), ("seed", s.get("seed", run.seed)), ("scenario", kind),
            ("control", run.control or "–"), ("config", s.get("config", "–")),
            ("SUMO version", s.get("sumo_version") or "–"), ("git", s.get("git", "–"))]
    parts.append('<dl class="meta">' + "".join(f"<dt>{_esc(k)}</dt><dd>{_esc(v)}</dd>" for k, v in meta)
                 + "</dl>")
    for n in run.notes:
        parts.append(f'<p class="note">{_esc(n)}</p>')

    methods = run.methods
    parts.append("<h2>Accuracy summary</h2>")
    parts.append("<p>From <code>summary.json</code>: position RMSE, velocity RMSE, median (p50) and "
                 "95th percentile (p95) of the position error over all vehicles and time steps, the mean "
                 "and median 2-D position NEES (2 and 1.39 for an estimator whose covariance matches its "
                 "errors; larger: overconfident), the share of samples inside the reported 95 % ellipse "
                 "(95 % when consistent) and the estimator's wall-clock time.</p>")
    parts.append(_table(["method", "RMSE pos [m]", "RMSE vel [m/s]", "p50 pos [m]", "p95 pos [m]",
                         "NEES mean", "NEES median", "inside 95 % [%]", "time [s]"], _method_stats_rows(methods, s)))
    perc = s.get("perception")
    if perc:
        per = perc.get("per_vehicle_step") or {}
        parts.append("<h3>Detections per vehicle-step</h3><p>From <code>[perception]</code>: (sensor, feature) "
                     "pairs inside a field of view, of which occluded and missed (not detected although "
                     "visible); detected features (one row per feature and vehicle) and false detections "
                     "(clutter).</p>")
        parts.append(_table(["in field of view", "occluded", "missed", "detected", "clutter"],
                            [[_fmt(per.get(k)) for k in ("in_fov", "occluded", "missed", "detected", "clutter")]],
                            left_cols=0))
    comm = [(m, (s.get("methods") or {}).get(m, {}).get("comm")) for m in methods]
    comm = [(m, c) for m, c in comm if c]
    if comm:
        parts.append("<h3>Communication</h3><p>V2V traffic the method's vehicles sent (<code>comm</code> in "
                     "summary.json; message formats in docs/architecture.md, every number 8 bytes, radio "
                     "headers not counted), averaged over vehicle-steps, and the consensus rounds used per "
                     "step.</p>")
        parts.append(_table(["method", "messages / vehicle-step", "bytes / vehicle-step", "max bytes / vehicle-step",
                             "consensus rounds / step"],
                            [[_method_cell(m), _fmt(c.get("messages_per_vehicle_step"), 1),
                              _fmt(c.get("bytes_per_vehicle_step"), 0), _fmt(c.get("max_bytes_vehicle_step")),
                              _fmt(c.get("rounds_per_step"), 1)] for m, c in comm]))
    parts.append("<h3>Per analysis area</h3>" + _by_table(methods, s, "by_area", "area"))
    parts.append("<h3>Per GNSS zone</h3>" + _by_table(methods, s, "by_zone", "zone"))
    parts.append("<h3>Consistency per GNSS zone</h3>" + _nees_zone_table(methods, s))
    cov = s.get("within_rsu_coverage")
    if cov:
        parts.append(_coverage_html(methods, cov))

    traffic = s.get("traffic") or {}
    parts.append("<h2>Traffic summary</h2>")
    if traffic:
        lab = {"mean_vehicles": "mean vehicles in network", "exit_flow_vph": "exit flow [veh/h]",
               "mean_queue": "mean queue [halting veh]", "stop_time_s_per_km": "stop time [s/km]",
               "loaded": "vehicles loaded by SUMO (incl. read ahead)", "inserted": "vehicles inserted",
               "never_inserted": "vehicles never inserted (waiting at the end)",
               "dropped_at_load": "vehicles dropped by SUMO at load", "collisions": "vehicles in collisions",
               "jammed": "jammed (the import's gridlock rule)", "jam_verdict": "gridlock rule verdict"}
        keys = [k for k in lab if k in traffic] + sorted(k for k in traffic if k not in lab)
        parts.append(_table(["quantity", "value"],
                            [[_esc(lab.get(k, k)), _fmt(traffic[k], 2)] for k in keys]))
    elif "traffic" in s and s["traffic"] is None:
        parts.append("<p>No traffic statistics: the frames come from a controlled scenario "
                     "(couplers.scenarios), not from SUMO.</p>")
    else:
        parts.append("<p>No traffic summary in summary.json.</p>")

    at = _association_table(run)
    if at:
        parts.append("<h2>Feature association</h2><p>Association decisions scored against the true "
                     "features outside the estimator, summed over the run.</p>" + at)

    parts.append("<h2>Figures</h2>")
    parts.extend(blocks if blocks else ["<p>No figures (missing input files).</p>"])
    return _page(f"coloc run report: {run.name}", "\n".join(parts))
