"""Study of Zhang et al.: the SME filter against the Kalman filter that knows the GPS association (Sec. IV).

Scenario (Sec. IV): three vehicles from the joint initial state
[0, 80, 0, 0, 0, 45, 0, 45, 0, 0, 0, 80] in the paper's order [px, vx, py, vy] per
vehicle (all start at the origin, heading east, north-east and north), constant
velocity with process noise delta = 1/2, T = 1; GPS covariance diag(50, 50); an
infrastructure sensor, covariance diag(10, 10), that sees every vehicle from a
pose no method is told. The paper states neither the run length nor the filters'
prior: ``n_steps`` and the prior (truth + N(0, diag(prior_pos_var, prior_vel_var)),
the same draw for every method) are ours. The paper shows one run; we run
``runs`` seeded Monte Carlo runs, each for every sensor pose of
``sensor_poses`` (common random numbers: the same truth, GPS and local-frame noise
for each pose, so pose effects are not hidden by sampling noise).

Methods: ``sme`` (coloc.methods.sme, the configured pseudo-noise), ``kf`` (the baseline),
diagnostics ``sme_no_topology`` (SME without the infrastructure sensor: what the
association costs) and ``sme_linearized`` (SME with the first-order pseudo-noise
covariance). Score: the paper's (12)-(13) per run, vehicles labelled by the
prior's order ("total error"), and the same with the best vehicle permutation per
step ("set error", association-free) as a check that labels did not swap.

Every run draws from ``numpy.random.default_rng([seed, run])``: same seed, same files
(results.parquet, curves.parquet, example.parquet byte-identical).
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from coloc.methods.sme import SmeFilter, SmeParams, cv_process_cov, cv_transition
from couplers.errors import InputError, seed_problem
from couplers.publish import staged_folder
from experiments.runner import write_parquet
from experiments.studies.ranges import STUDY_RANGES
from experiments.studies.study_config import (
    Key, at_least, git_revision, non_negative, one_of, positive, resolve, resolved_toml,
)

METHODS = ("sme", "kf", "sme_no_topology", "sme_linearized")


def _methods_check(v):
    bad = [m for m in v if m not in METHODS]
    if bad:
        return f"unknown method(s) {bad} (available: {', '.join(METHODS)})"
    if "sme" not in v or "kf" not in v:
        return "must include 'sme' and 'kf'"
    return None if len(set(v)) == len(v) else "methods repeated"


def _poses_check(v):
    for p in v:
        if not (isinstance(p, list) and len(p) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                                           for x in p)):
            return "each pose must be [x_m, y_m, heading_deg]"
    return None


def _state_check(v):
    return None if len(v) % 4 == 0 and len(v) >= 8 else "needs 4 numbers [px, vx, py, vy] per vehicle, >= 2 vehicles"


SPEC = {
    "study": {
        "kind": Key("sme", "str"),
        "name": Key("sme", "str"),
        "seed": Key(1, "int", seed_problem),
        "runs": Key(200, "int", at_least(1), "Monte Carlo runs (the paper shows one)"),
        "n_steps": Key(100, "int", at_least(2), "not given in the paper"),
        "methods": Key(list(METHODS), "list", _methods_check),
        "example_run": Key(0, "int", non_negative, "run whose trajectories are plotted (Fig. 2)"),
    },
    "scenario": {
        "initial_state": Key([0.0, 80.0, 0.0, 0.0, 0.0, 45.0, 0.0, 45.0, 0.0, 0.0, 0.0, 80.0], "floats",
                             _state_check, "Sec. IV, paper order [px, vx, py, vy] per vehicle"),
        "dt": Key(1.0, "float", positive, "T"),
        "process_sigma": Key(0.5, "float", non_negative, "delta of (8)"),
        "prior_pos_var": Key(50.0, "float", positive, "filters' prior around the true initial state (ours)"),
        "prior_vel_var": Key(25.0, "float", positive, "(ours)"),
        "sensor_poses": Key([[300.0, -200.0, 40.0], [-2000.0, 1500.0, 200.0], [0.0, 0.0, 0.0]], "list",
                            _poses_check, "infrastructure sensor [x_m, y_m, heading_deg], unknown to the filters"),
    },
    "sensors": {
        "gps_var": Key(50.0, "float", positive, "diag(50, 50)"),
        "sensor_var": Key(10.0, "float", positive, "diag(10, 10)"),
    },
    "filter": {
        "pseudo_noise": Key("moments", "str", one_of("moments", "linearized"), "coloc.methods.sme module doc"),
    },
}


def paper_state_to_blocks(state: list[float]) -> np.ndarray:
    """[px, vx, py, vy] per vehicle (paper) -> (N, 4) rows [px, py, vx, vy] (project)."""
    s = np.asarray(state, dtype=float).reshape(-1, 4)
    return s[:, [0, 2, 1, 3]]


def simulate_run(x0: np.ndarray, n_steps: int, dt: float, process_sigma: float, gps_var: float, sensor_var: float,
                 poses: list, rng: np.random.Generator) -> dict:
    """Truth (T, N, 4), GPS in vehicle order and shuffled (T, N, 2), sensor scans per pose (P, T, N, 2)."""
    n = x0.shape[0]
    a = cv_transition(n, dt)
    # white acceleration per vehicle and axis: w = B a, B = [T^2/2; T] (the Q of coloc.methods.sme)
    acc = process_sigma * rng.standard_normal((n_steps, n, 2))
    truth = np.empty((n_steps, n, 4))
    x = x0.reshape(-1).copy()
    for t in range(n_steps):
        if t > 0:
            w = np.concatenate([0.5 * dt * dt * acc[t], dt * acc[t]], axis=1).reshape(-1)
            x = a @ x + w
        truth[t] = x.reshape(n, 4)
    pos = truth[:, :, :2]
    gps = pos + np.sqrt(gps_var) * rng.standard_normal((n_steps, n, 2))
    gps_order = np.argsort(rng.random((n_steps, n)), axis=1)
    gps_shuffled = np.take_along_axis(gps, gps_order[:, :, None], axis=1)
    local_noise = np.sqrt(sensor_var) * rng.standard_normal((n_steps, n, 2))
    sensor_order = np.argsort(rng.random((n_steps, n)), axis=1)
    scans = []
    for sx, sy, hdg in poses:
        th = np.radians(hdg)
        rot = np.array([[np.cos(th), np.sin(th)], [-np.sin(th), np.cos(th)]])  # global -> sensor frame
        local = (pos - np.array([sx, sy])) @ rot.T + local_noise
        scans.append(np.take_along_axis(local, sensor_order[:, :, None], axis=1))
    prior_draw = rng.standard_normal(4 * n)
    return {"truth": truth, "gps": gps, "gps_shuffled": gps_shuffled, "scans": np.array(scans),
            "prior_draw": prior_draw}


def run_filter(method: str, sim: dict, pose_index: int, params: SmeParams, prior_mean: np.ndarray,
               prior_cov: np.ndarray) -> np.ndarray:
    """Joint means (T, N, 4) of one method over one run."""
    kind = "kf" if method == "kf" else "sme"
    p = params
    if method == "sme_no_topology":
        p = dataclasses.replace(p, use_topology=False)
    elif method == "sme_linearized":
        p = dataclasses.replace(p, pseudo_noise="linearized")
    f = SmeFilter(prior_mean, prior_cov, p, kind)
    T, n, _ = sim["truth"].shape
    out = np.empty((T, n, 4))
    for t in range(T):
        gps = sim["gps"][t] if kind == "kf" else sim["gps_shuffled"][t]
        mean, _ = f.step(gps, sim["scans"][pose_index, t], predict=t > 0)
        out[t] = mean.reshape(n, 4)
    return out


def step_errors(est: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step: (12) summed over labelled vehicles, and the minimum over vehicle permutations."""
    d = est[:, :, None, :2] - truth[:, None, :, :2]  # (T, track, vehicle, 2)
    cost = np.sum(d * d, axis=-1)
    n = est.shape[1]
    labelled = np.einsum("tii->t", cost)
    perms = np.array(list(itertools.permutations(range(n))))
    set_err = np.min(cost[:, np.arange(n)[None, :], perms].sum(axis=-1), axis=1)
    return labelled, set_err


