"""Study of Gulati et al.: factor graphs with old / new topology factors against the Kalman filter (Tables I-II).

Monte Carlo over ``study.runs`` runs of ``scenario.n_steps`` steps for each
vehicle count in ``study.vehicles``. One run (Sec. IV-A, the paper's
"random trajectory", whose generator it does not give; ours):

* N vehicles start uniformly in a ``start_box_m`` square, with a speed uniform in
  [speed_min, speed_max] m/s and a uniform heading, and move by the constant-
  velocity model with white acceleration noise ``accel_sigma`` (the paper's (20),
  T = dt).
* GPS: p + N(0, gps_var I2) per vehicle and step; odometry: the true displacement
  + N(0, odom_var I2); radar: q = R(theta) (p - s) + N(0, radar_var I2) with a pose
  (s, theta) drawn per run (s uniform in a ``sensor_box_m`` square, theta uniform)
  that no method is told, in shuffled order each step.

Methods: ``fg_topology_new``, ``fg_topology_old``, ``kf_gps_odom`` (coloc.methods.fg_topology)
and the diagnostic ``fg_gps_odom`` (the same graph without topology factors = the
RTS smoother of ``kf_gps_odom``), which separates the gain of smoothing from the
gain of the topology. Score: Gulati (21) per run ("final RMSE", summed over
vehicles); Table I averages it over the runs; Table II averages the seconds of
one run's solve (graph building + LM; the filter's whole pass).

Every run draws from ``numpy.random.default_rng([seed, N, run])``, so results do not
depend on the number of worker processes. results.parquet and curves.parquet are
byte-identical for the same config and seed; timings.parquet and the seconds in
summary.json are measured and vary.
"""

from __future__ import annotations

import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from coloc.methods.fg_topology import TOPOLOGY_NOISES, FgTopologyParams, fg_localize, kf_gps_odom, run_rmse
from couplers.errors import InputError, seed_problem
from couplers.publish import staged_folder
from experiments.runner import write_parquet
from experiments.studies.ranges import STUDY_RANGES
from experiments.studies.study_config import (
    Key, at_least, git_revision, non_negative, one_of, positive, resolve, resolved_toml,
)

METHODS = ("fg_topology_new", "fg_topology_old", "kf_gps_odom", "fg_gps_odom")
PAPER_METHODS = ("fg_topology_new", "fg_topology_old", "kf_gps_odom")
# Gulati et al. Table I (average final RMSE, 1000 runs) and Table II (seconds per run).
PAPER_TABLE_I = {2: (5.211, 7.187, 8.423), 3: (7.065, 7.076, 10.310), 4: (7.321, 8.184, 11.908)}
PAPER_TABLE_II = {2: (0.153, 0.692, 0.010), 3: (0.181, 0.468, 0.010), 4: (0.273, 0.583, 0.017)}


def _methods_check(v):
    bad = [m for m in v if m not in METHODS]
    if bad:
        return f"unknown method(s) {bad} (available: {', '.join(METHODS)})"
    if len(set(v)) != len(v):
        return "methods repeated"
    return None


def _vehicles_check(v):
    return None if all(n >= 2 for n in v) and len(set(v)) == len(v) else "vehicle counts must be distinct and >= 2"


