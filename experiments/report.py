"""Run and comparison reports (HTML + PNG figures) computed from run files only.

A run directory holds ``config.toml``, ``estimates.parquet``, ``traffic.parquet``,
``summary.json`` and optionally ``features.parquet`` and ``association.parquet``
(see DESIGN.md).  :func:`write_run_report` turns one such directory into
``report.html`` plus ``figures/*.png``; :func:`write_comparison_report` compares
several runs (e.g. TLR vs VSR, paper Figs. 13-16).

Everything is read back from the files, never from the in-memory state of a
run, so ``coloc report DIR`` rebuilds the same report a run wrote.  Output is
deterministic (fixed styles, sorted methods/areas, PNGs without software/date
metadata) and written atomically (temporary directory next to the target,
then renamed into place).
"""

from __future__ import annotations

import html
import json
import math
import os
import re
import shutil
import tempfile
import tomllib
import warnings
import xml.etree.ElementTree as ET
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.collections import LineCollection  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Polygon as MplPolygon  # noqa: E402

from coloc.methods.registry import METHODS  # noqa: E402

__all__ = [
    "write_run_report",
    "write_comparison_report",
    "method_label",
    "method_color",
    "order_methods",
]

# --------------------------------------------------------------------------- #
# Styles
# --------------------------------------------------------------------------- #

#: method -> (display name, colour), from the method registry.  Green is reserved for feature accuracy.
METHOD_STYLES: dict[str, tuple[str, str]] = {m.name: (m.label, m.color) for m in METHODS.values()}
_METHOD_ORDER = list(METHOD_STYLES)
_EXTRA_COLORS = ["tab:gray", "#17becf", "#9467bd", "#8c564b", "#bcbd22", "#e377c2",
                 "#393b79", "#843c39", "#7b4173", "#637939"]
_FEATURE_COLORS = ["tab:green", "#006d2c", "#74c476", "#31a354", "#a1d99b"]
_RUN_LINESTYLES = ["-", "--", ":", "-."]
_ZONE_FILLS = ["#a6dba0", "#fee08b", "#f4a582", "#92c5de", "#c2a5cf", "#dfc27d", "#bababa"]

#: matplotlib settings applied to every figure (independent of user matplotlibrc).
_RC = {
    "figure.dpi": 100,
    "savefig.dpi": 110,
    "font.size": 9,
    "axes.grid": True,
    "grid.alpha": 0.3,
    "legend.fontsize": 7,
    "legend.framealpha": 0.8,
    "path.simplify": True,
    "svg.hashsalt": "coloc",
}

RMSE_BIN_S = 300.0  # paper Figs. 13-16: 5-minute aggregation
TRACK_BIN_S = 30.0  # Fig. 18: along/cross-track over time
_CDF_GRID = np.linspace(0.0, 1.0, 1001)


def method_label(method: str) -> str:
    """Display name of a method (unknown methods are shown as-is)."""
    return METHOD_STYLES.get(method, (method, ""))[0]


def method_color(method: str) -> str:
    """Fixed colour of a method; unknown methods get a stable colour from their name."""
    if method in METHOD_STYLES:
        return METHOD_STYLES[method][1]
    return _EXTRA_COLORS[zlib.crc32(method.encode("utf-8")) % len(_EXTRA_COLORS)]


def order_methods(methods) -> list[str]:
    """Known methods in DESIGN order first, then unknown ones alphabetically."""
    ms = {str(m) for m in methods}
    known = [m for m in _METHOD_ORDER if m in ms]
    return known + sorted(ms - set(known))


