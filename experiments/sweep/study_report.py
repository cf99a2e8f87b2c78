"""Figures of the arterial studies in the sweep report: by GNSS zone, against one factor at a time
(``[sweep.factors]``, the realistic-sensing study) or against the first swept key (the V2X
penetration study), and the V2V degree distribution.

* ``factors_rmse_zone.png`` / ``factors_p95_zone.png``: RMSE / 95th percentile of the position error
  per zone (columns, last "all") against each factor's levels (rows; the preset where the factor
  puts it, else first), one line per method and grid combination;
* ``factors_association.png``: correct / wrong / discarded shares of V2F rows against each factor;
* ``factors_gap.png``: the RMSE of ICP-DA-LC minus that of ICP with known association per zone (the
  cost of not knowing the association);
* ``gain_zone.png``: the gain over GNSS (GNSS minus method, RMSE and p95) per zone against the first
  swept key (numeric), one line per method and value of the other swept keys;
* ``v2v_degree.png``: the mean V2V degree, its 10 / 50 / 90 % quantiles and the share of isolated
  vehicle-steps against the first swept key.

All from ``zones.parquet``, ``v2v.parquet`` and ``curves.parquet`` (experiments.sweep.zones).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_KNOWN_DA
from experiments.report.figures import _new_fig, _save
from experiments.report.html import _esc, _fmt, _table
from experiments.report.styles import method_color, method_label, order_methods

_LINESTYLES = ["-", "--", ":", "-."]
_MARKERS = ["o", "s", "^", "D", "v", "P"]
ALL = "all"


def _zone_order(zones: pd.DataFrame) -> list[str]:
    zs = sorted(z for z in zones["zone"].astype(str).unique() if z != ALL)
    return zs + [ALL]


def _combos(df: pd.DataFrame, keys: list[str]) -> list[dict]:
    if not keys:
        return [{}]
    return df[keys].drop_duplicates().sort_values(keys).to_dict("records")


def _select(df: pd.DataFrame, sel: dict) -> pd.DataFrame:
    for k, v in sel.items():
        df = df[df[k] == v]
    return df


def _combo_label(combo: dict) -> str:
    return ", ".join(f"{k.split('.')[-1]} = {v}" for k, v in combo.items())


def factor_axes(spec: dict) -> list[tuple[str, list[str], str | None]]:
    """(factor, its x labels, the label of the preset level) for every factor of the resolved sweep."""
    out = []
    for name, levels in (spec.get("factors") or {}).items():
        labels = [lv["label"] for lv in levels]
        preset = next((lv["label"] for lv in levels if lv.get("preset")), None)
        if preset is None:
            labels = ["preset"] + labels
            preset = "preset"
        out.append((name, labels, preset))
    return out


def _factor_rows(df: pd.DataFrame, factor: str, labels: list[str], preset: str) -> pd.DataFrame:
    """Rows of ``df`` on the factor's axis, with an ``x`` column (position among ``labels``)."""
    parts = []
    for i, lab in enumerate(labels):
        sel = df[(df["factor"] == "preset")] if lab == preset else df[(df["factor"] == factor) & (df["level"] == lab)]
        parts.append(sel.assign(x=float(i)))
    return pd.concat(parts, ignore_index=True) if parts else df.iloc[:0].assign(x=np.nan)


def fig_factors(zones: pd.DataFrame, spec: dict, grid_keys: list[str], ycol: str, ylabel: str, path: Path,
                from_zero: bool = True) -> int:
    axes_spec = factor_axes(spec)
    zorder = _zone_order(zones)
    combos = _combos(zones, grid_keys)
    fig = _new_fig(3.4 * len(zorder) + 2.8, 2.7 * len(axes_spec))
    axes = np.atleast_2d(fig.subplots(len(axes_spec), len(zorder), squeeze=False))
    n = 0
    for i, (factor, labels, preset) in enumerate(axes_spec):
        rows = _factor_rows(zones, factor, labels, preset)
        for j, z in enumerate(zorder):
            ax = axes[i, j]
            dz = rows[rows["zone"] == z]
            for m in order_methods(dz["method"].astype(str).unique()):
                for c, combo in enumerate(combos):
                    g = _select(dz[dz["method"] == m], combo).sort_values("x")
                    if not len(g):
                        continue
                    ax.plot(g["x"], g[ycol], color=method_color(m), ls=_LINESTYLES[c % 4], marker=_MARKERS[c % 6],
                            ms=3.5, lw=1.1, label=method_label(m) + (f" ({_combo_label(combo)})" if combo else ""))
                    n += 1
            ax.set_xticks(range(len(labels)), labels, fontsize=7)
            ax.set_title(f"{factor}, zone {z}" if z != ALL else f"{factor}, all zones", fontsize=9)
            if from_zero:
                ax.set_ylim(bottom=0)
            else:
                ax.axhline(0.0, color="0.5", lw=0.6)
            if j == 0:
                ax.set_ylabel(ylabel)
        if axes[i, -1].get_legend_handles_labels()[0]:
            axes[i, -1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7, borderaxespad=0.0)
    _save(fig, path)
    return n


