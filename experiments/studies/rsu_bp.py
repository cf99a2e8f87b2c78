"""Study of Fröhle et al. Sec. V (seed paper 001): the RSU particle BP on the synthetic scenario of
Sec. V-A against the GNSS-only Kalman filter, Figs. 3-5.

* Fig. 3: CDF over Monte Carlo runs of each vehicle's position RMSE (over the whole run), RSU BP
  against the GNSS-only Kalman filter (``study.runs`` runs of the base scenario).
* Fig. 4: mean RMSE against the V2F variance (``study.sweep.v2f_var``).
* Fig. 5: mean RMSE against the number of features K (``study.sweep.n_features``; K = 0 is the
  particle filter on GNSS alone, the reduce-to-Kalman case).

Run i of every point uses the same scenario and filter seeds (common random numbers: along the
V2F-variance sweep only the scale of the V2F noise changes); a sweep point equal to the base
scenario reuses the first runs of the base set. Results do not depend on ``study.workers``.

Outputs (atomically, as ``experiments.runner``): config.toml (resolved, with provenance),
results.parquet (one row per point, run, vehicle and method), summary.json, report.html and
figures/*.png. Timings are in summary.json only, so results.parquet is byte-identical for the same
config and seed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from tqdm import tqdm

from coloc.methods.rsu_bp import RsuBpParams, cv_kalman_filter, rsu_bp_filter
from couplers.errors import InputError, seed_problem
from couplers.frohle_scenario import FrohleScenarioParams, simulate
from experiments.config import section_from_table
from experiments.config_toml import toml_value
from experiments.scoring import score_association
from experiments.studies.ranges import STUDY_RANGES

METHODS = ("rsu_bp", "gnss_kf")
METHOD_LABELS = {"rsu_bp": "RSU BP (Fröhle et al.)", "gnss_kf": "GNSS-only Kalman filter"}
METHOD_COLORS = {"rsu_bp": "tab:red", "gnss_kf": "tab:blue"}
PAPER_KF_RMSE_VEHICLE2_M = 3.5  # Sec. V-B, text under Fig. 4


@dataclass(frozen=True)
class StudySection:
    kind: str = "rsu_bp"
    name: str = "rsu_bp"
    seed: int = 1
    runs: int = 20  # Monte Carlo runs of the base scenario (Fig. 3)
    workers: int = 1  # worker processes (1: this process)
    init_spread: float = 4.0  # inflation of the GNSS (+ V2F) covariance of the priors b_0 (footnote 1)

    def __post_init__(self):
        if self.runs < 1:
            raise ValueError("must be >= 1")
        if self.workers < 1:
            raise ValueError("must be >= 1")
        if (why := seed_problem(self.seed)) is not None:
            raise ValueError(why)
        if not self.init_spread >= 1.0:
            raise ValueError("must be >= 1")


@dataclass(frozen=True)
class SweepSection:
    v2f_var: tuple[float, ...] = (0.1, 0.3, 1.0, 3.0, 10.0)  # Fig. 4, m^2
    v2f_var_runs: int = 5
    n_features: tuple[int, ...] = (0, 1, 2, 3, 5)  # Fig. 5
    n_features_runs: int = 5

    def __post_init__(self):
        if any(not v > 0 for v in self.v2f_var):
            raise ValueError("V2F variances must be positive")
        if any(k < 0 for k in self.n_features):
            raise ValueError("numbers of features must be >= 0")
        if self.v2f_var_runs < 0 or self.n_features_runs < 0:
            raise ValueError("must be >= 0")


@dataclass(frozen=True)
class RsuBpStudy:
    path: Path
    study: StudySection
    scenario: FrohleScenarioParams
    filter: RsuBpParams
    sweep: SweepSection


def load_study(data: dict, path: Path, seed: int | None = None) -> RsuBpStudy:
    """Validate the ``[study]`` table; every error is an InputError naming the field."""
    table = dict(data["study"])
    unknown_top = sorted(set(data) - {"study"})
    if unknown_top:
        raise InputError(path, unknown_top[0], "unknown table (a study config has only [study] and its sub-tables)")
    subs = {}
    for name in ("scenario", "filter", "sweep"):
        sub = table.pop(name, {})
        if not isinstance(sub, dict):
            raise InputError(path, f"study.{name}", "expected a table")
        subs[name] = sub
    if seed is not None:
        table["seed"] = seed
    r = STUDY_RANGES["rsu_bp"]
    study = section_from_table(StudySection, table, "study", path, r)
    scenario = section_from_table(FrohleScenarioParams, subs["scenario"], "study.scenario", path, r)
    filt = section_from_table(RsuBpParams, subs["filter"], "study.filter", path, r)
    sweep = section_from_table(SweepSection, subs["sweep"], "study.sweep", path, r)
    if abs(filt.dt - scenario.dt) > 1e-12:
        raise InputError(path, "study.filter.dt", f"must equal study.scenario.dt = {scenario.dt!r}")
    if len(scenario.gnss_var) < 1:
        raise InputError(path, "study.scenario.gnss_var", "one variance per vehicle is needed")
    return RsuBpStudy(path=path, study=study, scenario=scenario, filter=filt, sweep=sweep)


def resolved_toml(cfg: RsuBpStudy, provenance: dict) -> str:
    lines = [f"# Resolved from {cfg.path}", ""]
    for header, obj in (("study", cfg.study), ("study.scenario", cfg.scenario), ("study.filter", cfg.filter),
                        ("study.sweep", cfg.sweep)):
        lines.append(f"[{header}]")
        for f in dataclasses.fields(obj):
            lines.append(f"{f.name} = {toml_value(getattr(obj, f.name))}")
        lines.append("")
    lines.append("[provenance]")
    for key, val in provenance.items():
        lines.append(f"{key} = {toml_value(val)}")
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- jobs


@dataclass(frozen=True)
class Job:
    point: str  # "base", "v2f_var", "n_features"
    v2f_var: float
    n_features: int
    run: int


def jobs_of(cfg: RsuBpStudy) -> tuple[list[Job], dict[Job, Job]]:
    """The distinct jobs to compute, and for every sweep job the job whose result it reuses."""
    base_var, base_k = cfg.scenario.v2f_var, cfg.scenario.n_features
    todo = [Job("base", base_var, base_k, i) for i in range(cfg.study.runs)]
    alias = {}

    def add(point, var, k, n_runs):
        for i in range(n_runs):
            job = Job(point, var, k, i)
            same = Job("base", var, k, i)
            if var == base_var and k == base_k and i < cfg.study.runs:
                alias[job] = same
            else:
                todo.append(job)

    for var in cfg.sweep.v2f_var:
        add("v2f_var", float(var), base_k, cfg.sweep.v2f_var_runs)
    for k in cfg.sweep.n_features:
        add("n_features", base_var, int(k), cfg.sweep.n_features_runs)
    return todo, alias


def _rmse(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """Per-vehicle RMSE over the run, (S,): sqrt(mean_t |est - truth|^2)."""
    return np.sqrt(np.mean(np.sum((est - truth) ** 2, axis=2), axis=0))


def run_job(cfg: RsuBpStudy, job: Job) -> tuple[list[dict], dict]:
    """One Monte Carlo run: the RSU BP and the GNSS-only KF on the same scenario realisation."""
    scen = dataclasses.replace(cfg.scenario, v2f_var=job.v2f_var, n_features=job.n_features)
    sc = simulate(scen, [cfg.study.seed, job.run, 0])
    params = cfg.filter
    rng = np.random.default_rng(np.random.SeedSequence([cfg.study.seed, job.run, 1]))
    t0 = time.perf_counter()
    bp = rsu_bp_filter(sc.gnss_z, sc.gnss_cov, sc.v2f_z, sc.v2f_cov, sc.v2f_owner, job.n_features, params, rng,
                       init_spread=cfg.study.init_spread)
    bp_seconds = time.perf_counter() - t0
    n_s = sc.gnss_z.shape[1]
    mean0 = np.concatenate([sc.gnss_z[0], np.zeros((n_s, 2))], axis=1)
    cov0 = np.zeros((n_s, 4, 4))
    cov0[:, :2, :2] = cfg.study.init_spread * sc.gnss_cov  # the same prior as the particle BP's vehicles
    cov0[:, 2:, 2:] = params.vehicle_init_velocity_std**2 * np.eye(2)
    t0 = time.perf_counter()
    km, _ = cv_kalman_filter(sc.gnss_z, sc.gnss_cov, mean0, cov0, params.dt, params.process_intensity)
    kf_seconds = time.perf_counter() - t0

    correct_pct = float("nan")
    if job.n_features:
        assign = bp.v2f_association.argmax(axis=2)
        counts, _ = score_association([(assign[t], sc.v2f_feature[t]) for t in range(assign.shape[0])])
        correct_pct = 100.0 * counts[:, 0].sum() / max(counts.sum(), 1)
    rows = []
    for method, est in (("rsu_bp", bp.vehicle_mean), ("gnss_kf", km)):
        pos = _rmse(est[:, :, :2], sc.x_true[:, :, :2])
        vel = _rmse(est[:, :, 2:], sc.x_true[:, :, 2:])
        for s in range(n_s):
            rows.append({
                "point": job.point, "v2f_var": job.v2f_var, "n_features": job.n_features, "run": job.run,
                "vehicle": str(s + 1), "gnss_var": float(cfg.scenario.gnss_var[s]), "method": method,
                "rmse_pos_m": float(pos[s]), "rmse_vel_mps": float(vel[s]),
                "association_correct_pct": correct_pct if method == "rsu_bp" else float("nan"),
            })
    timing = {"rsu_bp_s": bp_seconds, "gnss_kf_s": kf_seconds, "steps": int(sc.t.size),
              "rsu_bp_step_median_s": float(np.median(bp.seconds))}
    return rows, timing


def _run_job_packed(args):
    return run_job(*args)


# --------------------------------------------------------------------------- summary and report


def _stats(x: pd.Series) -> dict:
    x = np.asarray(x, dtype=float)
    return {"mean": float(x.mean()), "median": float(np.median(x)),
            "sem": float(x.std(ddof=1) / math.sqrt(x.size)) if x.size > 1 else None, "runs": int(x.size)}


def _point_table(results: pd.DataFrame, point: str, key: str) -> list[dict]:
    out = []
    sub = results[results["point"] == point]
    for value, g in sub.groupby(key, sort=True):
        entry = {key: value.item() if hasattr(value, "item") else value, "vehicles": {}}
        for (veh, method), gg in g.groupby(["vehicle", "method"], sort=True):
            entry["vehicles"].setdefault(veh, {})[method] = _stats(gg["rmse_pos_m"])
        assoc = g[g["method"] == "rsu_bp"]["association_correct_pct"].dropna()
        entry["association_correct_pct"] = float(assoc.mean()) if len(assoc) else None
        out.append(entry)
    return out


def summarize(cfg: RsuBpStudy, results: pd.DataFrame, timings: list[dict], git: str, wall: float) -> dict:
    base = results[results["point"] == "base"]
    vehicles = {}
    for (veh, method), g in base.groupby(["vehicle", "method"], sort=True):
        block = vehicles.setdefault(veh, {"gnss_var_m2": float(g["gnss_var"].iloc[0])})
        block[method] = {"rmse_pos_m": _stats(g["rmse_pos_m"]), "rmse_vel_mps": _stats(g["rmse_vel_mps"])}
    assoc = base[base["method"] == "rsu_bp"]["association_correct_pct"].dropna()
    bp_s = float(sum(t["rsu_bp_s"] for t in timings))
    steps = int(sum(t["steps"] for t in timings))
    summary = {
        "config": str(cfg.path), "study": "rsu_bp", "seed": cfg.study.seed, "git": git,
        "base": {"runs": cfg.study.runs, "n_steps": cfg.scenario.n_steps, "n_features": cfg.scenario.n_features,
                 "v2f_var_m2": cfg.scenario.v2f_var, "n_particles": cfg.filter.n_particles,
                 "vehicles": vehicles,
                 "association_correct_pct": float(assoc.mean()) if len(assoc) else None},
        "paper": {"gnss_kf_rmse_vehicle2_m": PAPER_KF_RMSE_VEHICLE2_M},
        "v2f_var_sweep": _point_table(results, "v2f_var", "v2f_var"),
        "n_features_sweep": _point_table(results, "n_features", "n_features"),
        "timing": {"jobs": len(timings), "rsu_bp_seconds": bp_s, "gnss_kf_seconds": float(sum(t["gnss_kf_s"] for t in timings)),
                   "rsu_bp_ms_per_step": 1000.0 * bp_s / max(steps, 1), "wall_seconds": wall,
                   "workers": cfg.study.workers},
    }
    lines = [f"rsu_bp study: {cfg.study.runs} base runs of {cfg.scenario.n_steps} steps, K = {cfg.scenario.n_features}, "
             f"V2F variance {cfg.scenario.v2f_var} m^2, Np = {cfg.filter.n_particles}"]
    for veh, block in vehicles.items():
        bp, kf = block["rsu_bp"]["rmse_pos_m"], block["gnss_kf"]["rmse_pos_m"]
        lines.append(f"  vehicle {veh} (GNSS variance {block['gnss_var_m2']:g} m^2): position RMSE mean "
                     f"{bp['mean']:.3f} m RSU BP vs {kf['mean']:.3f} m GNSS-only KF (median {bp['median']:.3f} vs "
                     f"{kf['median']:.3f})")
    if summary["base"]["association_correct_pct"] is not None:
        lines.append(f"  association: {summary['base']['association_correct_pct']:.1f} % of V2F rows on their "
                     "track's feature")
    for name, key, unit in (("v2f_var_sweep", "v2f_var", " m^2"), ("n_features_sweep", "n_features", "")):
        for entry in summary[name]:
            parts = [f"vehicle {veh}: {d['rsu_bp']['mean']:.3f} m" for veh, d in entry["vehicles"].items()]
            lines.append(f"  {key} = {entry[key]:g}{unit}: RSU BP " + ", ".join(parts))
    lines.append(f"  {len(timings)} runs, RSU BP {summary['timing']['rsu_bp_ms_per_step']:.1f} ms per step, "
                 f"wall {wall:.0f} s")
    summary["lines"] = lines
    return summary


def _fig_cdf(results: pd.DataFrame, path: Path) -> None:
    from experiments.report.figures import _new_fig, _save

    base = results[results["point"] == "base"]
    vehicles = sorted(base["vehicle"].unique(), key=int)
    fig = _new_fig(4.2 * len(vehicles), 3.4)
    axes = fig.subplots(1, len(vehicles), squeeze=False)[0]
    for ax, veh in zip(axes, vehicles):
        for method in METHODS:
            x = np.sort(base[(base["vehicle"] == veh) & (base["method"] == method)]["rmse_pos_m"].to_numpy())
            ax.step(x, np.arange(1, x.size + 1) / x.size, where="post", color=METHOD_COLORS[method],
                    label=METHOD_LABELS[method])
        ax.set_title(f"vehicle {veh} (GNSS variance {base[base['vehicle'] == veh]['gnss_var'].iloc[0]:g} m²)")
        ax.set_xlabel("position RMSE over the run [m]")
        ax.set_ylabel("CDF over Monte Carlo runs")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    _save(fig, path)


def _fig_sweep(results: pd.DataFrame, point: str, key: str, xlabel: str, path: Path, logx: bool) -> None:
    """Mean RMSE (error bars: standard error over runs) against the swept value, one panel per
    vehicle (their scales differ by an order of magnitude)."""
    from matplotlib.ticker import NullFormatter, ScalarFormatter

    from experiments.report.figures import _new_fig, _save

    sub = results[results["point"] == point]
    vehicles = sorted(sub["vehicle"].unique(), key=int)
    fig = _new_fig(4.2 * len(vehicles), 3.4)
    axes = fig.subplots(1, len(vehicles), squeeze=False)[0]
    for ax, veh in zip(axes, vehicles):
        for method in METHODS:
            g = sub[(sub["vehicle"] == veh) & (sub["method"] == method)].groupby(key)["rmse_pos_m"]
            mean, sem = g.mean(), g.sem().fillna(0.0)
            ax.errorbar(mean.index.to_numpy(dtype=float), mean.to_numpy(), yerr=sem.to_numpy(),
                        color=METHOD_COLORS[method], linestyle="-" if method == "rsu_bp" else ":", marker="o",
                        ms=4, capsize=2, label=METHOD_LABELS[method])
        if logx:
            ax.set_xscale("log")
            ax.xaxis.set_major_formatter(ScalarFormatter())
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_xticks(sorted(sub[key].unique()))
        else:
            ax.set_xticks(sorted(sub[key].unique()))
        ax.set_ylim(bottom=0)
        gnss_var = sub[sub["vehicle"] == veh]["gnss_var"].iloc[0]
        ax.set_title(f"vehicle {veh} (GNSS variance {gnss_var:g} m²)")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("mean position RMSE over the run [m]")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    _save(fig, path)


def write_report(out: Path, cfg: RsuBpStudy, results: pd.DataFrame, summary: dict) -> None:
    from experiments.report.html import _esc, _figure_html, _fmt, _page, _table

    figs = out / "figures"
    figs.mkdir(exist_ok=True)
    body = [f"<p>Fröhle et al. (WCNC 2018) Sec. V-A scenario: {len(cfg.scenario.gnss_var)} vehicles with GNSS "
            f"variances {', '.join(f'{v:g}' for v in cfg.scenario.gnss_var)} m², K = {cfg.scenario.n_features} "
            f"crossing features, ΔT = {cfg.scenario.dt} s, r = {cfg.scenario.process_intensity}, V2F variance "
            f"{cfg.scenario.v2f_var} m², P = {cfg.filter.da_iterations}, I = {cfg.filter.correction_iterations}, "
            f"Np = {cfg.filter.n_particles}, {cfg.scenario.n_steps} steps. Seed {cfg.study.seed}; "
            f"git {_esc(summary['git'])}.</p>"]
    rows = []
    for veh, block in summary["base"]["vehicles"].items():
        for method in METHODS:
            s = block[method]["rmse_pos_m"]
            rows.append([f"vehicle {_esc(veh)}", _esc(METHOD_LABELS[method]), _fmt(s["mean"]), _fmt(s["median"]),
                         _fmt(s["sem"]), _fmt(block[method]["rmse_vel_mps"]["mean"]), str(s["runs"])])
    body.append("<h2>Base scenario</h2>")
    body.append(_table(["vehicle", "method", "mean pos. RMSE [m]", "median [m]", "s.e.m. [m]",
                        "mean vel. RMSE [m/s]", "runs"], rows, left_cols=2))
    body.append(f"<p>The paper reports 3.5 m for the GNSS-only Kalman filter of vehicle 2. "
                f"Association: {_fmt(summary['base']['association_correct_pct'], 1)} % of V2F rows were given "
                "(by the largest β η) the track whose majority feature produced them.</p>")
    _fig_cdf(results, figs / "fig3_rmse_cdf.png")
    body.append(_figure_html("fig3_rmse_cdf.png", "Fig. 3: CDF of the vehicle position RMSE",
                             f"{cfg.study.runs} Monte Carlo runs of the base scenario."))
    if cfg.sweep.v2f_var and cfg.sweep.v2f_var_runs:
        _fig_sweep(results, "v2f_var", "v2f_var", "V2F measurement variance [m²]", figs / "fig4_rmse_v2f_var.png",
                   logx=True)
        body.append(_figure_html("fig4_rmse_v2f_var.png", "Fig. 4: RMSE against the V2F variance",
                                 f"Mean over {cfg.sweep.v2f_var_runs} runs per point (error bars: standard error)."))
    if cfg.sweep.n_features and cfg.sweep.n_features_runs:
        _fig_sweep(results, "n_features", "n_features", "number of features K", figs / "fig5_rmse_features.png",
                   logx=False)
        body.append(_figure_html("fig5_rmse_features.png", "Fig. 5: RMSE against the number of features",
                                 f"Mean over {cfg.sweep.n_features_runs} runs per point; K = 0 is the particle "
                                 "filter on GNSS alone."))
    t = summary["timing"]
    body.append(f"<p>{t['jobs']} runs; RSU BP {_fmt(t['rsu_bp_ms_per_step'], 1)} ms per step on average, wall time "
                f"{_fmt(t['wall_seconds'], 0)} s with {t['workers']} worker(s) (timings depend on the machine's load)."
                "</p>")
    (out / "report.html").write_text(_page(f"RSU particle BP (Fröhle et al.): {cfg.study.name}", "\n".join(body)))


# --------------------------------------------------------------------------- entry point


def run(data: dict, path: Path, out: Path, seed: int | None, progress: bool, force: bool = False) -> dict:
    from couplers.publish import staged_folder
    from experiments.runner import git_revision, write_parquet

    cfg = load_study(data, Path(path), seed)
    todo, alias = jobs_of(cfg)
    with staged_folder(Path(out), "run", force=force) as tmp:
        t_start = time.perf_counter()
        bar = tqdm(total=len(todo), desc=cfg.study.name, unit="run", disable=not (progress and sys.stderr.isatty()),
                   mininterval=1.0)
        results_of: dict[Job, tuple[list[dict], dict]] = {}
        if cfg.study.workers == 1:
            for job in todo:
                results_of[job] = run_job(cfg, job)
                bar.update()
        else:
            with ProcessPoolExecutor(max_workers=cfg.study.workers) as pool:
                for job, res in zip(todo, pool.map(_run_job_packed, [(cfg, j) for j in todo])):
                    results_of[job] = res
                    bar.update()
        bar.close()
        wall = time.perf_counter() - t_start
        rows = []
        for job in todo:
            rows.extend(results_of[job][0])
        for job, same in alias.items():
            rows.extend({**r, "point": job.point} for r in results_of[same][0])
        results = pd.DataFrame(rows)
        order = {"base": 0, "v2f_var": 1, "n_features": 2}
        results = results.sort_values(
            ["point", "v2f_var", "n_features", "run", "vehicle", "method"],
            key=lambda c: c.map(order) if c.name == "point" else c, kind="mergesort",
        ).reset_index(drop=True)
        results = results.astype({"point": "string", "vehicle": "string", "method": "string"})
        git = git_revision()
        (tmp / "config.toml").write_text(resolved_toml(cfg, {"git": git, "config_source": str(cfg.path)}))
        write_parquet(results, tmp / "results.parquet")
        summary = summarize(cfg, results, [results_of[j][1] for j in todo], git, wall)
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        write_report(tmp, cfg, results, summary)
    return summary


def rebuild_report(out: Path) -> Path:
    """Re-draw report.html and figures/ of a finished study folder from its config.toml, results.parquet
    and summary.json (e.g. after a change of the report code; the numbers are not recomputed)."""
    from couplers.errors import read_toml

    out = Path(out)
    for name in ("config.toml", "results.parquet", "summary.json"):
        if not (out / name).is_file():
            raise InputError(out / name, None, "not found: is this an rsu_bp study output folder?")
    data = read_toml(out / "config.toml", "config file")
    data.pop("provenance", None)
    cfg = load_study(data, out / "config.toml")
    results = pd.read_parquet(out / "results.parquet")
    summary = json.loads((out / "summary.json").read_text())
    write_report(out, cfg, results, summary)
    return out / "report.html"