def _natural_key(s: str):
    return [(0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.split(r"(\d+)", str(s)) if p]


def _sorted_labels(values) -> list[str]:
    return sorted({str(v) for v in values}, key=_natural_key)


# --------------------------------------------------------------------------- #
# Loading
# --------------------------------------------------------------------------- #

_EST_COLS = ["method", "t", "err_pos", "err_vel", "err_along", "err_cross", "zone", "area"]


def _read_parquet(path: Path, wanted: list[str]) -> pd.DataFrame | None:
    """Read the wanted columns that exist; None when the file is absent."""
    if not path.exists():
        return None
    import pyarrow.parquet as pq

    names = set(pq.read_schema(path).names)
    cols = [c for c in wanted if c in names]
    cat_cols = [c for c in ("method", "zone", "area", "run") if c in cols]
    # Label columns are read dictionary-encoded (-> pandas categoricals): millions of rows
    # would otherwise become millions of Python strings.
    table = pq.read_table(path, columns=cols, read_dictionary=cat_cols)
    df = table.to_pandas()
    for c in cat_cols:
        if not isinstance(df[c].dtype, pd.CategoricalDtype) or not all(
                isinstance(v, str) for v in df[c].cat.categories):
            df[c] = df[c].astype("string").astype("category")
    return df


@dataclass
class _Run:
    run_dir: Path
    config: dict
    summary: dict
    estimates: pd.DataFrame | None = None
    features: pd.DataFrame | None = None
    traffic: pd.DataFrame | None = None
    association: pd.DataFrame | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return str(self.config.get("run", {}).get("name") or self.run_dir.name)

    @property
    def seed(self):
        s = self.config.get("run", {}).get("seed")
        return self.summary.get("seed", s) if s is None else s

    @property
    def control(self) -> str:
        return str(self.config.get("scenario", {}).get("control", "") or "")

    @property
    def methods(self) -> list[str]:
        ms: set[str] = set(self.summary.get("methods", {}) or {})
        if self.estimates is not None and len(self.estimates):
            ms |= {str(m) for m in self.estimates["method"].unique()}
        return order_methods(ms)


def _load_run(run_dir: Path, *, need_areas: bool = True) -> _Run:
    run_dir = Path(run_dir)
    cfg_path = run_dir / "config.toml"
    config: dict = {}
    if cfg_path.exists():
        with open(cfg_path, "rb") as fh:
            config = tomllib.load(fh)
    summary: dict = {}
    if (run_dir / "summary.json").exists():
        summary = json.loads((run_dir / "summary.json").read_text(encoding="utf-8"))
    cols = _EST_COLS if need_areas else ["method", "t", "err_pos", "err_vel"]
    run = _Run(run_dir=run_dir, config=config, summary=summary)
    run.estimates = _read_parquet(run_dir / "estimates.parquet", cols)
    run.features = _read_parquet(run_dir / "features.parquet", ["method", "t", "err_pos"])
    run.traffic = _read_parquet(
        run_dir / "traffic.parquet",
        ["interval_start_s", "interval_end_s", "mean_vehicles", "exit_flow_vph",
         "mean_queue", "stop_time_s_per_km", "teleports"],
    )
    run.association = _read_parquet(
        run_dir / "association.parquet", ["method", "t", "correct", "wrong", "discarded"]
    )
    if run.estimates is None:
        run.notes.append("estimates.parquet is missing: no accuracy figures.")
    if not run.summary.get("methods") and run.estimates is not None and need_areas:
        run.summary.setdefault("methods", _summary_from_estimates(run.estimates))
        run.notes.append("summary.json has no per-method statistics: computed from estimates.parquet.")
    return run


def _rmse(x: pd.Series) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def _summary_from_estimates(est: pd.DataFrame) -> dict:
    """Fallback statistics in the summary.json schema (only used when summary lacks them)."""
    out: dict = {}
    for m, g in est.groupby("method", observed=True, sort=False):
        e = g["err_pos"].to_numpy(dtype=float)
        e = e[np.isfinite(e)]
        d: dict[str, Any] = {
            "rmse_pos_m": _rmse(e),
            "rmse_vel_mps": _rmse(g["err_vel"]) if "err_vel" in g else float("nan"),
            "p50_pos_m": float(np.quantile(e, 0.5)) if e.size else float("nan"),
            "p95_pos_m": float(np.quantile(e, 0.95)) if e.size else float("nan"),
        }
        for key, col in (("by_area", "area"), ("by_zone", "zone")):
            if col not in g:
                continue
            d[key] = {}
            for lab, gg in g.groupby(col, observed=True):
                ee = gg["err_pos"].to_numpy(dtype=float)
                ee = ee[np.isfinite(ee)]
                if not ee.size or not _valid_label(lab):
                    continue
                d[key][str(lab)] = {"rmse_pos_m": _rmse(ee),
                                    "p95_pos_m": float(np.quantile(ee, 0.95)), "n": int(ee.size)}
        out[str(m)] = d
    return out


def _valid_label(v) -> bool:
    if v is None or (isinstance(v, float) and math.isnan(v)) or v is pd.NA:
        return False
    return str(v).strip().lower() not in ("", "nan", "none", "<na>", "-")


# --------------------------------------------------------------------------- #
# Computations (vectorised)
# --------------------------------------------------------------------------- #


def _choose_bin(t: np.ndarray, preferred: float) -> float:
    """Preferred bin width unless the run is too short to show at least 3 bins."""
    if t.size == 0:
        return preferred
    span = float(np.nanmax(t) - np.nanmin(t))
    if span >= 3 * preferred or span <= 0:
        return preferred
    # Short runs (tests, smoke runs): about 10 bins, rounded to a nice number of seconds.
    for w in (1, 2, 5, 10, 15, 30, 60, 120, 150, 300):
        if span / w <= 12:
            return float(min(w, preferred))
    return preferred


def _binned_rmse(df: pd.DataFrame, cols: list[str], width: float,
                 by: str = "method") -> pd.DataFrame:
    """RMSE of each column in ``cols`` per (by, time bin); index (by, t_mid_s)."""
    t = df["t"].to_numpy(dtype=float)
    tmp = pd.DataFrame({by: df[by], "bin": np.floor(t / width) * width + width / 2.0})
    for c in cols:
        v = df[c].to_numpy(dtype=float)
        tmp[c] = v * v
    g = tmp.groupby([by, "bin"], observed=True, sort=True)[cols].mean()
    return np.sqrt(g)


def _quantile_curves(df: pd.DataFrame, group_col: str) -> dict[tuple[str, str], np.ndarray]:
    """Position error quantiles on a fixed grid per (group, method): deterministic CDF points."""
    out: dict[tuple[str, str], np.ndarray] = {}
    err = df["err_pos"].to_numpy(dtype=float)
    for (lab, m), idx in df.groupby([group_col, "method"], observed=True, sort=False).indices.items():
        if not _valid_label(lab):
            continue
        e = err[idx]
        e = e[np.isfinite(e)]
        if e.size:
            out[(str(lab), str(m))] = np.quantile(e, _CDF_GRID)
    return out


# --------------------------------------------------------------------------- #
# Figures
# --------------------------------------------------------------------------- #


def _save(fig: Figure, path: Path) -> None:
    fig.savefig(path, format="png", metadata={"Software": None})


def _new_fig(w: float, h: float) -> Figure:
    return Figure(figsize=(w, h), layout="constrained")


def _empty_axis(ax, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, color="0.4")
    ax.set_xticks([])
    ax.set_yticks([])


def _fig_rmse_time(runs: list[_Run], path: Path, linestyles: list[str] | None = None) -> str:
    width = min(_choose_bin(r.estimates["t"].to_numpy(dtype=float), RMSE_BIN_S)
                for r in runs if r.estimates is not None)
    fig = _new_fig(8.0, 6.0)
    ax_p, ax_v = fig.subplots(2, 1, sharex=True)
    multi = len(runs) > 1
    for k, run in enumerate(runs):
        ls = (linestyles or _RUN_LINESTYLES)[k % len(_RUN_LINESTYLES)]
        suffix = f" [{_run_label(run, runs)}]" if multi else ""
        est = run.estimates
        if est is None or not len(est):
            continue
        cols = ["err_pos"] + (["err_vel"] if "err_vel" in est.columns else [])
        r = _binned_rmse(est, cols, width)
        for m in order_methods(r.index.get_level_values(0).unique()):
            sub = r.loc[m]
            x = sub.index.to_numpy() / 60.0
            kw = dict(color=method_color(m), ls=ls, marker="o", ms=3, lw=1.4)
            ax_p.plot(x, sub["err_pos"].to_numpy(), label=method_label(m) + suffix, **kw)
            if "err_vel" in sub:
                ax_v.plot(x, sub["err_vel"].to_numpy(), label=method_label(m) + suffix, **kw)
        feats = run.features
        if feats is not None and len(feats):
            rf = _binned_rmse(feats, ["err_pos"], width)
            for j, m in enumerate(order_methods(rf.index.get_level_values(0).unique())):
                sub = rf.loc[m]
                ax_p.plot(sub.index.to_numpy() / 60.0, sub["err_pos"].to_numpy(),
                          color=_FEATURE_COLORS[j % len(_FEATURE_COLORS)], ls=ls, marker="^",
                          ms=3, lw=1.4, label=f"features, {method_label(m)}{suffix}")
    ax_p.set_ylabel("position RMSE [m]")
    ax_v.set_ylabel("velocity RMSE [m/s]")
    ax_v.set_xlabel("time [min]")
    ax_p.set_title(f"(a) position RMSE per {width / 60:g}-min bin")
    ax_v.set_title(f"(b) velocity RMSE per {width / 60:g}-min bin")
    for ax in (ax_p, ax_v):
        ax.set_ylim(bottom=0)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    _save(fig, path)
    return f"{width:g}"


def _fig_cdf(run: _Run, group_col: str, path: Path, title_word: str) -> list[str]:
    est = run.estimates
    curves = _quantile_curves(est, group_col)
    labels = _sorted_labels(k[0] for k in curves)
    if not labels:
        return []
    n = len(labels)
    ncol = min(3, n)
    nrow = math.ceil(n / ncol)
    fig = _new_fig(3.4 * ncol, 2.8 * nrow)
    axes = np.atleast_1d(fig.subplots(nrow, ncol, squeeze=False)).ravel()
    i95 = int(np.searchsorted(_CDF_GRID, 0.95))
    for ax, lab in zip(axes, labels):
        ms = order_methods(m for (lb, m) in curves if lb == lab)
        xmax = 0.0
        for m in ms:
            q = curves[(lab, m)]
            p95 = float(q[i95])
            c = method_color(m)
            ax.plot(q, _CDF_GRID, color=c, lw=1.4, label=f"{method_label(m)} (p95 {p95:.2f} m)")
            ax.plot([p95, p95], [0, 0.95], color=c, ls=":", lw=1.0)
            ax.plot([p95], [0.95], marker="o", ms=4, color=c)
            xmax = max(xmax, float(q[int(np.searchsorted(_CDF_GRID, 0.99))]))
        ax.axhline(0.95, color="0.5", lw=0.7, ls="--")
        ax.set_xlim(0, max(xmax * 1.1, 1e-3))
        ax.set_ylim(0, 1.0)
        ax.set_title(f"{title_word} {lab}")
        ax.set_xlabel("position error [m]")
        ax.set_ylabel("CDF")
        ax.legend(loc="lower right")
    for ax in axes[n:]:
        ax.set_visible(False)
    _save(fig, path)
    return labels


def _fig_track(run: _Run, area: str, path: Path) -> float:
    est = run.estimates
    sub = est[(est["area"] == area).to_numpy(dtype=bool)] if "area" in est.columns else est.iloc[:0]
    width = min(_choose_bin(est["t"].to_numpy(dtype=float), TRACK_BIN_S), TRACK_BIN_S)
    fig = _new_fig(8.0, 5.6)
    ax_a, ax_c = fig.subplots(2, 1, sharex=True)
    if len(sub):
        r = _binned_rmse(sub, ["err_along", "err_cross"], width)
        for m in order_methods(r.index.get_level_values(0).unique()):
            s = r.loc[m]
            x = s.index.to_numpy() / 60.0
            for ax, col in ((ax_a, "err_along"), (ax_c, "err_cross")):
                ax.plot(x, s[col].to_numpy(), color=method_color(m), lw=1.1, label=method_label(m))
        for ax in (ax_a, ax_c):
            ax.set_ylim(bottom=0)
            ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
    else:
        _empty_axis(ax_a, f"no samples in area {area}")
        _empty_axis(ax_c, f"no samples in area {area}")
    ax_a.set_title(f"along-track RMSE, area {area} ({width:g} s bins)")
    ax_c.set_title(f"cross-track RMSE, area {area} ({width:g} s bins)")
    ax_a.set_ylabel("along-track RMSE [m]")
    ax_c.set_ylabel("cross-track RMSE [m]")
    ax_c.set_xlabel("time [min]")
    _save(fig, path)
    return width


_TRAFFIC_PANELS = [
    ("exit_flow_vph", "exit flow [veh/h]", "exit flow"),
    ("mean_vehicles", "vehicles in network", "vehicles in network"),
    ("mean_queue", "mean queue [halting veh]", "mean queue"),
    ("stop_time_s_per_km", "stop time [s/km]", "stop time per km"),
]


def _fig_traffic(runs: list[_Run], path: Path) -> None:
    fig = _new_fig(8.5, 5.6)
    axes = fig.subplots(2, 2, sharex=True).ravel()
    multi = len(runs) > 1
    for k, run in enumerate(runs):
        tr = run.traffic
        if tr is None or not len(tr):
            continue
        tr = tr.sort_values("interval_start_s")
        end = tr["interval_end_s"] if "interval_end_s" in tr else tr["interval_start_s"] + RMSE_BIN_S
        x = ((tr["interval_start_s"] + end) / 2.0 / 60.0).to_numpy(dtype=float)
        color = f"C{k % 10}" if multi else "tab:blue"
        ls = _RUN_LINESTYLES[k % len(_RUN_LINESTYLES)]
        for ax, (col, ylabel, title) in zip(axes, _TRAFFIC_PANELS):
            if col in tr:
                ax.plot(x, tr[col].to_numpy(dtype=float), color=color, ls=ls, marker="o", ms=3,
                        label=_run_label(run, runs))
    for ax, (col, ylabel, title) in zip(axes, _TRAFFIC_PANELS):
        ax.set_title(title)
        ax.set_ylabel(ylabel)
        ax.set_ylim(bottom=0)
    if multi and axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(loc="best")
    axes[2].set_xlabel("time [min]")
    axes[3].set_xlabel("time [min]")
    _save(fig, path)


def _geojson_polys(path: Path):
    """(properties, [exterior rings as Nx2 arrays]) per feature of a GeoJSON FeatureCollection."""
    data = json.loads(path.read_text(encoding="utf-8"))
    feats = data.get("features", []) if data.get("type") == "FeatureCollection" else [data]
    out = []
    for f in feats:
        geom = f.get("geometry") or {}
        gt, coords = geom.get("type"), geom.get("coordinates") or []
        polys = [coords] if gt == "Polygon" else coords if gt == "MultiPolygon" else []
        rings = [np.asarray(p[0], dtype=float)[:, :2] for p in polys if p and len(p[0]) >= 3]
        if rings:
            out.append((f.get("properties") or {}, rings))
    return out


def _label_point(rings: list[np.ndarray]) -> tuple[float, float]:
    try:
        from shapely.geometry import Polygon

        big = max(rings, key=lambda r: Polygon(r).area)
        p = Polygon(big).representative_point()
        return float(p.x), float(p.y)
    except Exception:  # pragma: no cover - shapely is a dependency, this is a fallback
        r = rings[0]
        return float(r[:, 0].mean()), float(r[:, 1].mean())


def _resolve_net_files(run: _Run) -> dict[str, Path] | None:
    scen = run.config.get("scenario", {}) or {}
    net_dir = scen.get("net_dir")
    if not net_dir:
        return None
    net_dir = Path(net_dir)
    if not net_dir.is_absolute():
        net_dir = (run.run_dir / net_dir).resolve()
    if not net_dir.is_dir():
        run.notes.append(f"map skipped: net_dir {net_dir} does not exist.")
        return None
    files: dict = {}
    if (net_dir / "scenario.toml").exists():
        with open(net_dir / "scenario.toml", "rb") as fh:
            files = (tomllib.load(fh).get("files") or {})
    defaults = {"zones": "zones.geojson", "areas": "areas.geojson", "features": "features.add.xml"}
    out: dict[str, Path] = {}
    for key, default in defaults.items():
        p = net_dir / str(files.get(key, default))
        if p.exists():
            out[key] = p
    net_candidates = []
    if files.get("net"):
        net_candidates.append(net_dir / str(files["net"]))
    if run.control:
        net_candidates.append(net_dir / f"{run.control}.net.xml")
    net_candidates += sorted(net_dir.glob("*.net.xml")) + sorted(net_dir.glob("*.net.xml.gz"))
    for p in net_candidates:
        if p.exists():
            out["net"] = p
            break
    return out


def _fig_map(run: _Run, files: dict[str, Path], path: Path) -> dict[str, int]:
    counts = {"lanes": 0, "zones": 0, "areas": 0, "features": 0}
    fig = _new_fig(9.0, 7.0)
    ax = fig.subplots()
    if "zones" in files:
        polys = sorted(_geojson_polys(files["zones"]), key=lambda p: _natural_key(str(p[0].get("zone", ""))))
        zone_names = _sorted_labels(p[0].get("zone", "?") for p in polys)
        for props, rings in polys:
            z = str(props.get("zone", "?"))
            color = _ZONE_FILLS[zone_names.index(z) % len(_ZONE_FILLS)]
            for r in rings:
                ax.add_patch(MplPolygon(r, closed=True, facecolor=color, edgecolor=color,
                                        alpha=0.35, lw=0.8, zorder=1))
            sp = props.get("sigma_p", props.get("sp"))
            lab = f"zone {z}" + (f"\nσp = {float(sp):g} m" if sp is not None else "")
            x, y = _label_point(rings)
            ax.text(x, y, lab, ha="center", va="center", fontsize=8, zorder=5,
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec=color, alpha=0.8))
            counts["zones"] += 1
    if "net" in files:
        import sumolib

        net = sumolib.net.readNet(str(files["net"]), withConnections=False, withFoes=False,
                                  withInternal=False)
        segs = []
        for edge in sorted(net.getEdges(withInternal=False), key=lambda e: e.getID()):
            if edge.getID().startswith(":") or edge.getFunction() == "internal":
                continue
            for lane in edge.getLanes():
                shp = np.asarray(lane.getShape(), dtype=float)[:, :2]
                if len(shp) >= 2:
                    segs.append(shp)
        ax.add_collection(LineCollection(segs, colors="0.45", linewidths=0.5, zorder=2))
        counts["lanes"] = len(segs)
    if "areas" in files:
        for props, rings in sorted(_geojson_polys(files["areas"]),
                                   key=lambda p: _natural_key(str(p[0].get("area", "")))):
            a = str(props.get("area", "?"))
            for r in rings:
                ax.add_patch(MplPolygon(r, closed=True, fill=False, edgecolor="black", ls="--",
                                        lw=1.1, zorder=3))
            x, y = _label_point(rings)
            ax.text(x, y, a, ha="center", va="center", fontsize=11, fontweight="bold", zorder=6,
                    color="black", bbox=dict(boxstyle="circle,pad=0.2", fc="white", ec="black"))
            counts["areas"] += 1
    if "features" in files:
        xs, ys = [], []
        for poi in ET.parse(files["features"]).getroot().iter("poi"):
            if poi.get("x") is not None and poi.get("y") is not None:
                xs.append(float(poi.get("x")))
                ys.append(float(poi.get("y")))
        if xs:
            ax.scatter(xs, ys, marker="^", s=22, c="red", edgecolors="darkred", linewidths=0.4,
                       zorder=7, label=f"features ({len(xs)})")
            ax.legend(loc="upper right")
        counts["features"] = len(xs)
    ax.autoscale_view()
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m] (SUMO net coordinates)")
    ax.set_ylabel("y [m]")
    ax.set_title("net lanes, GNSS zones, analysis areas and features")
    _save(fig, path)
    return counts