SPEC = {
    "study": {
        "kind": Key("fg_topology", "str"),
        "name": Key("fg_topology", "str"),
        "seed": Key(1, "int", seed_problem),
        "runs": Key(1000, "int", at_least(1), "Monte Carlo runs per vehicle count (Tables I-II: 1000)"),
        "vehicles": Key([2, 3, 4], "ints", _vehicles_check),
        "methods": Key(list(METHODS), "list", _methods_check),
        "workers": Key(1, "int", at_least(1), "worker processes (results do not depend on it)"),
        "example_run": Key(0, "int", non_negative, "run whose trajectories are plotted (Figs. 3, 5)"),
    },
    "scenario": {
        "n_steps": Key(250, "int", at_least(2), "Sec. IV-A"),
        "dt": Key(1.0, "float", positive, "T of Sec. IV-A"),
        "accel_sigma": Key(0.5, "float", non_negative, "alpha of (20) for the truth; the paper gives no value"),
        "start_box_m": Key(100.0, "float", positive),
        "speed_min": Key(5.0, "float", non_negative),
        "speed_max": Key(15.0, "float", non_negative),
        "sensor_box_m": Key(1000.0, "float", non_negative, "unknown radar position drawn in this square"),
    },
    "sensors": {
        "odom_var": Key(1.0, "float", positive, "diag(1, 1), Sec. IV-A"),
        "gps_var": Key(9.0, "float", positive, "diag(9, 9)"),
        "radar_var": Key(0.1, "float", positive, "diag(0.1, 0.1)"),
    },
    "solver": {
        "max_iterations": Key(100, "int", at_least(1), "Levenberg-Marquardt"),
        "relative_error_tol": Key(1e-5, "float", positive),
        "absolute_error_tol": Key(1e-5, "float", positive),
        "topology_noise": Key("z2", "str", one_of(*TOPOLOGY_NOISES),
                              "noise of the topology factors: 'z2' = variance of z^2 ((15) with M the gradient of "
                              "z^2, + 2nd-order term); 'eq16_literal' = (16) as printed (gradient of z: N radar_var)"),
    },
}


@dataclass(frozen=True)
class FgScenario:
    n_steps: int = 250
    dt: float = 1.0
    accel_sigma: float = 0.5
    start_box_m: float = 100.0
    speed_min: float = 5.0
    speed_max: float = 15.0
    sensor_box_m: float = 1000.0


@dataclass(frozen=True)
class FgRunData:
    """Truth and measurements of one run (module doc)."""

    truth: np.ndarray  # (T, N, 2)
    gps: np.ndarray  # (T, N, 2), vehicle order
    odom: np.ndarray  # (T, N, 2), odom[t] = displacement t-1 -> t, odom[0] = 0 (unused)
    sensor: np.ndarray  # (T, N, 2), radar frame, shuffled each step
    sensor_pose: tuple[float, float, float]  # x, y, heading (rad), for the record only


def simulate_run(n_veh: int, scenario: FgScenario, sensors: FgTopologyParams, rng: np.random.Generator) -> FgRunData:
    s = scenario
    T = s.n_steps
    pos = rng.uniform(-0.5 * s.start_box_m, 0.5 * s.start_box_m, (n_veh, 2))
    speed = rng.uniform(s.speed_min, s.speed_max, n_veh)
    heading = rng.uniform(0.0, 2 * np.pi, n_veh)
    vel = np.stack([speed * np.cos(heading), speed * np.sin(heading)], axis=1)
    acc = s.accel_sigma * rng.standard_normal((T, n_veh, 2))
    truth = np.empty((T, n_veh, 2))
    truth[0] = pos
    for t in range(1, T):
        pos = pos + s.dt * vel + 0.5 * s.dt * s.dt * acc[t]
        vel = vel + s.dt * acc[t]
        truth[t] = pos
    gps = truth + np.sqrt(sensors.gps_var) * rng.standard_normal((T, n_veh, 2))
    odom = np.zeros((T, n_veh, 2))
    odom[1:] = np.diff(truth, axis=0) + np.sqrt(sensors.odom_var) * rng.standard_normal((T - 1, n_veh, 2))
    sx, sy = rng.uniform(-0.5 * s.sensor_box_m, 0.5 * s.sensor_box_m, 2)
    theta = rng.uniform(0.0, 2 * np.pi)
    c, sn = np.cos(theta), np.sin(theta)
    rot = np.array([[c, sn], [-sn, c]])  # global -> sensor frame
    local = (truth - np.array([sx, sy])) @ rot.T + np.sqrt(sensors.radar_var) * rng.standard_normal((T, n_veh, 2))
    order = np.argsort(rng.random((T, n_veh)), axis=1)
    sensor = np.take_along_axis(local, order[:, :, None], axis=1)
    return FgRunData(truth, gps, odom, sensor, (float(sx), float(sy), float(theta)))