def run(data: dict, path: Path, out: Path, seed: int | None, progress: bool, force: bool = False) -> dict:
    if seed is not None:  # --seed: checked like the file's own seed
        data = {**data, "study": {**data.get("study", {}), "seed": seed}}
    cfg = resolve(data, path, SPEC, STUDY_RANGES["sme"])
    st, sc, se = cfg["study"], cfg["scenario"], cfg["sensors"]
    if st["example_run"] >= st["runs"]:
        raise InputError(path, "study.example_run", f"must be < study.runs ({st['runs']})")
    sc["sensor_poses"] = [[float(x) for x in p] for p in sc["sensor_poses"]]
    x0 = paper_state_to_blocks(sc["initial_state"])
    n = x0.shape[0]
    params = SmeParams(gps_var=se["gps_var"], sensor_var=se["sensor_var"], process_sigma=sc["process_sigma"],
                       dt=sc["dt"], pseudo_noise=cfg["filter"]["pseudo_noise"])
    prior_cov = np.kron(np.eye(n), np.diag([sc["prior_pos_var"]] * 2 + [sc["prior_vel_var"]] * 2))
    prior_sd = np.sqrt(np.diag(prior_cov))
    methods, poses = list(st["methods"]), sc["sensor_poses"]
    T = st["n_steps"]

    t_start = time.perf_counter()
    seconds = {m: 0.0 for m in methods}
    rows, example_rows = [], []
    err_sum = {(k, m): np.zeros(T) for k in range(len(poses)) for m in methods}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=st["runs"], desc=st["name"], unit="run", mininterval=1.0)
    for r in range(st["runs"]):
        sim = simulate_run(x0, T, sc["dt"], sc["process_sigma"], se["gps_var"], se["sensor_var"], poses,
                           np.random.default_rng([st["seed"], r]))
        prior_mean = sim["truth"][0].reshape(-1) + prior_sd * sim["prior_draw"]
        for k in range(len(poses)):
            for m in methods:
                if m == "kf" and k > 0:  # the KF does not use the sensor: identical for every pose
                    est = kf_est
                else:
                    t0 = time.perf_counter()
                    est = run_filter(m, sim, k, params, prior_mean, prior_cov)
                    seconds[m] += time.perf_counter() - t0
                    if m == "kf":
                        kf_est = est
                lab, setr = step_errors(est, sim["truth"])
                finite = bool(np.all(np.isfinite(lab)))
                rows.append({"pose": k, "run": r, "method": m,
                             "total_error_m": float(np.sqrt(np.mean(lab))),  # (13)
                             "set_error_m": float(np.sqrt(np.mean(setr))), "finite": finite})
                err_sum[(k, m)] += lab
                if r == st["example_run"] and k == 0:
                    for i in range(n):
                        example_rows.append(pd.DataFrame({
                            "method": m, "vehicle": i, "t": np.arange(T) * sc["dt"],
                            "px": est[:, i, 0], "py": est[:, i, 1],
                            "px_true": sim["truth"][:, i, 0], "py_true": sim["truth"][:, i, 1]}))
        if bar:
            bar.update(1)
    if bar:
        bar.close()
    wall = time.perf_counter() - t_start
    results = pd.DataFrame(rows)
    curves = pd.concat([pd.DataFrame({"pose": k, "method": m, "t": np.arange(T) * sc["dt"],
                                      "rmse_m": np.sqrt(err_sum[(k, m)] / st["runs"])})
                        for (k, m) in err_sum], ignore_index=True)
    example = pd.concat(example_rows, ignore_index=True)

    by_pose = summarize_poses(results, poses, methods)
    provenance = {"git": git_revision(), "config_source": str(path)}
    summary = {"config": str(path), "study": "sme", "seed": st["seed"], "git": provenance["git"],
               "runs": st["runs"], "n_steps": T, "methods": methods, "by_pose": by_pose,
               "seconds": {m: seconds[m] for m in methods}, "wall_seconds": wall}
    summary["lines"] = _lines(summary)
    with staged_folder(out, "run", force=force) as tmp:
        (tmp / "config.toml").write_text(resolved_toml(cfg, SPEC, path, provenance))
        write_parquet(results, tmp / "results.parquet")
        write_parquet(curves, tmp / "curves.parquet")
        write_parquet(example, tmp / "example.parquet")
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        write_report(tmp)
    return summary