# --------------------------------------------------------------------------- #
# HTML helpers
# --------------------------------------------------------------------------- #

_CSS = """
body{font-family:Helvetica,Arial,sans-serif;margin:2em auto;max-width:1100px;color:#222;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.25em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.6em 0;font-size:.9em}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f2f2f2}td.l,th.l{text-align:left}
dl.meta{display:grid;grid-template-columns:max-content auto;gap:.1em 1em}dl.meta dt{font-weight:bold}dl.meta dd{margin:0;font-family:monospace}
figure{margin:1em 0 2em 0}figure img{max-width:100%;border:1px solid #ddd}
figcaption{font-size:.9em;color:#444;margin-top:.4em}
.note{background:#fff8e1;border-left:4px solid #f0b400;padding:.4em .8em;margin:.5em 0}
.swatch{display:inline-block;width:.8em;height:.8em;margin-right:.4em;vertical-align:middle;border:1px solid #888}
"""


def _esc(x) -> str:
    return html.escape(str(x), quote=True)


def _fmt(x, digits: int = 3) -> str:
    if x is None:
        return "–"
    if isinstance(x, bool):
        return str(x)
    if isinstance(x, (int, np.integer)):
        return str(int(x))
    try:
        v = float(x)
    except (TypeError, ValueError):
        return _esc(x)
    if not math.isfinite(v):
        return "–"
    return f"{v:.{digits}f}"