def estimate(method: str, data: FgRunData, params: FgTopologyParams) -> tuple[np.ndarray, int]:
    """Positions (T, N, 2) of one method and its LM iterations (0 for the filter)."""
    if method == "kf_gps_odom":
        mean, _ = kf_gps_odom(data.gps, data.odom, params)
        return mean, 0
    topology = {"fg_topology_new": "new", "fg_topology_old": "old", "fg_gps_odom": "none"}[method]
    return fg_localize(data.gps, data.odom, data.sensor, params, topology)


def _run_chunk(args) -> list[dict]:
    """Runs [start, stop) for one vehicle count; returns per-run results (picklable, for the pool)."""
    n_veh, start, stop, seed, methods, scenario, params, example_run = args
    out = []
    for run in range(start, stop):
        data = simulate_run(n_veh, scenario, params, np.random.default_rng([seed, n_veh, run]))
        per = {}
        for m in methods:
            t0 = time.perf_counter()
            est, iters = estimate(m, data, params)
            secs = time.perf_counter() - t0
            err2 = np.sum((est - data.truth) ** 2, axis=(1, 2))  # (T,) summed over vehicles
            per[m] = {"rmse": run_rmse(est, data.truth), "seconds": secs, "iterations": iters, "err2": err2,
                      "est": est if run == example_run else None}
        out.append({"vehicles": n_veh, "run": run, "methods": per,
                    "truth": data.truth if run == example_run else None})
    return out


