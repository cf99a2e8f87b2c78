"""``DIR/effects.parquet`` and ``DIR/effects.png`` of a sweep with ``design = "full"`` or ``"fractional"``:
main effects and two-factor interactions on each method's RMSE (:func:`experiments.sweep.design.effects`),
per combination of the grid's values, over the scored runs (the evaluation seeds when declared)."""
from __future__ import annotations

import io

import numpy as np
import pandas as pd

from experiments.sweep import design as dsg

RESPONSE = "rmse_pos_m"


def effects_table(spec, sweep: pd.DataFrame) -> pd.DataFrame:
    """One row per (grid values, method, term): effect of the factor (or interaction) from its first to its
    second level on the run's position RMSE, its 95 % t interval, the terms it is aliased with. Only designs
    whose factors all have two levels are estimated (empty otherwise)."""
    if not len(sweep) or any(len(f.levels) != 2 for f in spec.factors):
        return pd.DataFrame()
    k = len(spec.factors)
    names = [f.name for f in spec.factors]
    highs = [f.levels[1].label for f in spec.factors]
    keys = spec.grid_keys
    rows = []
    groups = sweep.groupby(keys + ["method"], sort=False, dropna=False) if keys else sweep.groupby(["method"], sort=False)
    for gkey, g in groups:
        gkey = gkey if isinstance(gkey, tuple) else (gkey,)
        g = g[np.isfinite(g[RESPONSE].to_numpy(dtype=float))]
        levels = np.stack([np.where(g[n].astype(str).to_numpy() == h, 1, -1) for n, h in zip(names, highs)], axis=1)
        if len(g) <= len(dsg.model_terms(k, spec.generators)) + 1:
            continue  # no residual degree of freedom: no interval
        for r in dsg.effects(levels, g[RESPONSE].to_numpy(dtype=float), k, spec.generators, names):
            rows.append({**dict(zip(keys + ["method"], gkey)), "response": RESPONSE, **r, "n_runs": len(g),
                         "low": ",".join(f.levels[0].label for f in spec.factors if f.name in r["term"].split(" x ")),
                         "high": ",".join(f.levels[1].label for f in spec.factors if f.name in r["term"].split(" x "))})
    df = pd.DataFrame(rows)
    if not len(df):
        return df
    for c in df.columns:
        if df[c].dtype == object:
            df[c] = df[c].astype("string")
    return df


def effects_figure(eff: pd.DataFrame) -> bytes:
    """A PNG: one panel per (grid values, method), a horizontal bar per term with its 95 % interval."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    group_cols = [c for c in eff.columns if c not in ("response", "term", "letters", "aliases", "effect", "ci_low",
                                                      "ci_high", "se", "dof", "n_runs", "low", "high")]
    groups = list(eff.groupby(group_cols, sort=False)) if group_cols else [((), eff)]
    n_terms = eff.groupby(group_cols, sort=False).size().max() if group_cols else len(eff)
    fig, axes = plt.subplots(1, len(groups), figsize=(4.2 * len(groups), 0.32 * n_terms + 1.5), squeeze=False,
                             sharey=True)
    for ax, (gkey, g) in zip(axes[0], groups):
        y = np.arange(len(g))[::-1]
        ax.barh(y, g["effect"], color=["#4477aa" if len(t) == 1 else "#cc6677" for t in g["letters"]])
        ax.errorbar(g["effect"], y, xerr=[g["effect"] - g["ci_low"], g["ci_high"] - g["effect"]], fmt="none",
                    ecolor="black", capsize=2, lw=0.8)
        ax.axvline(0.0, color="grey", lw=0.6)
        ax.set_yticks(y, g["term"])
        gkey = gkey if isinstance(gkey, tuple) else (gkey,)
        ax.set_title(", ".join(str(v) for v in gkey), fontsize=9)
        ax.set_xlabel("effect on RMSE, m (95 % CI)")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()