# A run is "ghost-locked" when its set error (best vehicle permutation) exceeds this multiple of the KF's
# error in the same run: the filter followed a ghost of (9)-(10), not a label swap (see coloc.methods.sme).
GHOST_FACTOR = 5.0


def summarize_poses(results: pd.DataFrame, poses: list, methods: list[str]) -> list[dict]:
    """Per sensor pose: mean / median / max total error per method, ghost-locked runs, SME - KF paired."""
    by_pose = []
    for k, pose in enumerate(poses):
        block = {"pose": pose, "methods": {}}
        sub = results[results.pose == k]
        wide = sub.pivot(index="run", columns="method", values="total_error_m")
        wide_set = sub.pivot(index="run", columns="method", values="set_error_m")
        for m in methods:
            v = wide[m].to_numpy()
            ghost = wide_set[m].to_numpy() > GHOST_FACTOR * wide["kf"].to_numpy()
            block["methods"][m] = {
                "mean_total_error_m": float(np.mean(v)), "median_total_error_m": float(np.median(v)),
                "max_total_error_m": float(np.max(v)),
                "stderr_m": float(np.std(v, ddof=1) / np.sqrt(v.size)) if v.size > 1 else None,
                "mean_set_error_m": float(wide_set[m].mean()),
                "ghost_locked_runs": int(ghost.sum()),
                "mean_total_error_without_ghost_runs_m": float(np.mean(v[~ghost])) if (~ghost).any() else None,
            }
        d = (wide["sme"] - wide["kf"]).to_numpy()
        block["sme_minus_kf"] = {"mean_m": float(d.mean()), "median_m": float(np.median(d)),
                                 "stderr_m": float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else None,
                                 "runs_sme_better": int(np.sum(d < 0)), "runs": int(d.size),
                                 "fraction_of_runs_sme_better": float(np.mean(d < 0))}
        by_pose.append(block)
    return by_pose