def _chunks(vehicles, runs, seed, methods, scenario, params, example_run, workers):
    size = max(1, min(50, -(-runs // (4 * workers))))
    return [(n, s, min(s + size, runs), seed, methods, scenario, params, example_run)
            for n in vehicles for s in range(0, runs, size)]


def run(data: dict, path: Path, out: Path, seed: int | None, progress: bool, force: bool = False) -> dict:
    if seed is not None:  # --seed: checked like the file's own seed
        data = {**data, "study": {**data.get("study", {}), "seed": seed}}
    cfg = resolve(data, path, SPEC, STUDY_RANGES["fg_topology"])
    st, sc = cfg["study"], cfg["scenario"]
    if sc["speed_max"] < sc["speed_min"]:
        raise InputError(path, "scenario.speed_max", "must be >= scenario.speed_min")
    if st["example_run"] >= st["runs"]:
        raise InputError(path, "study.example_run", f"must be < study.runs ({st['runs']})")
    scenario = FgScenario(**sc)
    params = FgTopologyParams(**cfg["sensors"], **cfg["solver"])
    methods = list(st["methods"])
    vehicles = list(st["vehicles"])
    runs = st["runs"]

    t_start = time.perf_counter()
    jobs = _chunks(vehicles, runs, st["seed"], methods, scenario, params, st["example_run"], st["workers"])
    results: list[dict] = []
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(vehicles) * runs, desc=st["name"], unit="run", mininterval=1.0)
    if st["workers"] == 1:
        for job in jobs:
            part = _run_chunk(job)
            results.extend(part)
            if bar:
                bar.update(len(part))
    else:
        import multiprocessing as mp

        with ProcessPoolExecutor(max_workers=st["workers"], mp_context=mp.get_context("spawn")) as pool:
            for part in pool.map(_run_chunk, jobs):
                results.extend(part)
                if bar:
                    bar.update(len(part))
    if bar:
        bar.close()
    wall = time.perf_counter() - t_start
    results.sort(key=lambda r: (r["vehicles"], r["run"]))

    rows, timing_rows, curve_rows, example_rows = [], [], [], []
    for r in results:
        for m in methods:
            pm = r["methods"][m]
            rows.append({"vehicles": r["vehicles"], "run": r["run"], "method": m, "rmse_m": pm["rmse"],
                         "iterations": pm["iterations"]})
            timing_rows.append({"vehicles": r["vehicles"], "run": r["run"], "method": m, "seconds": pm["seconds"]})
            if pm["est"] is not None:
                T, N, _ = pm["est"].shape
                for i in range(N):
                    example_rows.append(pd.DataFrame({
                        "vehicles": r["vehicles"], "method": m, "vehicle": i, "t": np.arange(T),
                        "px": pm["est"][:, i, 0], "py": pm["est"][:, i, 1],
                        "px_true": r["truth"][:, i, 0], "py_true": r["truth"][:, i, 1]}))
    for n in vehicles:
        for m in methods:
            err2 = np.array([r["methods"][m]["err2"] for r in results if r["vehicles"] == n])  # (runs, T)
            T = err2.shape[1]
            curve_rows.append(pd.DataFrame({
                "vehicles": n, "method": m, "t": np.arange(T) * scenario.dt,
                # total-system RMSE at each step over the runs, and the running (combined) RMSE (21) up to it
                "rmse_step_m": np.sqrt(err2.mean(axis=0)),
                "rmse_cumulative_m": np.sqrt((np.cumsum(err2, axis=1) / np.arange(1, T + 1)).mean(axis=0)),
            }))
    results_df = pd.DataFrame(rows)
    timings_df = pd.DataFrame(timing_rows)
    curves_df = pd.concat(curve_rows, ignore_index=True)
    example_df = pd.concat(example_rows, ignore_index=True) if example_rows else None

    table = {}
    for n in vehicles:
        block = {}
        for m in methods:
            v = results_df[(results_df.vehicles == n) & (results_df.method == m)]["rmse_m"].to_numpy()
            secs = timings_df[(timings_df.vehicles == n) & (timings_df.method == m)]["seconds"].to_numpy()
            its = results_df[(results_df.vehicles == n) & (results_df.method == m)]["iterations"].to_numpy()
            block[m] = {"mean_final_rmse_m": float(v.mean()),
                        "stderr_m": float(v.std(ddof=1) / np.sqrt(v.size)) if v.size > 1 else None,
                        "median_m": float(np.median(v)), "mean_seconds": float(secs.mean()),
                        "mean_iterations": float(its.mean())}
        if n in PAPER_TABLE_I:
            block["paper"] = {m: {"mean_final_rmse_m": PAPER_TABLE_I[n][k], "mean_seconds": PAPER_TABLE_II[n][k]}
                              for k, m in enumerate(PAPER_METHODS)}
        block["ordering"] = _ordering(results_df[results_df.vehicles == n], methods)
        table[str(n)] = block

    provenance = {"git": git_revision(), "config_source": str(path), "gtsam": _gtsam_version()}
    summary = {"config": str(path), "study": "fg_topology", "seed": st["seed"], "git": provenance["git"],
               "runs": runs, "vehicles": vehicles, "methods": methods, "table": table, "wall_seconds": wall,
               "workers": st["workers"]}
    summary["lines"] = _lines(summary)
    with staged_folder(out, "run", force=force) as tmp:
        (tmp / "config.toml").write_text(resolved_toml(cfg, SPEC, path, provenance))
        write_parquet(results_df, tmp / "results.parquet")
        write_parquet(timings_df, tmp / "timings.parquet")
        write_parquet(curves_df, tmp / "curves.parquet")
        if example_df is not None:
            write_parquet(example_df, tmp / "example.parquet")
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        write_report(tmp)
    return summary


def _gtsam_version() -> str:
    try:
        from importlib.metadata import version

        return version("gtsam")
    except Exception:  # noqa: BLE001 - provenance only
        return "unknown"


def _ordering(df: pd.DataFrame, methods: list[str]) -> dict:
    """Paired comparisons over the runs: mean difference of the final RMSE and its standard error."""
    out = {}
    pairs = [("fg_topology_new", "fg_topology_old"), ("fg_topology_old", "kf_gps_odom"),
             ("fg_topology_new", "kf_gps_odom"), ("fg_topology_old", "fg_gps_odom")]
    wide = df.pivot(index="run", columns="method", values="rmse_m")
    for a, b in pairs:
        if a in methods and b in methods:
            d = (wide[a] - wide[b]).to_numpy()
            out[f"{a} - {b}"] = {"mean_m": float(d.mean()),
                                 "stderr_m": float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else None,
                                 "fraction_of_runs_below": float(np.mean(d < 0))}
    return out


def _lines(summary: dict) -> list[str]:
    lines = [f"fg_topology: {summary['runs']} runs per vehicle count, average final RMSE (21) [m] "
             "(paper Table I in brackets), mean seconds per run (Table II in brackets)"]
    for n, block in summary["table"].items():
        paper = block.get("paper", {})
        cells = []
        for m in summary["methods"]:
            b = block[m]
            p = paper.get(m)
            cells.append(f"{m} {b['mean_final_rmse_m']:.3f}" + (f" [{p['mean_final_rmse_m']:.3f}]" if p else "")
                         + f" {b['mean_seconds']:.3f}s" + (f" [{p['mean_seconds']:.3f}s]" if p else ""))
        lines.append(f"  N={n}: " + "; ".join(cells))
    return lines


# ----------------------------------------------------------------------------------------------- report

def write_report(run_dir: Path) -> None:
    """report.html + figures/*.png from the files of ``run_dir`` (never from memory)."""
    from experiments.report.figures import _new_fig, _save
    from experiments.report.html import _esc, _figure_html, _fmt, _page, _table

    run_dir = Path(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    curves = pd.read_parquet(run_dir / "curves.parquet")
    example = pd.read_parquet(run_dir / "example.parquet") if (run_dir / "example.parquet").exists() else None
    figs = run_dir / "figures"
    figs.mkdir(exist_ok=True)
    methods = summary["methods"]
    colors = {"fg_topology_new": "tab:green", "fg_topology_old": "tab:orange", "kf_gps_odom": "tab:blue",
              "fg_gps_odom": "tab:gray"}
    vehicles = [int(n) for n in summary["table"]]

    def curves_by_vehicle_count(column: str, ylabel: str, name: str, **line) -> None:
        """One panel per vehicle count: ``column`` of curves.parquet over t, one line per method."""
        fig = _new_fig(4.2 * len(vehicles), 3.4)
        axes = fig.subplots(1, len(vehicles), squeeze=False)[0]
        for ax, n in zip(axes, vehicles):
            for m in methods:
                c = curves[(curves.vehicles == n) & (curves.method == m)]
                ax.plot(c.t, c[column], color=colors[m], label=m, **line)
            ax.set_title(f"{n} vehicles")
            ax.set_xlabel("t [s]")
            ax.set_ylabel(ylabel)
            ax.grid(alpha=0.3)
        axes[0].legend(fontsize=8)
        _save(fig, figs / name)

    curves_by_vehicle_count("rmse_cumulative_m", "combined RMSE (21) up to t [m]", "rmse_time.png")
    curves_by_vehicle_count("rmse_step_m", "total-system error at t, RMS over runs [m]", "rmse_step.png", lw=0.8)

    if example is not None:
        fig = _new_fig(4.2 * len(vehicles), 4.0)
        axes = fig.subplots(1, len(vehicles), squeeze=False)[0]
        for ax, n in zip(axes, vehicles):
            ex = example[example.vehicles == n]
            first = True
            for v, g in ex[ex.method == methods[0]].groupby("vehicle"):
                ax.plot(g.px_true, g.py_true, color="k", lw=1.2, label="truth" if first else None)
                first = False
            for m in methods:
                for k, (v, g) in enumerate(ex[ex.method == m].groupby("vehicle")):
                    ax.plot(g.px, g.py, color=colors[m], lw=0.6, label=m if k == 0 else None)
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_title(f"{n} vehicles, one run")
            ax.set_xlabel("x [m]")
            ax.set_ylabel("y [m]")
        axes[0].legend(fontsize=7)
        _save(fig, figs / "trajectories.png")

    rows_i, rows_ii = [], []
    for n in vehicles:
        block = summary["table"][str(n)]
        paper = block.get("paper", {})
        r1 = [str(n)]
        r2 = [str(n)]
        for m in methods:
            b = block[m]
            r1.append(f"{_fmt(b['mean_final_rmse_m'])} ± {_fmt(b['stderr_m'])}")
            r2.append(_fmt(b["mean_seconds"], 4))
        for m in PAPER_METHODS:
            r1.append(_fmt(paper.get(m, {}).get("mean_final_rmse_m")))
            r2.append(_fmt(paper.get(m, {}).get("mean_seconds")))
        new, old = block.get("fg_topology_new"), block.get("fg_topology_old")
        r1.append(_fmt(100 * (old["mean_final_rmse_m"] - new["mean_final_rmse_m"]) / old["mean_final_rmse_m"], 2)
                  if new and old else "–")
        r2.append(_fmt(100 * (old["mean_seconds"] - new["mean_seconds"]) / old["mean_seconds"], 2)
                  if new and old else "–")
        rows_i.append(r1)
        rows_ii.append(r2)
    head = ["N"] + [_esc(m) for m in methods] + [f"paper {_esc(m)}" for m in PAPER_METHODS]
    table_i = _table(head + ["% decrease new vs old (ours)"], rows_i)
    table_ii = _table(head + ["% decrease new vs old (ours)"], rows_ii)
    order_rows = []
    for n in vehicles:
        for k, v in summary["table"][str(n)]["ordering"].items():
            order_rows.append([str(n), _esc(k), _fmt(v["mean_m"]), _fmt(v["stderr_m"]),
                               _fmt(v["fraction_of_runs_below"], 3)])
    order_table = _table(["N", "paired difference", "mean [m]", "std. error [m]", "fraction of runs < 0"],
                         order_rows, left_cols=2)
    body = (
        f"<p>Gulati et al., factor graphs with topology factors. {summary['runs']} Monte Carlo runs per vehicle "
        f"count, seed {summary['seed']}, git {_esc(summary['git'])}, {summary['workers']} worker process(es), "
        f"wall time {summary['wall_seconds']:.1f} s. Our trajectories, initial values and Kalman filter are our "
        "own choices where the paper is silent (see config.toml and coloc/fg_topology.py); the paper's numbers "
        "are shown for reference, not as targets our scenario should hit.</p>"
        "<h2>Table I: average final RMSE (21) [m]</h2>" + table_i +
        "<h2>Table II: average seconds per run</h2>"
        "<p>Measured on a shared 2-core machine: noisy. The paper used C++ GTSAM 3.2.1; our topology "
        "factors are Python CustomFactors called from gtsam's C++ optimizer.</p>" + table_ii +
        "<h2>Paired differences over the runs</h2>" + order_table +
        _figure_html("rmse_time.png", "Combined RMSE over time (Figs. 4, 6)",
                     "RMSE (21) from the start up to t, root of the mean over runs.") +
        _figure_html("rmse_step.png", "Error at each step", "Total-system position error at t, RMS over runs.") +
        (_figure_html("trajectories.png", "Trajectories (Figs. 3, 5)", "Truth and estimates of the example run.")
         if example is not None else "")
    )
    (run_dir / "report.html").write_text(_page("fg_topology: Gulati et al. Tables I-II", body))