def fig_factor_association(curves: pd.DataFrame, spec: dict, grid_keys: list[str], path: Path) -> None:
    axes_spec = factor_axes(spec)
    asc = curves[(curves["curve"] == "association") & curves["correct_pct"].notna()]
    cols = [("correct_pct", "correct"), ("wrong_pct", "wrong"), ("discarded_pct", "discarded")]
    combos = _combos(asc, grid_keys)
    fig = _new_fig(3.6 * 3 + 2.8, 2.7 * len(axes_spec))
    axes = np.atleast_2d(fig.subplots(len(axes_spec), 3, squeeze=False))
    for i, (factor, labels, preset) in enumerate(axes_spec):
        rows = _factor_rows(asc, factor, labels, preset)
        for j, (col, title) in enumerate(cols):
            ax = axes[i, j]
            for m in order_methods(rows["method"].astype(str).unique()):
                for c, combo in enumerate(combos):
                    g = _select(rows[rows["method"] == m], combo).sort_values("x")
                    if len(g):
                        ax.plot(g["x"], g[col], color=method_color(m), ls=_LINESTYLES[c % 4], marker=_MARKERS[c % 6],
                                ms=3.5, lw=1.1, label=method_label(m) + (f" ({_combo_label(combo)})" if combo else ""))
            ax.set_xticks(range(len(labels)), labels, fontsize=7)
            ax.set_title(f"{factor}: {title}", fontsize=9)
            ax.set_ylim(0, 100.5 if col == "correct_pct" else max(1.0, ax.get_ylim()[1]))
            if j == 0:
                ax.set_ylabel("% of V2F rows")
        if axes[i, -1].get_legend_handles_labels()[0]:
            axes[i, -1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7, borderaxespad=0.0)
    _save(fig, path)


def gap_table(zones: pd.DataFrame, keys: list[str], a: str = ICP_DA_LC.name, b: str = ICP_KNOWN_DA.name) -> pd.DataFrame:
    """RMSE of method ``a`` minus that of ``b`` per setting and zone (``keys``: the setting columns)."""
    za = zones[zones["method"] == a].set_index(keys + ["zone"])["rmse_pos_m"]
    zb = zones[zones["method"] == b].set_index(keys + ["zone"])["rmse_pos_m"]
    both = za.index.intersection(zb.index)
    return (za.loc[both] - zb.loc[both]).rename("gap_m").reset_index()


def fig_factor_gap(zones: pd.DataFrame, spec: dict, grid_keys: list[str], path: Path) -> bool:
    keys = grid_keys + ["factor", "level"]
    gap = gap_table(zones, keys)
    if not len(gap):
        return False
    fig_factors(gap.assign(method=ICP_DA_LC.name).rename(columns={"gap_m": "value"}), spec, grid_keys, "value",
                "LC − known DA RMSE [m]", path, from_zero=False)
    return True


def fig_gain(zones: pd.DataFrame, keys: list[str], path: Path) -> pd.DataFrame:
    """GNSS minus method, RMSE and p95, per zone against the first key; returns the gain table."""
    first, other = keys[0], keys[1:]
    g = zones[zones["method"] == GNSS.name].set_index(keys + ["zone"])[["rmse_pos_m", "p95_pos_m"]]
    rows = []
    for m in order_methods(zones["method"].astype(str).unique()):
        if m == GNSS.name:
            continue
        d = zones[zones["method"] == m].set_index(keys + ["zone"])[["rmse_pos_m", "p95_pos_m"]]
        both = d.index.intersection(g.index)
        gain = (g.loc[both] - d.loc[both]).add_prefix("gain_").reset_index()
        rows.append(gain.assign(method=m))
    gain = pd.concat(rows, ignore_index=True) if rows else pd.DataFrame()
    if not len(gain):
        return gain
    zorder = _zone_order(zones)
    combos = _combos(gain, other)
    fig = _new_fig(3.4 * len(zorder) + 2.8, 2.9 * 2)
    axes = np.atleast_2d(fig.subplots(2, len(zorder), squeeze=False))
    for i, (col, what) in enumerate((("gain_rmse_pos_m", "RMSE"), ("gain_p95_pos_m", "p95"))):
        for j, z in enumerate(zorder):
            ax = axes[i, j]
            dz = gain[gain["zone"] == z]
            for m in order_methods(dz["method"].astype(str).unique()):
                for c, combo in enumerate(combos):
                    s = _select(dz[dz["method"] == m], combo).sort_values(first)
                    if len(s):
                        ax.plot(s[first].astype(float), s[col], color=method_color(m), ls=_LINESTYLES[c % 4],
                                marker=_MARKERS[c % 6], ms=3.5, lw=1.1,
                                label=method_label(m) + (f" ({_combo_label(combo)})" if combo else ""))
            ax.axhline(0.0, color="0.5", lw=0.6)
            ax.set_title(f"{what} gain over GNSS, zone {z}" if z != ALL else f"{what} gain over GNSS, all zones",
                         fontsize=9)
            ax.set_xlabel(first)
            if j == 0:
                ax.set_ylabel("GNSS − method [m]")
        if axes[i, -1].get_legend_handles_labels()[0]:
            axes[i, -1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7, borderaxespad=0.0)
    _save(fig, path)
    return gain