def _lines(summary: dict) -> list[str]:
    lines = [f"sme: {summary['runs']} runs x {summary['n_steps']} steps, total error (13) [m] per sensor pose: "
             "mean / median (ghost-locked runs)"]
    for b in summary["by_pose"]:
        cells = "; ".join(f"{m} {v['mean_total_error_m']:.3f} / {v['median_total_error_m']:.3f} ({v['ghost_locked_runs']})"
                          for m, v in b["methods"].items())
        d = b["sme_minus_kf"]
        lines.append(f"  pose {b['pose']}: {cells}; sme - kf median {d['median_m']:+.3f} m, "
                     f"sme better in {d['runs_sme_better']} of {d['runs']} runs")
    return lines


def write_report(run_dir: Path) -> None:
    """report.html + figures/*.png from the files of ``run_dir``."""
    from experiments.report.figures import _new_fig, _save
    from experiments.report.html import _esc, _figure_html, _fmt, _page, _table

    run_dir = Path(run_dir)
    summary = json.loads((run_dir / "summary.json").read_text())
    curves = pd.read_parquet(run_dir / "curves.parquet")
    example = pd.read_parquet(run_dir / "example.parquet")
    figs = run_dir / "figures"
    figs.mkdir(exist_ok=True)
    methods = summary["methods"]
    colors = {"sme": "tab:green", "kf": "tab:blue", "sme_no_topology": "tab:gray", "sme_linearized": "tab:red"}

    fig = _new_fig(6.0, 4.2)
    ax = fig.subplots()
    for m in methods:
        g = example[example.method == m]
        for k, (v, gv) in enumerate(g.groupby("vehicle")):
            ax.plot(gv.px, gv.py, color=colors[m], lw=0.8, label=m if k == 0 else None)
    for k, (v, gv) in enumerate(example[example.method == methods[0]].groupby("vehicle")):
        ax.plot(gv.px_true, gv.py_true, color="k", lw=1.2, label="truth" if k == 0 else None)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(fontsize=8)
    ax.set_title("One run, sensor pose 0 (Fig. 2)")
    _save(fig, figs / "trajectories.png")

    n_pose = len(summary["by_pose"])
    fig = _new_fig(4.2 * n_pose, 3.4)
    axes = fig.subplots(1, n_pose, squeeze=False)[0]
    for k, ax in enumerate(axes):
        for m in methods:
            c = curves[(curves.pose == k) & (curves.method == m)]
            ax.plot(c.t, c.rmse_m, color=colors[m], label=m, lw=0.9)
        ax.set_title("sensor pose " + ", ".join(_fmt(x, 0) for x in summary["by_pose"][k]["pose"]))
        ax.set_xlabel("t [s]")
        ax.set_ylabel("total error at t, RMS over runs [m]")
        kf_curve = curves[(curves.pose == k) & (curves.method == "kf")].rmse_m
        ax.set_ylim(0, 1.6 * float(kf_curve.max()))  # a diverging run would hide the others
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    _save(fig, figs / "rmse_time.png")

    rows = []
    for k, b in enumerate(summary["by_pose"]):
        for m in methods:
            v = b["methods"][m]
            rows.append([str(k), _esc(", ".join(_fmt(x, 1) for x in b["pose"])), _esc(m),
                         f"{_fmt(v['mean_total_error_m'])} ± {_fmt(v['stderr_m'])}", _fmt(v["median_total_error_m"]),
                         _fmt(v["max_total_error_m"]), _fmt(v["mean_set_error_m"]), str(v["ghost_locked_runs"]),
                         _fmt(v["mean_total_error_without_ghost_runs_m"])])
    table = _table(["pose", "x, y [m], heading [deg]", "method", "mean total error (13) [m]", "median", "max",
                    "mean set error [m]", "ghost-locked runs", "mean without them [m]"], rows, left_cols=3)
    diff_rows = [[str(k), _fmt(b["sme_minus_kf"]["mean_m"]), _fmt(b["sme_minus_kf"]["stderr_m"]),
                  _fmt(b["sme_minus_kf"]["median_m"]),
                  f"{b['sme_minus_kf']['runs_sme_better']} of {b['sme_minus_kf']['runs']}"]
                 for k, b in enumerate(summary["by_pose"])]
    body = (
        f"<p>Zhang et al., SME filter. {summary['runs']} seeded runs of {summary['n_steps']} steps, seed "
        f"{summary['seed']}, git {_esc(summary['git'])}, wall time {summary['wall_seconds']:.1f} s. The same "
        "truth, GPS and sensor noise for each sensor pose (the filters are not told the pose).</p>"
        + table + "<h2>SME minus KF, paired over runs</h2>"
        + _table(["pose", "mean [m]", "std. error [m]", "median [m]", "runs SME better"], diff_rows)
        + "<p><b>Ghost lock.</b> A run is counted ghost-locked when its set error (best vehicle permutation "
        f"per step) exceeds {GHOST_FACTOR:g} times the KF's error in that run. The per-axis power sums (9) do "
        "not tie each x to its y, and the topology (10) equals N y_x,2 - y_x,1^2 + N y_y,2 - y_y,1^2, a function "
        "of (9)'s components, so pairings that permute the y coordinates among vehicles give exactly the same "
        "pseudo-measurements. In Zhang's scenario (vehicles east, north-east and north from one point) the "
        "ghost (80t, 0), (45t, 80t), (0, 45t) is such a pairing; a filter that locks onto it diverges linearly. "
        "It is a property of the paper's pseudo-measurements, not of the sensor pose.</p>"
        + _figure_html("rmse_time.png", "Error over time (Fig. 3)", "Total error at each step, RMS over runs; the axis stops at 1.6 times the KF's largest value, so a "
                       "diverging method leaves the plot (see the table).")
        + _figure_html("trajectories.png", "Trajectories (Fig. 2)", "Truth and estimates of the example run.")
    )
    (run_dir / "report.html").write_text(_page("sme: Zhang et al. SME filter vs Kalman filter", body))
