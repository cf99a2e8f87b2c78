"""``coloc tune SWEEP.toml --out DIR``: choose parameter values on the tuning seeds only.

The sweep file declares the candidates as its ``[sweep.grid]`` (every combination is a candidate), the
seeds as ``tune_seeds`` + ``eval_seeds`` (disjoint) and what to minimise::

    [sweep]
    name = "tune_lc"
    base = "../arterial_tlr_realistic.toml"
    tune_seeds = [101, 102, 103]
    eval_seeds = {start = 1, count = 30}          # never run by coloc tune
    objective = {method = "icp_da_lc", statistic = "rmse_pos_m"}
    [sweep.grid]
    "lc.visibility" = [0.5, 0.6, 0.7]
    "icp.own_consistency_gate" = [0.0, 0.99]

``coloc tune`` runs the grid on the tuning seeds only (an ordinary sweep folder in DIR, resumable); the
objective of a candidate is the mean over the tuning seeds of the method's scored statistic (summary.json:
after ``[analysis] warmup_s``, every zone pooled). The smallest wins (a tie: the first in grid order). It
writes ``DIR/tuned.toml``, an ``extends`` overlay of the base setting the chosen values, whose header says
what was tuned, on which seeds, with which objective and every candidate's score; ``DIR/tuned.resolved.toml``,
the overlay fully resolved; ``DIR/tuning.parquet``, the scores. ``[sweep.set]`` (e.g. a shorter duration)
applies to the tuning runs only and is not carried into the overlay.
"""
from __future__ import annotations

import dataclasses
import io
from pathlib import Path

import numpy as np
import pandas as pd

from couplers.errors import InputError
from couplers.publish import write_file_atomic
from experiments.config import load_config
from experiments.config_toml import toml_value, config_to_toml
from experiments.sweep.spec import SweepSpec, load_sweep

TUNED = "tuned.toml"
RESOLVED = "tuned.resolved.toml"
SCORES = "tuning.parquet"


def tuning_spec(path: str | Path) -> SweepSpec:
    """The sweep narrowed to its tuning seeds; refused when it cannot be tuned."""
    spec = load_sweep(path)
    if not spec.tune_seeds:
        raise InputError(spec.path, "sweep.tune_seeds", "coloc tune needs tune_seeds and eval_seeds (disjoint): it "
                                                        "runs the tuning seeds only")
    if spec.objective is None:
        raise InputError(spec.path, "sweep.objective", "coloc tune needs an objective = {method = \"...\", "
                                                       "statistic = \"rmse_pos_m\"}")
    if not spec.grid:
        raise InputError(spec.path, "sweep.grid", "coloc tune searches the grid's candidates: give at least one key")
    if spec.factors:
        raise InputError(spec.path, "sweep.factors", "coloc tune searches [sweep.grid] only (leave the factors out)")
    if spec.bases:
        raise InputError(spec.path, "sweep.bases", "coloc tune writes one overlay of one base: no [sweep.bases]")
    return dataclasses.replace(spec, seeds=spec.tune_seeds, tune_seeds=(), eval_seeds=())


def scores(spec: SweepSpec, sweep: pd.DataFrame) -> pd.DataFrame:
    """One row per candidate: the grid values, the objective's mean and standard error over the seeds, the
    number of seeds, and the rank (1: chosen)."""
    method, stat = spec.objective
    keys = spec.grid_keys
    rows = sweep[sweep["method"] == method]
    out = []
    for combo in _combos(spec):
        m = np.ones(len(rows), dtype=bool)
        for k, v in zip(keys, combo):
            m &= (rows[k].astype(object) == v).to_numpy()
        y = rows.loc[m, stat].to_numpy(dtype=float)
        out.append({**dict(zip(keys, combo)), "objective_mean": float(np.mean(y)) if len(y) else np.nan,
                    "objective_se": float(np.std(y, ddof=1) / np.sqrt(len(y))) if len(y) > 1 else np.nan,
                    "seeds": int(len(y))})
    df = pd.DataFrame(out)
    order = np.argsort(df["objective_mean"].to_numpy(), kind="stable")
    df["rank"] = 0
    df.loc[df.index[order], "rank"] = np.arange(1, len(df) + 1)
    for c in keys:
        if df[c].dtype == object:
            df[c] = df[c].astype("string")
    return df


def _combos(spec: SweepSpec) -> list[tuple]:
    import itertools

    return list(itertools.product(*[values for _, values in spec.grid]))


def overlay_text(spec: SweepSpec, table: pd.DataFrame, source: Path) -> str:
    """``tuned.toml``: the header (what, on what, how, every score) and the chosen values over the base."""
    method, stat = spec.objective
    best = table[table["rank"] == 1].iloc[0]
    keys = spec.grid_keys
    lines = [f"# Tuned by coloc tune from {source}",
             f"# parameters: {', '.join(keys)}",
             *[f"#   candidates {k} = {toml_value(list(v))}" for k, v in spec.grid],
             f"# objective: mean over the tuning seeds of {method}'s {stat} (summary.json, scored after the warm-up), "
             "smallest wins",
             f"# tuning seeds: {toml_value(list(spec.seeds))} (the evaluation seeds were not run)",
             *([f"# tuning runs with [sweep.set]: " + ", ".join(f"{k} = {toml_value(v)}" for k, v in spec.fixed)]
               if spec.fixed else []),
             "# scores (objective mean +- standard error over the seeds, m):"]
    for r in table.sort_values("rank", kind="stable").itertuples(index=False):
        vals = ", ".join(f"{k} = {toml_value(_plain(r[i]))}"
                         for i, k in enumerate(keys))
        lines.append(f"#   {r.rank:>3}. {vals}: {r.objective_mean:.4f} +- {r.objective_se:.4f} ({r.seeds} seeds)")
    lines += ["", f"extends = {toml_value(str(spec.base))}"]
    by_table: dict[str, list[str]] = {}
    for i, k in enumerate(keys):
        sec, key = k.split(".")
        by_table.setdefault(sec, []).append(f"{key} = {toml_value(_plain(best.iloc[i]))}")
    for sec, items in by_table.items():
        lines += ["", f"[{sec}]", *items]
    return "\n".join(lines) + "\n"


def _plain(v):
    """numpy / pandas scalars as Python values (TOML text)."""
    return v.item() if hasattr(v, "item") else (str(v) if isinstance(v, str) else v)


def write_tuning(spec: SweepSpec, out: Path, source: Path) -> tuple[pd.DataFrame, Path]:
    """After the tuning sweep: tuning.parquet, tuned.toml and tuned.resolved.toml in ``out``."""
    from experiments.runner import write_parquet

    sweep = pd.read_parquet(out / "sweep.parquet")
    table = scores(spec, sweep)
    buf = io.BytesIO()
    write_parquet(table, buf)
    write_file_atomic(out / SCORES, buf.getvalue())
    write_file_atomic(out / TUNED, overlay_text(spec, table, source).encode())
    cfg = load_config(out / TUNED)
    write_file_atomic(out / RESOLVED, config_to_toml(cfg, {"tuned_from": str(source)}).encode())
    return table, out / TUNED