def degree_stats(v2v: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Per setting: vehicle-steps, mean degree, 10 / 50 / 90 % quantiles (inverted CDF), isolated share."""
    out = []
    for combo in _combos(v2v, keys):
        d = _select(v2v, combo).sort_values("degree")
        k, c = d["degree"].to_numpy(), d["vehicle_steps"].to_numpy(dtype=float)
        cum = np.cumsum(c) / c.sum()
        q = {f"q{int(p * 100)}": int(k[np.searchsorted(cum, p, side="left")]) for p in (0.1, 0.5, 0.9)}
        out.append({**combo, "vehicle_steps": int(c.sum()), "mean_degree": float((k * c).sum() / c.sum()),
                    **q, "isolated_share": float(c[k == 0].sum() / c.sum())})
    return pd.DataFrame(out)


def fig_degree(v2v: pd.DataFrame, keys: list[str], path: Path) -> pd.DataFrame:
    first, other = keys[0], keys[1:]
    stats = degree_stats(v2v, keys)
    fig = _new_fig(11.5, 3.6)
    ax1, ax2 = fig.subplots(1, 2)
    for c, combo in enumerate(_combos(stats, other)):
        s = _select(stats, combo).sort_values(first)
        x = s[first].astype(float).to_numpy()
        lab = _combo_label(combo) or "all runs"
        line, = ax1.plot(x, s["mean_degree"], ls=_LINESTYLES[c % 4], marker=_MARKERS[c % 6], ms=4, lw=1.2,
                         label=f"mean ({lab})")
        ax1.fill_between(x, s["q10"], s["q90"], color=line.get_color(), alpha=0.15, lw=0)
        ax1.plot(x, s["q50"], color=line.get_color(), ls=":", lw=1.0)
        ax2.plot(x, 100.0 * s["isolated_share"], ls=_LINESTYLES[c % 4], marker=_MARKERS[c % 6], ms=4, lw=1.2,
                 color=line.get_color(), label=lab)
    ax1.set_title("V2V degree (band: 10–90 %, dotted: median)", fontsize=9)
    ax1.set_xlabel(first)
    ax1.set_ylabel("neighbours within Rc")
    ax1.set_ylim(bottom=0)
    ax2.set_title("isolated vehicle-steps (no neighbour)", fontsize=9)
    ax2.set_xlabel(first)
    ax2.set_ylabel("% of vehicle-steps")
    ax2.set_ylim(bottom=0)
    ax1.legend(fontsize=7)
    _save(fig, path)
    return stats


def control_difference_table(gain: pd.DataFrame, keys: list[str], method: str = ICP_DA_LC.name) -> tuple[list, list]:
    """TLR minus VSR RMSE gain per zone and value of the other keys (the paper's "TLR platoons help")."""
    ctl = "scenario.control"
    g = gain[gain["method"] == method]
    if ctl not in keys or set(g[ctl].astype(str).unique()) != {"tlr", "vsr"}:
        return [], []
    rest = [k for k in keys if k != ctl]
    t = g[g[ctl] == "tlr"].set_index(rest + ["zone"])["gain_rmse_pos_m"]
    v = g[g[ctl] == "vsr"].set_index(rest + ["zone"])["gain_rmse_pos_m"]
    both = t.index.intersection(v.index)
    diff = pd.DataFrame({"tlr": t.loc[both], "vsr": v.loc[both]}).reset_index()
    header = [_esc(k) for k in rest] + ["zone", "gain TLR [m]", "gain VSR [m]", "TLR − VSR [m]"]
    rows = [[_esc(str(r[k])) for k in rest] + [_esc(str(r["zone"])), _fmt(r["tlr"]), _fmt(r["vsr"]),
                                                 _fmt(r["tlr"] - r["vsr"])] for _, r in diff.iterrows()]
    return header, rows


def table_html(header, rows, left: int) -> str:
    return _table(header, rows, left_cols=left) if rows else ""