def _table(header: list[str], rows: list[list[str]], left_cols: int = 1) -> str:
    """HTML table; cells are already-escaped strings."""
    th = "".join(f'<th class="l">{h}</th>' if i < left_cols else f"<th>{h}</th>"
                 for i, h in enumerate(header))
    body = []
    for row in rows:
        body.append("<tr>" + "".join(f'<td class="l">{c}</td>' if i < left_cols else f"<td>{c}</td>"
                                     for i, c in enumerate(row)) + "</tr>")
    return f"<table><thead><tr>{th}</tr></thead><tbody>{''.join(body)}</tbody></table>"


def _method_cell(m: str) -> str:
    return (f'<span class="swatch" style="background:{_esc(_css_color(method_color(m)))}"></span>'
            f"{_esc(method_label(m))} <small>({_esc(m)})</small>")


def _css_color(c: str) -> str:
    from matplotlib.colors import to_hex

    return to_hex(c)


def _figure_html(fname: str, title: str, caption: str, prefix: str = "figures/") -> str:
    return (f'<figure id="{_esc(Path(fname).stem)}"><img src="{_esc(prefix + fname)}" alt="{_esc(title)}">'
            f"<figcaption><b>{_esc(title)}.</b> {caption}</figcaption></figure>")


def _page(title: str, body: str) -> str:
    return (
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
        f"<title>{_esc(title)}</title><style>{_CSS}</style></head>\n<body>\n"
        f"<h1>{_esc(title)}</h1>\n{body}\n</body></html>\n"
    )


