"""Monte Carlo and parameter sweeps on Dask: ``coloc sweep SWEEP.toml --out DIR``.

A sweep file names a base run config, the seeds and a grid of parameters::

    [sweep]
    name = "fig8_9_crossroad_nf"
    base = "../crossroad.toml"            # relative to the sweep file
    seeds = {start = 1, count = 200}      # or a list: [1, 2, 3]
    methods = ["gnss", "icp_known_da"]    # optional: overrides [run] methods
    distance_bin_m = 20.0                 # optional: bin of the RMSE-vs-distance curves (crossroad)

    [sweep.set]                           # optional: fixed overrides of the base config
    "run.duration_s" = 30.0

    [sweep.grid]                          # dotted keys -> lists; runs = product x seeds
    "crossroad.n_features" = [3, 10, 20, 60]
    "lc.eta_threshold" = [0.5, 1.0]

A grid key may select the base config per value (``[sweep.bases]``, e.g. each control from its own
preset: ``"scenario.control" = {vsr = "../arterial_vsr_realistic.toml"}``); a factor level's own
``base`` still wins.

Any key of a run config's tables can be swept or set, including the optional ``[infra]``
(e.g. ``"infra.rsu_range_m" = [40.0, 70.0, 100.0]``; the base config must have the ``[infra]``
table: a sweep varies infrastructure mode, it does not switch it on). Every run's config is
validated before anything runs and saved fully resolved in its run folder (``config.toml``).

Every run is an ordinary run (:func:`experiments.runner.run_experiment`, without
the per-run HTML report) written to ``DIR/runs/<run_id>/`` where run_id is
built from the swept values and the seed (e.g.
``n_features=20,eta_threshold=0.5,seed=7``). Runs execute on a
``dask.distributed`` LocalCluster of single-threaded worker processes (libsumo
holds one simulation per process), or on a running scheduler given with
``--scheduler`` (its workers must import this package and see DIR).

Resumable: a run folder appears complete or not at all (atomic rename), so a
restart computes only the missing runs and removes the hidden partial folders
a killed run left behind. The resolved sweep (including a hash of the resolved
base config) is stored in ``DIR/sweep.toml``; a restart with a different sweep
into the same DIR is refused. The files the runs read (every config TOML loaded, ``extends``
chains included, and every file of each run's net folder) are stored with their sha256 in
``DIR/inputs.json``: a restart after one of them changed is refused, naming the file, while a
finished run was made with the old one; ``--force`` then recomputes those runs (only the runs that
read the changed file). A lock (``.DIR.lock`` beside DIR) keeps two commands from writing into
one DIR at once.

Outputs, computed from the run files only and byte-identical for the same
sweep (sorted rows, no timestamps):

* ``DIR/sweep.parquet``: one row per (run, method): run_id, seed, every swept
  parameter as a column named by its dotted key, the summary numbers; when runs have
  ``[infra]``, also ``covered_rmse_pos_m``, ``covered_p95_pos_m`` and ``covered_n``: the
  summary's ``within_rsu_coverage`` (every method on the same covered vehicle-steps of a run).
* ``DIR/curves.parquet``: per (setting, method) aggregates over the Monte Carlo
  runs, one ``curve`` kind per figure of Brambilla Sec. V:
  ``time`` (RMSE over time, Fig. 7: x = t), ``feature_time`` (feature RMSE
  over time), ``distance`` (RMSE versus the distance of the true position to
  the junction centre, Figs. 8 and 10: x = bin centre, crossroad only),
  ``association`` (correct / wrong / discarded percentages of all V2F rows,
  Figs. 9 and 11), ``overall`` and ``feature_overall`` (pooled RMSE).
  RMSE = sqrt(mean of the squared error over all runs and vehicles).
* ``DIR/report.html`` with ``DIR/figures/*.png`` (:mod:`experiments.sweep.report`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import math
import os
import sys
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from couplers.errors import InputError, recording_reads
from couplers.publish import check_members, check_target, make_folder, mark, publish_files
from experiments.scoring import scored_mask
from experiments.config import Config
from experiments.config_toml import toml_value
from experiments.sweep.consistency import consistency_table, nees_partial
from experiments.sweep.zones import aggregate_zones, degree_partial, zone_partials
from experiments.sweep.spec import (  # noqa: F401 (re-exported: the names of the sweep, one import path)
    SPEC_KEYS,
    FORBIDDEN_KEYS,
    DEFAULT_DISTANCE_BIN_M,
    RUNS_DIR,
    CURVE_KINDS,
    COVERED_COLUMNS,
    SweepSpec,
    SweepRun,
    settings_of,
    _check_dotted,
    _seeds,
    load_sweep,
    _grid_bases,
    _grid_base,
    _load_base,
    _config,
    _value_text,
    _safe,
    _short_names,
    run_id_of,
    expand_runs,
    resolved_spec_toml,
    _first_difference,
)
from experiments.sweep.folder import (  # noqa: F401 (re-exported: the names of the sweep, one import path)
    _acquire_lock,
    _check_spec,
    _check_or_write_spec,
    INPUTS_FILE,
    OWN_FILES,
    TABLES,
    _sha256,
    _net_files,
    sweep_inputs,
    _inputs_text,
    _check_inputs,
    _restart_changed,
    clean_leftovers,
    run_complete,
)

# --------------------------------------------------------------------------- #
# Work done on a Dask worker
# --------------------------------------------------------------------------- #

# libsumo holds one simulation per process: on a multi-threaded worker, SUMO runs are serialised.
_SUMO_LOCK = threading.Lock()


def execute_run(cfg: Config, run_dir: str, distance_bin_m: float) -> dict:
    """Run (unless already complete) and return the run's partial sums for the sweep outputs.

    Never raises: errors (libsumo's cannot be pickled) come back as text.
    """
    run_dir = Path(run_dir)
    status = "present"
    try:
        if not run_complete(run_dir):
            from experiments.runner import run_experiment

            if cfg.is_controlled_scenario:
                run_experiment(cfg, run_dir, progress=False, write_report=False)
            else:
                with _SUMO_LOCK:
                    run_experiment(cfg, run_dir, progress=False, write_report=False)
            status = "computed"
        centre = tuple(cfg.crossroad.centre) if cfg.scenario.kind == "crossroad" else None
        return {"status": status, "partials": run_partials(run_dir, centre, distance_bin_m)}
    except BaseException as exc:  # noqa: BLE001 - reported to the client as text
        if isinstance(exc, KeyboardInterrupt):
            raise
        msg = exc.describe() if isinstance(exc, InputError) else f"{type(exc).__name__}: {exc}"
        return {"status": "error", "error": msg, "traceback": traceback.format_exc()}


def _sse(df: pd.DataFrame, keys: list[str], cols: dict[str, str]) -> pd.DataFrame:
    """Sums of squares of ``cols`` (source -> output name) and counts per ``keys``."""
    tmp = df[keys].copy()
    for src, dst in cols.items():
        v = df[src].to_numpy(dtype=float)
        tmp[dst] = v * v
    tmp["n"] = 1
    return tmp.groupby(keys, sort=True, observed=True).sum().reset_index()


def run_partials(run_dir: Path, centre: tuple[float, float] | None, distance_bin_m: float) -> dict:
    """Per-run sums for the sweep outputs, read from the run's files (never from memory)."""
    import pyarrow.parquet as pq

    summary = json.loads((run_dir / "summary.json").read_text())
    coverage = summary.get("within_rsu_coverage")
    rows = []
    for method, block in summary["methods"].items():
        assoc = (summary.get("association") or {}).get(method) or {}
        feat = block.get("features") or {}
        row = {
            "method": method,
            "rmse_pos_m": block.get("rmse_pos_m"), "rmse_vel_mps": block.get("rmse_vel_mps"),
            "p50_pos_m": block.get("p50_pos_m"), "p95_pos_m": block.get("p95_pos_m"), "n": block.get("n"),
            "correct_pct": assoc.get("correct_pct"), "wrong_pct": assoc.get("wrong_pct"),
            "discarded_pct": assoc.get("discarded_pct"),
            "feature_rmse_pos_m": feat.get("rmse_pos_m"),
        }
        if coverage is not None:  # infrastructure mode: the same covered vehicle-steps for every method
            cb = coverage["methods"].get(method) or {}
            row.update({f"covered_{k}": cb.get(k) for k in COVERED_COLUMNS})
        rows.append(row)
    est = pq.read_table(run_dir / "estimates.parquet",
                        columns=["method", "t", "err_pos", "err_vel", "px_true", "py_true", "zone"]).to_pandas()
    est["method"] = est["method"].astype(str)
    # [analysis] warmup_s: the tables score what the run's summary scored (t >= scored_from_s)
    t0 = (summary.get("analysis") or {}).get("scored_from_s")
    if t0 is not None:
        est = est[scored_mask(est["t"], t0)]
    out = {"summary": rows}
    out["zone_sums"], out["zone_hist"] = zone_partials(est)
    out["degree"] = degree_partial(summary)
    out["nees"] = nees_partial(summary)
    out["time"] = _sse(est, ["method", "t"], {"err_pos": "sse_pos", "err_vel": "sse_vel"}).rename(columns={"t": "x"})
    out["overall"] = _sse(est, ["method"], {"err_pos": "sse_pos", "err_vel": "sse_vel"})
    if centre is not None:
        d = np.hypot(est["px_true"].to_numpy() - centre[0], est["py_true"].to_numpy() - centre[1])
        est["x"] = (np.floor(d / distance_bin_m) + 0.5) * distance_bin_m
        out["distance"] = _sse(est, ["method", "x"], {"err_pos": "sse_pos", "err_vel": "sse_vel"})
    fpath = run_dir / "features.parquet"
    if fpath.exists():
        feat = pq.read_table(fpath, columns=["method", "t", "err_pos"]).to_pandas()
        feat["method"] = feat["method"].astype(str)
        if t0 is not None:
            feat = feat[scored_mask(feat["t"], t0)]
        out["feature_time"] = _sse(feat, ["method", "t"], {"err_pos": "sse_pos"}).rename(columns={"t": "x"})
        out["feature_overall"] = _sse(feat, ["method"], {"err_pos": "sse_pos"})
    assoc = pq.read_table(run_dir / "association.parquet",
                          columns=["method", "t", "correct", "wrong", "discarded"]).to_pandas()
    assoc["method"] = assoc["method"].astype(str)
    assoc = (assoc[scored_mask(assoc["t"], t0)] if t0 is not None else assoc).drop(columns="t")
    out["association"] = assoc.groupby("method", sort=True).sum().reset_index()
    return out


# --------------------------------------------------------------------------- #
# Aggregation (client side, deterministic)
# --------------------------------------------------------------------------- #


def _param_columns(spec: SweepSpec, settings: np.ndarray) -> dict[str, np.ndarray | pd.Series]:
    """One column per swept key for the given setting indices, typed from the values; with factors, the
    string columns ``factor`` and ``level``."""
    all_settings = settings_of(spec)
    combos = [c for c, _ in all_settings]
    cols = {}
    for j, (key, values) in enumerate(spec.grid):
        vals = [c[j] for c in combos]
        if all(isinstance(v, bool) for v in values):
            arr = np.array(vals, dtype=bool)
        elif all(isinstance(v, int) and not isinstance(v, bool) for v in values):
            arr = np.array(vals, dtype=np.int64)
        elif all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            arr = np.array(vals, dtype=np.float64)
        else:
            arr = np.array([v if isinstance(v, str) else toml_value(v) for v in vals], dtype=object)
        col = arr[settings]
        cols[key] = pd.Series(col, dtype="string") if col.dtype == object else col
    if spec.factors:
        for name, attr in (("factor", "factor"), ("level", "level")):
            arr = np.array([getattr(v, attr) for _, v in all_settings], dtype=object)
            cols[name] = pd.Series(arr[settings], dtype="string")
    if spec.design != "one_at_a_time":  # a design: every factor's level label in a column of its own
        for j, f in enumerate(spec.factors):
            arr = np.array([v.combo[j][1] for _, v in all_settings], dtype=object)
            cols[f.name] = pd.Series(arr[settings], dtype="string")
    return cols


def paired_partials(spec: SweepSpec, runs: list[SweepRun], partials: list[dict]) -> pd.DataFrame:
    """``DIR/paired.parquet``: per setting and GNSS zone ("all" pools them), LC minus GNSS and LC minus
    known association of the per-seed RMSE (same seed, same traffic), mean over the seeds with its 95 %
    paired t interval and the number of seeds (:mod:`experiments.sweep.paired`). Empty without LC."""
    from experiments.sweep.paired import paired_table

    rows = []
    for run, part in zip(runs, partials):
        zs = part.get("zone_sums")
        if zs is None or not len(zs):
            continue
        for r in zs.itertuples(index=False):
            rows.append({"_setting": run.setting, "zone": str(r.zone), "seed": run.seed, "method": str(r.method),
                         "rmse_pos_m": math.sqrt(r.sse_pos / r.n) if r.n else math.nan})
    if not rows:
        return pd.DataFrame()
    t = paired_table(pd.DataFrame(rows), ["_setting", "zone"])
    if not len(t):
        return pd.DataFrame()
    params = _param_columns(spec, t["_setting"].to_numpy(dtype=np.int64))
    front = pd.DataFrame(params)
    rest = t.drop(columns=["_setting"]).reset_index(drop=True)
    rest["seeds"] = rest["seeds"].astype("int64")
    return pd.concat([front.reset_index(drop=True), rest], axis=1)


def aggregate(spec: SweepSpec, runs: list[SweepRun], partials: list[dict]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """sweep.parquet and curves.parquet tables from the runs' partial sums (in run order)."""
    method_rank = {m: i for i, m in enumerate(runs[0].cfg.run.methods)} if runs else {}
    # sweep.parquet: one row per (run, method)
    rows = []
    for k, (run, part) in enumerate(zip(runs, partials)):
        for r in part["summary"]:
            rows.append({"_run": k, "_setting": run.setting, "run_id": run.run_id, "seed": run.seed, **r})
    sweep = pd.DataFrame(rows)
    if len(sweep):
        sweep["_rank"] = sweep["method"].map(lambda m: method_rank.get(m, len(method_rank)))
        sweep = sweep.sort_values(["_setting", "seed", "_rank", "method"], kind="mergesort").reset_index(drop=True)
    params = _param_columns(spec, sweep["_setting"].to_numpy(dtype=np.int64))
    front = pd.DataFrame({"run_id": sweep["run_id"].astype("string"), "seed": sweep["seed"].astype("int64"), **params})
    numeric = ["rmse_pos_m", "rmse_vel_mps", "p50_pos_m", "p95_pos_m", "correct_pct", "wrong_pct",
               "discarded_pct", "feature_rmse_pos_m"]
    blocks = [front, sweep[["method"]].astype("string"), sweep[numeric].astype("float64"),
              sweep[["n"]].astype("int64")]
    if "covered_n" in sweep.columns:  # some run has [infra]: within-coverage columns (NaN / 0 for runs without)
        blocks += [sweep[[f"covered_{k}" for k in COVERED_COLUMNS if k != "n"]].astype("float64"),
                   sweep[["covered_n"]].fillna(0).astype("int64")]
    table = pd.concat(blocks, axis=1)

    # curves.parquet
    n_runs = np.bincount([r.setting for r in runs], minlength=len(settings_of(spec)))
    parts = []
    for kind in CURVE_KINDS:
        frames = []
        for run, part in zip(runs, partials):
            df = part.get(kind)
            if df is not None and len(df):
                df = df.copy()
                df.insert(0, "_setting", run.setting)
                frames.append(df)
        if not frames:
            continue
        df = pd.concat(frames, ignore_index=True)
        keys = ["_setting", "method"] + (["x"] if "x" in df.columns else [])
        g = df.groupby(keys, sort=True, observed=True).sum(numeric_only=True).reset_index()
        res = pd.DataFrame({"_setting": g["_setting"].to_numpy(dtype=np.int64), "method": g["method"].astype(str)})
        res["x"] = g["x"].to_numpy(dtype=float) if "x" in g else np.nan
        res["n_runs"] = n_runs[res["_setting"].to_numpy()]
        nan = np.full(len(g), np.nan)
        if kind == "association":
            total = (g["correct"] + g["wrong"] + g["discarded"]).to_numpy(dtype=float)
            safe = np.where(total > 0, total, np.nan)
            res["n_samples"] = total.astype(np.int64)
            res["rmse_pos_m"], res["rmse_vel_mps"] = nan, nan
            for c in ("correct", "wrong", "discarded"):
                res[f"{c}_pct"] = 100.0 * g[c].to_numpy(dtype=float) / safe
        else:
            n = g["n"].to_numpy(dtype=float)
            res["n_samples"] = g["n"].to_numpy(dtype=np.int64)
            res["rmse_pos_m"] = np.sqrt(g["sse_pos"].to_numpy(dtype=float) / n)
            res["rmse_vel_mps"] = np.sqrt(g["sse_vel"].to_numpy(dtype=float) / n) if "sse_vel" in g else nan
            for c in ("correct", "wrong", "discarded"):
                res[f"{c}_pct"] = nan
        res.insert(0, "curve", kind)
        parts.append(res)
    cols = ["curve", "_setting", "method", "x", "n_runs", "n_samples", "rmse_pos_m", "rmse_vel_mps",
            "correct_pct", "wrong_pct", "discarded_pct"]
    curves = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=cols)
    curves["_kind"] = curves["curve"].map({k: i for i, k in enumerate(CURVE_KINDS)})
    curves["_rank"] = curves["method"].map(lambda m: method_rank.get(m, len(method_rank)))
    curves = curves.sort_values(["_kind", "_setting", "_rank", "method", "x"], kind="mergesort").reset_index(drop=True)
    params = _param_columns(spec, curves["_setting"].to_numpy(dtype=np.int64))
    curves_out = pd.concat([
        pd.DataFrame({"curve": curves["curve"].astype("string"), **params,
                      "method": curves["method"].astype("string")}),
        curves[["x"]].astype("float64"),
        curves[["n_runs", "n_samples"]].astype("int64"),
        curves[["rmse_pos_m", "rmse_vel_mps", "correct_pct", "wrong_pct", "discarded_pct"]].astype("float64"),
    ], axis=1)
    return table, curves_out


# --------------------------------------------------------------------------- #
# Driver
# --------------------------------------------------------------------------- #


@dataclass
class SweepResult:
    out: Path
    n_runs: int
    computed: int
    present: int
    failed: list[tuple[str, str]]
    seconds: float
    workers: int
    dry_run: bool = False
    recomputed: int = 0  # finished runs computed again (--force) because a file they read changed
    workers_asked: int | None = None  # --workers when it was capped (:func:`cap_workers`), else None


class SweepFailed(Exception):
    """Some runs of a sweep failed; the completed ones are kept for a restart."""


def default_workers() -> int:
    try:
        ncpu = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        ncpu = os.cpu_count() or 1
    return max(1, min(ncpu, 4))


def usable_cores() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def cap_workers(asked: int, to_compute: int) -> int:
    """Local worker processes worth starting: at most the runs still to compute (a worker computes one
    run at a time, one more would only start and idle) and at most the usable cores (each worker is one
    single-threaded process: more than the cores only share them, each with its own SUMO and imports,
    and 100 workers starting at once on 2 cores time out connecting to the scheduler); at least 1."""
    return max(1, min(asked, to_compute, usable_cores()))


class _DaskClient:
    """A Client on a new LocalCluster of processes, or on a running scheduler."""

    def __init__(self, scheduler: str | None, workers: int, connect_timeout: str = "20s"):
        self.scheduler, self.workers, self.connect_timeout = scheduler, workers, connect_timeout
        self.cluster = self.client = None

    def __enter__(self):
        from dask.distributed import Client, LocalCluster

        if self.scheduler:
            try:
                self.client = Client(self.scheduler, timeout=self.connect_timeout)
            except (OSError, TimeoutError, ValueError) as exc:  # ValueError: not an address (no port, ...)
                raise InputError(None, "--scheduler", f"cannot connect to {self.scheduler} ({exc})") from None
        else:
            self.cluster = LocalCluster(n_workers=self.workers, threads_per_worker=1, processes=True,
                                        dashboard_address=None, silence_logs=logging.ERROR)
            self.client = Client(self.cluster)
        return self.client

    def __exit__(self, *exc):
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def run_sweep(spec_path: str | Path, out: str | Path, scheduler: str | None = None, workers: int | None = None,
              progress: bool = True, dry_run: bool = False, write_report: bool = True,
              connect_timeout: str = "20s", force: bool = False, spec: SweepSpec | None = None) -> SweepResult:
    """Run (or resume) a sweep; returns counts. Raises InputError on bad input, SweepFailed on failed runs.
    ``spec``: the sweep already loaded from ``spec_path`` (and possibly narrowed, e.g. by ``coloc tune``)."""
    t0 = time.perf_counter()
    spec = spec if spec is not None else load_sweep(spec_path)
    with recording_reads() as config_files:
        base_cfg, runs = expand_runs(spec)
    out = Path(out)
    # An empty folder or a sweep folder (``force``: any folder; never a file). Checked for --dry-run too.
    check_target(out, ("sweep",), force=force, replaces_folder=False)
    told, workers = workers, workers or default_workers()
    if dry_run:
        return SweepResult(out, len(runs), 0, 0, [], time.perf_counter() - t0, workers, dry_run=True)
    if workers < 1:
        raise InputError(None, "--workers", "must be >= 1")
    spec_text = resolved_spec_toml(spec, base_cfg, len(runs))
    inputs = sweep_inputs(spec, runs, config_files)
    if (out / "sweep.toml").exists():  # another sweep, then the same one on changed files (named by the file)
        _check_spec(out, spec_text, spec.path, ("base_config_sha256",))
    redo, ignore = _check_inputs(out, inputs, runs, force)
    if (out / "sweep.toml").exists():
        _check_spec(out, spec_text, spec.path, ignore)  # refuse a different sweep before starting anything
    need = [r for r in runs if r.run_id in redo or not run_complete(out / RUNS_DIR / r.run_id)]
    asked, workers = workers, workers if scheduler else cap_workers(workers, len(need))
    capped = told is not None and workers != asked and bool(need)  # a default is capped silently
    if capped and progress:
        print(f"{spec.name}: {workers} local worker(s), not {asked}: {len(need)} run(s) to compute on "
              f"{usable_cores()} usable core(s)", file=sys.stderr)
    # Nothing to compute (e.g. rebuilding the outputs): the runs are read here, no cluster needed.
    # Otherwise the cluster is started (or the scheduler reached) before anything is written.
    with (_DaskClient(scheduler, workers, connect_timeout) if need else contextlib.nullcontext()) as client:
        make_folder(out)
        mark(out, "sweep")
        lock = _acquire_lock(out, spec.path)
        try:
            check_members(out, OWN_FILES, force)  # a user's file of such a name: refused before any run
            _check_or_write_spec(out, spec_text, spec.path, ignore, force)
            _restart_changed(out, inputs, redo, force)
            res = _run_locked(spec, runs, out, spec_text, client, progress, write_report, workers, t0, force)
            return dataclasses.replace(res, recomputed=len(redo), workers_asked=asked if capped else None)
        finally:
            lock.close()


def _run_locked(spec: SweepSpec, runs: list[SweepRun], out: Path, spec_text: str, client, progress: bool,
                write_report: bool, workers: int, t0: float, force: bool = False) -> SweepResult:
    _check_or_write_spec(out, spec_text, spec.path, force=force)
    clean_leftovers(out)
    (out / RUNS_DIR).mkdir(exist_ok=True)
    partials: list[dict | None] = [None] * len(runs)
    failed: list[tuple[str, str]] = []
    computed = present = 0
    from tqdm import tqdm

    # Redirected stderr (logs, CI): a line every 30 s instead of a carriage-return stream.
    bar = tqdm(total=len(runs), desc=spec.name, unit="run", file=sys.stderr, disable=not progress,
               mininterval=0.5 if sys.stderr.isatty() else 30.0)

    def collect(k: int, res: dict) -> None:
        nonlocal computed, present
        if res["status"] == "error":
            failed.append((runs[k].run_id, res["error"]))
        else:
            partials[k] = res["partials"]
            computed += res["status"] == "computed"
            present += res["status"] == "present"
        bar.set_postfix(computed=computed, present=present, failed=len(failed), refresh=False)
        bar.update(1)

    if client is None:
        for k, run in enumerate(runs):
            collect(k, execute_run(run.cfg, str(out / RUNS_DIR / run.run_id), spec.distance_bin_m))
    else:
        from dask.distributed import as_completed

        futures = {}
        for k, run in enumerate(runs):
            fut = client.submit(execute_run, run.cfg, str(out / RUNS_DIR / run.run_id), spec.distance_bin_m,
                                key=f"coloc-sweep-{k}-{os.getpid()}-{time.time_ns()}", pure=False)
            futures[fut] = k
        for fut in as_completed(futures):
            collect(futures[fut], fut.result())
            fut.release()
    bar.close()
    if failed:
        failed.sort()
        raise SweepFailed(f"{len(failed)} of {len(runs)} runs failed (first: {failed[0][0]}: {failed[0][1]}); "
                          "completed runs are kept: rerun the same command to retry the others")
    if spec.eval_seeds:  # the tables and the report score the evaluation seeds only
        keep = [k for k, r in enumerate(runs) if r.seed in set(spec.eval_seeds)]
        runs, partials = [runs[k] for k in keep], [partials[k] for k in keep]
    table, curves = aggregate(spec, runs, partials)
    paired = paired_partials(spec, runs, partials)
    method_rank = {m: i for i, m in enumerate(runs[0].cfg.run.methods)} if runs else {}
    n_runs = np.bincount([r.setting for r in runs], minlength=len(settings_of(spec)))
    zones, v2v = aggregate_zones(runs, partials, lambda st: _param_columns(spec, st), n_runs, method_rank)
    consistency = consistency_table(runs, partials, lambda st: _param_columns(spec, st), method_rank)
    from experiments.runner import write_parquet

    outputs = [("sweep.parquet", table), ("curves.parquet", curves)]
    outputs += [(name, df) for name, df in (("zones.parquet", zones), ("v2v.parquet", v2v),
                                            ("paired.parquet", paired), ("consistency.parquet", consistency))
                if len(df)]
    tables = {}
    if spec.design != "one_at_a_time":  # main effects and two-factor interactions with their intervals
        from experiments.sweep.effects import effects_figure, effects_table

        eff = effects_table(spec, table)
        if len(eff):
            outputs.append(("effects.parquet", eff))
            tables["effects.png"] = effects_figure(eff)
    for name, df in outputs:
        buf = io.BytesIO()
        write_parquet(df, buf)
        tables[name] = buf.getvalue()
    # in the manifest, one rename each; coloc's table of an earlier pass that this one lacks is removed
    publish_files(out, tables, tuple(n for n in TABLES if n not in tables), force=force)
    if write_report:
        from experiments.sweep.report import write_sweep_report

        write_sweep_report(out, force=force)
    return SweepResult(out, len(runs), computed, present, [], time.perf_counter() - t0, workers)