def _method_stats_rows(methods: list[str], summary: dict) -> list[list[str]]:
    rows = []
    for m in methods:
        s = (summary.get("methods") or {}).get(m, {}) or {}
        rows.append([_method_cell(m), _fmt(s.get("rmse_pos_m")), _fmt(s.get("rmse_vel_mps")),
                     _fmt(s.get("p50_pos_m")), _fmt(s.get("p95_pos_m")), _fmt(s.get("seconds"), 2)])
    return rows


def _by_table(methods: list[str], summary: dict, key: str, word: str) -> str:
    labels = _sorted_labels(
        lab for m in methods for lab in (((summary.get("methods") or {}).get(m) or {}).get(key) or {})
    )
    if not labels:
        return f"<p>No per-{word} statistics in summary.json.</p>"
    header = ["method"] + [f"{word} {_esc(a)}<br><small>p95 [m] / RMSE [m] / n</small>" for a in labels]
    rows = []
    for m in methods:
        d = ((summary.get("methods") or {}).get(m) or {}).get(key) or {}
        row = [_method_cell(m)]
        for a in labels:
            s = d.get(a)
            row.append("–" if not s else
                       f"{_fmt(s.get('p95_pos_m'))} / {_fmt(s.get('rmse_pos_m'))} / {_fmt(s.get('n'))}")
        rows.append(row)
    return _table(header, rows)


def _association_table(run: _Run) -> str | None:
    assoc = run.summary.get("association") or {}
    rows_src: dict[str, dict] = {}
    if assoc:
        rows_src = {str(m): v for m, v in assoc.items() if isinstance(v, dict)}
    elif run.association is not None and len(run.association):
        cols = [c for c in ("correct", "wrong", "discarded") if c in run.association]
        agg = run.association.groupby("method", observed=True)[cols].sum()
        rows_src = {str(m): {c: int(agg.loc[m, c]) for c in cols} for m in agg.index}
    if not rows_src:
        return None
    rows = []
    for m in order_methods(rows_src):
        v = rows_src[m]
        tot = sum(float(v.get(c) or 0) for c in ("correct", "wrong", "discarded"))
        frac = _fmt(float(v.get("correct") or 0) / tot) if tot > 0 else "–"
        rows.append([_method_cell(m), _fmt(v.get("correct")), _fmt(v.get("wrong")),
                     _fmt(v.get("discarded")), frac])
    return _table(["method", "correct", "wrong", "discarded", "fraction correct"], rows)


def _run_label(run: _Run, runs: list[_Run]) -> str:
    base = run.name
    if run.control and run.control.lower() not in base.lower():
        base = f"{base} ({run.control.upper()})"
    names = [r.name for r in runs]
    if names.count(run.name) > 1:
        base = f"{base} – {run.run_dir.name}"
    return base


# --------------------------------------------------------------------------- #
# Atomic output
# --------------------------------------------------------------------------- #


def _atomic_publish(target_dir: Path, build: Callable[[Path], None]) -> Path:
    """Build report.html + figures/ in a temp dir next to the target, then move into place.

    ``report.html`` is replaced last with :func:`os.replace`, so readers see either the old
    or the new complete page, never a half-written one.
    """
    target_dir.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".report-tmp-", dir=target_dir))
    old = None
    try:
        (tmp / "figures").mkdir()
        build(tmp)
        figs = target_dir / "figures"
        if figs.exists():
            old = Path(tempfile.mkdtemp(prefix=".report-old-", dir=target_dir))
            os.replace(figs, old / "figures")
        os.replace(tmp / "figures", figs)
        os.replace(tmp / "report.html", target_dir / "report.html")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    return target_dir / "report.html"


# --------------------------------------------------------------------------- #
# Run report
# --------------------------------------------------------------------------- #


def write_run_report(run_dir: Path) -> Path:
    """Write ``run_dir/figures/*.png`` and ``run_dir/report.html`` from the run's files."""
    run_dir = Path(run_dir)
    run = _load_run(run_dir)

    def build(tmp: Path) -> None:
        figdir = tmp / "figures"
        figs: list[str] = []
        with matplotlib.rc_context(_RC):
            figs = _run_figures(run, figdir)
        (tmp / "report.html").write_text(_run_html(run, figs), encoding="utf-8")

    return _atomic_publish(run_dir, build)


def _run_figures(run: _Run, figdir: Path) -> list[str]:
    """Draw the figures; returns HTML <figure> blocks in display order."""
    blocks: list[str] = []
    est = run.estimates
    has_est = est is not None and len(est) > 0

    tr = run.traffic
    if tr is not None and len(tr):
        _fig_traffic([run], figdir / "traffic.png")
        blocks.append(_figure_html(
            "traffic.png", "Traffic over time (paper Figs. 13-15)",
            "From <code>traffic.parquet</code>, one point per aggregation interval (5 min) at its "
            "midpoint: exit flow (vehicles leaving the network per hour), mean number of vehicles "
            "in the network, mean queue (mean number of halting vehicles) and stop time per km "
            "travelled. How to read: higher queue and stop time mean more platooning at junctions "
            "(denser V2V cooperation) but longer exposure to poor-GNSS zones."))

    files = None
    try:
        files = _resolve_net_files(run)
    except Exception as exc:  # malformed scenario.toml: report it, keep the rest of the report
        run.notes.append(f"map skipped: {exc!r}")
    if files:
        try:
            counts = _fig_map(run, files, figdir / "map.png")
            blocks.append(_figure_html(
                "map.png", "Scenario map (paper Figs. 12 and 17a)",
                "Net lanes (thin grey lines, internal junction lanes omitted), GNSS zones as "
                "translucent fills labelled with zone name and position accuracy σp, analysis areas "
                "as dashed outlines labelled with their number (the CDFs below are per area), and "
                f"static features as red triangles. {counts['lanes']} lanes, {counts['zones']} "
                f"zone polygons, {counts['areas']} areas, {counts['features']} features. "
                "Coordinates are SUMO net metres, equal aspect."))
        except Exception as exc:
            run.notes.append(f"map skipped: {exc!r}")
            warnings.warn(f"coloc report: map skipped for {run.run_dir}: {exc!r}", stacklevel=2)
            (figdir / "map.png").unlink(missing_ok=True)

    if has_est:
        width = _fig_rmse_time([run], figdir / "rmse_time.png")
        feat = run.features is not None and len(run.features) > 0
        blocks.append(_figure_html(
            "rmse_time.png", "Accuracy over time (paper Fig. 16)",
            f"Root-mean-square error over all vehicles and all time steps inside each {width} s bin, "
            "plotted at the bin midpoint: (a) vehicle position RMSE, (b) velocity RMSE, one line per "
            "method" + (" ; green lines with triangles are the RMSE of the feature position estimates "
                        "of each cooperative method (from <code>features.parquet</code>)" if feat else "")
            + ". How to read: lower is better; the gap between GNSS and a cooperative method is the "
            "cooperative gain at that time of the traffic evolution."))

        if "area" in est.columns:
            areas = _fig_cdf(run, "area", figdir / "cdf_area.png", "area")
            if areas:
                blocks.append(_figure_html(
                    "cdf_area.png", "Position error CDF per analysis area (paper Fig. 17b)",
                    "Empirical CDF of the Euclidean position error of all (vehicle, time) samples "
                    "whose true position lies in the area, one subplot per area and one line per "
                    "method (drawn from 1001 exact quantiles). The dot and dotted line mark the 95th "
                    "percentile, also given in the legend. How to read: a curve further left is "
                    "better; compare p95 between methods within one area."))
        if "zone" in est.columns:
            zones = _fig_cdf(run, "zone", figdir / "cdf_zone.png", "zone")
            if zones:
                blocks.append(_figure_html(
                    "cdf_zone.png", "Position error CDF per GNSS zone",
                    "Same as the per-area CDF, but grouping samples by the GNSS zone of the vehicle's "
                    "true position (zones differ in GNSS σp and σv). The dot marks the 95th "
                    "percentile. How to read: GNSS degrades from open-sky to built-up zones; a "
                    "cooperative method should flatten that difference."))
        area = str((run.config.get("report") or {}).get("track_area", "5"))
        if {"err_along", "err_cross", "area"} <= set(est.columns) and area in set(est["area"].astype(str)):
            w = _fig_track(run, area, figdir / "track_errors.png")
            blocks.append(_figure_html(
                "track_errors.png", f"Along-track and cross-track accuracy in area {area} (paper Fig. 18)",
                f"RMSE of the signed position error component along the true heading (top) and across "
                f"it (bottom), over all vehicles in area {_esc(area)} within each {w:g} s bin, one line "
                "per method. How to read: periodic GNSS error follows the traffic-light cycle (vehicles "
                "averaging while stopped); cross-track below about 1 m is what lane-level services need."))
    return blocks


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
                 "95th percentile (p95) of the position error over all vehicles and time steps, and "
                 "the estimator's wall-clock time.</p>")
    parts.append(_table(["method", "RMSE pos [m]", "RMSE vel [m/s]", "p50 pos [m]", "p95 pos [m]",
                         "time [s]"], _method_stats_rows(methods, s)))
    parts.append("<h3>Per analysis area</h3>" + _by_table(methods, s, "by_area", "area"))
    parts.append("<h3>Per GNSS zone</h3>" + _by_table(methods, s, "by_zone", "zone"))
    cov = s.get("within_rsu_coverage")
    if cov:
        parts.append(_coverage_html(methods, cov))

    traffic = s.get("traffic") or {}
    parts.append("<h2>Traffic summary</h2>")
    if traffic:
        lab = {"mean_vehicles": "mean vehicles in network", "exit_flow_vph": "exit flow [veh/h]",
               "mean_queue": "mean queue [halting veh]", "stop_time_s_per_km": "stop time [s/km]"}
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


# --------------------------------------------------------------------------- #
# Comparison report
# --------------------------------------------------------------------------- #


def write_comparison_report(run_dirs: list[Path], out_dir: Path, *,
                            build_missing: bool = True) -> Path:
    """Compare runs side by side (e.g. TLR vs VSR); writes ``out_dir/report.html`` and figures.

    Runs keep the order given (the first is drawn with continuous lines, the second
    dashed, ...).  When ``build_missing`` is true, a run without ``report.html`` gets one
    so the links work.
    """
    run_dirs = [Path(d) for d in run_dirs]
    out_dir = Path(out_dir)
    if not run_dirs:
        raise ValueError("write_comparison_report needs at least one run directory")
    if build_missing:
        for d in run_dirs:
            if not (d / "report.html").exists():
                write_run_report(d)
    runs = [_load_run(d, need_areas=False) for d in run_dirs]
    for r in runs:  # per-area tables come from summary.json; compute only if it lacks them
        if not r.summary.get("methods"):
            est = _read_parquet(r.run_dir / "estimates.parquet", _EST_COLS)
            if est is not None:
                r.summary["methods"] = _summary_from_estimates(est)

    def build(tmp: Path) -> None:
        figdir = tmp / "figures"
        blocks: list[str] = []
        with matplotlib.rc_context(_RC):
            if any(r.traffic is not None and len(r.traffic) for r in runs):
                _fig_traffic(runs, figdir / "compare_traffic.png")
                blocks.append(_figure_html(
                    "compare_traffic.png", "Traffic over time per run (paper Figs. 13-15)",
                    "One line per run (colour and line style per run, see legend), one point per "
                    "5-minute interval: exit flow, mean vehicles in the network, mean queue (halting "
                    "vehicles) and stop time per km. How to read: with similar exit flow, a run with "
                    "more vehicles and queues inside the network (e.g. traffic lights) offers denser "
                    "cooperation."))
            if any(r.estimates is not None and len(r.estimates) for r in runs):
                width = _fig_rmse_time(runs, figdir / "compare_rmse_time.png")
                styles = ", ".join(f"{_esc(_run_label(r, runs))}: {_ls_name(k)}"
                                   for k, r in enumerate(runs))
                blocks.append(_figure_html(
                    "compare_rmse_time.png", "Accuracy over time per run (paper Fig. 16)",
                    f"Position (a) and velocity (b) RMSE over vehicles per {width} s bin; colour is the "
                    f"method, line style the run ({styles}); green lines with triangles are feature "
                    "RMSE of cooperative methods. How to read: compare the same colour across line "
                    "styles to see how traffic control changes each method's accuracy."))
        (tmp / "report.html").write_text(_comparison_html(runs, out_dir, blocks), encoding="utf-8")

    return _atomic_publish(out_dir, build)


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
    parts.append(_table(["run", "method", "RMSE pos [m]", "RMSE vel [m/s]", "p50 pos [m]", "p95 pos [m]",
                         "time [s]"], rows, left_cols=2))

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
