"""The sweep report: ``DIR/report.html`` + ``DIR/figures/*.png`` from sweep.toml, curves.parquet, sweep.parquet.

One generic renderer draws every figure of Brambilla Sec. V from the swept keys:
one panel per value of the *first* grid key, one line per method x values of
the other grid keys. Keys a method does not depend on (its curves are equal
for all their values, e.g. GNSS under different eta_TH) are dropped from that
method's lines, so each reference curve is drawn once per panel.

* ``rmse_time.png``: vehicle position RMSE versus time, and feature position
  RMSE versus time where methods estimate features (Fig. 7, one panel per df);
* ``rmse_distance.png``: vehicle position RMSE versus the distance of the true
  position to the junction centre (Figs. 8 and 10, one panel per Nf or vf);
* ``association.png``: correct / wrong / discarded percentages of all V2F
  measurements versus the first grid key (Figs. 9 and 11).

Every caption states the number of Monte Carlo runs behind each point.
Deterministic output (sorted inputs, PNGs without metadata), written atomically.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from couplers.errors import InputError  # noqa: E402
from experiments.report.figures import _new_fig, _save  # noqa: E402
from experiments.report.html import _esc, _figure_html, _fmt, _method_cell, _page, _table  # noqa: E402
from experiments.report.output import _atomic_publish  # noqa: E402
from experiments.report.styles import _RC, method_color, method_label, order_methods  # noqa: E402

__all__ = ["write_sweep_report"]

_LINESTYLES = ["-", "--", ":", "-."]
_MARKERS = ["o", "s", "^", "D", "v", "P", "X"]
_ASSOC_COLORS = {"correct": "tab:blue", "wrong": "tab:red", "discarded": "tab:orange"}


def _key_label(key: str) -> str:
    """Paper notation for the usual swept keys, the dotted key otherwise."""
    names = {
        "single_road.feature_spacing_m": "df [m]",
        "crossroad.n_features": "Nf",
        "crossroad.feature_speed_mps": "vf [m/s]",
        "lc.eta_threshold": "ηTH",
    }
    return names.get(key, key)


def _value_label(v) -> str:
    if isinstance(v, (float, np.floating)):
        return f"{float(v):g}"
    return str(v)


def _runs_text(df: pd.DataFrame) -> str:
    n = sorted(set(int(v) for v in df["n_runs"]))
    if not n:
        return "no runs"
    if len(n) == 1:
        return f"{n[0]} Monte Carlo run{'s' if n[0] != 1 else ''} per setting"
    return f"{n[0]}–{n[-1]} Monte Carlo runs per setting"


def _independent_keys(df: pd.DataFrame, keys: list[str], ycols: list[str]) -> list[str]:
    """Keys whose values leave this method's curves exactly unchanged (e.g. GNSS under eta_TH)."""
    drop = []
    for k in keys:
        if df[k].nunique() < 2:
            continue
        rest = [c for c in keys if c != k] + ["x"]
        if all(int(df.groupby(rest, dropna=False)[y].nunique(dropna=False).max()) == 1 for y in ycols):
            drop.append(k)
    return drop


def _lines(df: pd.DataFrame, other: list[str], ycols: list[str]) -> list[tuple[str, dict, pd.DataFrame]]:
    """(method, {key: value} of the line, rows) for every line to draw, deterministic order."""
    out = []
    for m in order_methods(df["method"].astype(str).unique()):
        dm = df[df["method"].astype(str) == m]
        drop = _independent_keys(dm, other, ycols) if other else []
        if drop:
            first = {k: dm[k].iloc[0] for k in drop}
            dm = dm[np.logical_and.reduce([dm[k] == v for k, v in first.items()])]
        keep = [k for k in other if k not in drop]
        if keep:
            for vals, g in dm.groupby(keep, sort=True):
                vals = vals if isinstance(vals, tuple) else (vals,)
                out.append((m, dict(zip(keep, vals)), g))
        else:
            out.append((m, {}, dm))
    return out


def _style_index(combo: dict, other: list[str], values: dict[str, list]) -> int:
    """Line style / marker index of a combination of other-key values (stable across panels)."""
    idx = 0
    for k in other:
        if k in combo:
            idx = idx * len(values[k]) + values[k].index(combo[k])
    return idx


def _line_label(m: str, combo: dict) -> str:
    extra = ", ".join(f"{_key_label(k)} = {_value_label(v)}" for k, v in combo.items())
    return method_label(m) + (f" ({extra})" if extra else "")


def _panel_values(df: pd.DataFrame, first: str | None) -> list:
    return [None] if first is None else sorted(df[first].dropna().unique().tolist())


def _fig_panels(curves: pd.DataFrame, rows: list[tuple[str, str, str]], keys: list[str], xlabel: str,
                path: Path) -> int:
    """Rows of panels (one row per (curve, y column, title)), one column per value of the first key."""
    first, other = (keys[0], keys[1:]) if keys else (None, [])
    values = {k: sorted(curves[k].dropna().unique().tolist()) for k in keys}
    rows = [r for r in rows if len(curves[curves["curve"] == r[0]])]
    panels = _panel_values(curves[curves["curve"].isin([r[0] for r in rows])], first)
    ncol = len(panels)
    fig = _new_fig(min(4.2 * ncol, 17.0) + 2.6, 3.3 * len(rows))
    axes = np.atleast_2d(fig.subplots(len(rows), ncol, squeeze=False))
    n_lines = 0
    for i, (curve, ycol, title) in enumerate(rows):
        d = curves[curves["curve"] == curve]
        for j, pv in enumerate(panels):
            ax = axes[i, j]
            dp = d if first is None else d[d[first] == pv]
            for m, combo, g in _lines(dp, other, [ycol]):
                g = g.sort_values("x")
                k = _style_index(combo, other, values)
                ax.plot(g["x"].to_numpy(dtype=float), g[ycol].to_numpy(dtype=float), color=method_color(m),
                        ls=_LINESTYLES[k % len(_LINESTYLES)], marker=_MARKERS[k % len(_MARKERS)], ms=3.5,
                        lw=1.2, label=_line_label(m, combo))
                n_lines += 1
            head = title if first is None else f"{title}, {_key_label(first)} = {_value_label(pv)}"
            ax.set_title(head)
            ax.set_xlabel(xlabel)
            ax.set_ylabel("RMSE [m]")
            ax.set_ylim(bottom=0)
        handles, labels = axes[i, -1].get_legend_handles_labels()
        if handles:
            axes[i, -1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    _save(fig, path)
    return n_lines


def _fig_association(curves: pd.DataFrame, keys: list[str], path: Path) -> None:
    d = curves[curves["curve"] == "association"]
    first, other = (keys[0], keys[1:]) if keys else (None, [])
    values = {k: sorted(curves[k].dropna().unique().tolist()) for k in keys}
    fig = _new_fig(13.5, 3.6)
    axes = fig.subplots(1, 3)
    xs = values[first] if first else [None]
    numeric = first is not None and all(isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)
                                        for v in xs)
    ycols = ["correct_pct", "wrong_pct", "discarded_pct"]
    for m, combo, g in _lines(d, other, ycols):
        if first is None:
            x = np.zeros(len(g))
        elif numeric:
            x = g[first].to_numpy(dtype=float)
        else:
            x = np.array([xs.index(v) for v in g[first]], dtype=float)
        order = np.argsort(x, kind="stable")
        k = _style_index(combo, other, values)
        for ax, col in zip(axes, ycols):
            ax.plot(x[order], g[col].to_numpy(dtype=float)[order], color=method_color(m),
                    ls=_LINESTYLES[k % len(_LINESTYLES)], marker=_MARKERS[k % len(_MARKERS)], ms=4, lw=1.2,
                    label=_line_label(m, combo))
    titles = {"correct_pct": "correctly associated", "wrong_pct": "wrongly associated",
              "discarded_pct": "discarded (not associated)"}
    for ax, col in zip(axes, ycols):
        ax.set_title(titles[col])
        ax.set_ylabel("% of V2F measurements")
        # Own scale per panel: correct is often near 100 %, wrong / discarded a few percent.
        lo, hi = ax.get_ylim()
        if col == "correct_pct":
            ax.set_ylim(max(0.0, min(lo, 99.0)), 100.5)
        else:
            ax.set_ylim(0.0, max(1.0, hi))
        ax.set_xlabel(_key_label(first) if first else "")
        if first is not None and not numeric:
            ax.set_xticks(range(len(xs)), [_value_label(v) for v in xs])
        elif first is None:
            ax.set_xticks([])
    if axes[-1].get_legend_handles_labels()[0]:
        axes[-1].legend(loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0.0)
    _save(fig, path)


def _summary_rows(curves: pd.DataFrame, keys: list[str]) -> tuple[list[str], list[list[str]]]:
    ov = curves[curves["curve"] == "overall"]
    fo = curves[curves["curve"] == "feature_overall"]
    asc = curves[curves["curve"] == "association"]

    def pick(df, sel, col):
        r = df
        for k, v in sel.items():
            r = r[r[k] == v]
        return r[col].iloc[0] if len(r) else None

    header = [_esc(_key_label(k)) for k in keys] + ["method", "runs", "RMSE pos [m]", "RMSE vel [m/s]",
                                                    "feature RMSE [m]", "correct [%]", "wrong [%]", "discarded [%]"]
    rows = []
    settings = ov[keys].drop_duplicates().to_dict("records") if keys else [{}]
    for sel in settings:
        sub = ov
        for k, v in sel.items():
            sub = sub[sub[k] == v]
        for m in order_methods(sub["method"].astype(str).unique()):
            s = {**sel, "method": m}
            rows.append([_esc(_value_label(sel[k])) for k in keys] + [
                _method_cell(m), _fmt(pick(ov, s, "n_runs")), _fmt(pick(ov, s, "rmse_pos_m")),
                _fmt(pick(ov, s, "rmse_vel_mps")), _fmt(pick(fo, s, "rmse_pos_m")),
                _fmt(pick(asc, s, "correct_pct"), 1), _fmt(pick(asc, s, "wrong_pct"), 1),
                _fmt(pick(asc, s, "discarded_pct"), 1)])
    return header, rows


def _read_checked(path: Path, required) -> pd.DataFrame:
    """A sweep output table; one with other columns (another tool's, an edited one) is an InputError
    naming the file and the missing columns."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from experiments.report.load import require_columns

    try:
        require_columns(path, pq.read_schema(path).names, required)
        return pd.read_parquet(path)
    except (pa.ArrowException, OSError) as exc:
        raise InputError(path, None, f"not a readable Parquet file ({str(exc).splitlines()[0]})") from None


def _read_optional(path: Path, required=()) -> pd.DataFrame | None:
    if not path.exists():
        return None
    df = _read_checked(path, required)
    for c in ("method", "zone", "factor", "level"):
        if c in df.columns:
            df[c] = df[c].astype(str)
    return df


def _study_blocks(curves, zones, v2v, spec, grid_keys, figdir, runs_text, seed_text, what) -> list[str]:
    """Figures of a one-factor-at-a-time sweep (experiments.sweep.study_report)."""
    from experiments.sweep.study_report import fig_factor_association, fig_factor_gap, fig_factors

    blocks = []
    lines = "one line per method" + (" and value of " + ", ".join(_esc(_key_label(k)) for k in grid_keys)
                                     if grid_keys else "")
    axis = ("each row one factor, its levels on the x axis in the sweep file's order; the preset's level "
            "(or 'preset', first, where no level is the preset's) is the same runs on every row")
    if zones is not None:
        for ycol, name, title, word in (("rmse_pos_m", "factors_rmse_zone.png", "Position RMSE by zone, one factor at a time",
                                         "root mean square"),
                                        ("p95_pos_m", "factors_p95_zone.png", "95th percentile of the position error by zone, one factor at a time",
                                         "95th percentile (exact to 1 cm)")):
            fig_factors(zones, spec, grid_keys, ycol, "RMSE [m]" if ycol == "rmse_pos_m" else "p95 [m]", figdir / name)
            blocks.append(_figure_html(
                name, title,
                f"The {word} of the vehicle position error over all vehicle-steps of a setting's runs ({runs_text}, "
                f"{_esc(seed_text)}), per GNSS zone of the vehicle (columns; the last pools the zones); {axis}; "
                f"{lines}. How to read: a factor's effect is the slope of its row; the gap between ICP-DA-LC and "
                "the known-association bound is what unknown association costs under that factor.", what=what))
        if fig_factor_gap(zones, spec, grid_keys, figdir / "factors_gap.png"):
            blocks.append(_figure_html(
                "factors_gap.png", "ICP-DA-LC minus the known-association bound, by zone",
                f"RMSE of ICP-DA-LC minus the RMSE of ICP with known association on the same runs, per zone; "
                f"{axis}. How to read: zero means the data association costs nothing; the idealised arterial "
                "has a gap of zero.", what=what))
    asc = curves[curves["curve"] == "association"]
    if len(asc) and asc["correct_pct"].notna().any():
        fig_factor_association(curves, spec, grid_keys, figdir / "factors_association.png")
        blocks.append(_figure_html(
            "factors_association.png", "Association of V2F rows, one factor at a time",
            f"Correct, wrong and discarded shares of all V2F rows of a setting's runs (a clutter row counts as "
            f"discarded when left out and as wrong when paired with any track); {axis}; {lines}.", what=what))
    return blocks


def _zone_blocks(zones, v2v, keys, figdir, runs_text, seed_text, what) -> list[str]:
    """Gain over GNSS by zone and the V2V degree against the first swept key (the penetration study)."""
    from experiments.sweep.study_report import control_difference_table, fig_degree, fig_gain, table_html

    blocks = []
    first = keys[0]
    numeric = pd.api.types.is_numeric_dtype(zones[first])
    if not numeric:
        return blocks
    gain = fig_gain(zones, keys, figdir / "gain_zone.png")
    if len(gain):
        blocks.append(_figure_html(
            "gain_zone.png", f"Gain over GNSS by zone against {_esc(_key_label(first))}",
            f"GNSS minus method, for the RMSE (top) and the 95th percentile (bottom, exact to 1 cm) of the "
            f"position error over all vehicle-steps of a setting's runs ({runs_text}, {_esc(seed_text)}), per "
            f"GNSS zone of the vehicle (the last column pools them); one line per method and value of "
            + ", ".join(_esc(_key_label(k)) for k in keys[1:]) + ". How to read: above zero the method beats GNSS.",
            what=what))
        header, rows = control_difference_table(gain, keys)
        if rows:
            blocks.append("<h3>TLR against VSR: RMSE gain of ICP-DA-LC over GNSS</h3>"
                          "<p>Gain = GNSS RMSE minus ICP-DA-LC RMSE of the same runs; a positive difference "
                          "means the traffic-light platoons help (Brambilla et al., Sec. VII).</p>"
                          + table_html(header, rows, len(header) - 3))
    if v2v is not None and len(v2v) and first in v2v.columns:
        fig_degree(v2v, keys, figdir / "v2v_degree.png")
        blocks.append(_figure_html(
            "v2v_degree.png", f"V2V degree against {_esc(_key_label(first))}",
            "Neighbours within Rc of a vehicle at a step (the intended V2V graph of the equipped vehicles, "
            "before packet loss), pooled over the vehicle-steps of a setting's runs: mean (solid), median "
            "(dotted), 10-90 % band; right: share of vehicle-steps with no neighbour. One line per value of "
            + (", ".join(_esc(_key_label(k)) for k in keys[1:]) or "the setting") + ".", what=what))
    return blocks


def _effects_parts(effects: pd.DataFrame, grid_keys: list[str], has_figure: bool, what: str) -> list[str]:
    """The section of a sweep with ``design = "full" | "fractional"``: its effects table (effects.parquet,
    :func:`experiments.sweep.effects.effects_table`) and, when present, its figure (effects.png)."""
    names = {str(r["letters"]): str(r["term"]) for _, r in effects.iterrows() if len(str(r["letters"])) == 1}

    def aliases(v) -> str:  # "CD,EF" -> "CD (eta x vis), EF (...)": the letters of the factors' order
        if v is None or pd.isna(v) or not str(v):
            return "–"
        return ", ".join(_esc(w + (" (" + " x ".join(names[c] for c in w) + ")" if all(c in names for c in w) else ""))
                         for w in str(v).split(","))

    def levels(r) -> str:  # an interaction: from the runs where its factors' levels differ to where they agree
        if len(str(r["letters"])) > 1:
            return "differ → agree"
        if "low" not in r or pd.isna(r["low"]) or pd.isna(r["high"]):
            return "–"
        return _esc(f"{r['low']} → {r['high']}")

    parts = ["<h2>Main effects and two-factor interactions</h2>",
             "<p>Effect of each factor (and of each pair, its interaction) from its first to its second level on "
             "a run's position RMSE, per method and setting of the grid: the difference of the mean RMSE of the "
             "runs at the two levels (for an interaction, of the runs where the two factors' levels agree and "
             "where they differ), with its 95 % t interval from the residual variance of the fitted model "
             "(Montgomery, Design and Analysis of Experiments, Ch. 6 and 8). An interval that holds 0 leaves "
             "the sign undetermined. In a fraction, an effect is the sum of the effects of the terms it is "
             "aliased with (column aliases, in the design's letters, A the first factor of the sweep file). From "
             "<code>effects.parquet</code>.</p>",
             _table([*(_esc(_key_label(k)) for k in grid_keys), "method", "term", "levels", "effect [m]",
                     "95 % interval [m]", "aliases", "runs"],
                    [[*(_esc(_value_label(r[k])) for k in grid_keys), _method_cell(str(r["method"])),
                      _esc(str(r["term"])), levels(r), f"{r['effect']:+.3f}",
                      f"[{r['ci_low']:+.3f}, {r['ci_high']:+.3f}]", aliases(r["aliases"]), str(int(r["n_runs"]))]
                     for _, r in effects.iterrows()], left_cols=len(grid_keys) + 3)]
    if has_figure:
        parts.append(_figure_html(
            "effects.png", "Effects on the position RMSE with their 95 % intervals",
            "One panel per setting of the grid and method, one bar per term (blue: main effect, red: two-factor "
            "interaction) with its 95 % interval. How to read: a bar whose interval crosses 0 is not resolved by "
            "these seeds; the longest bars are the factors that matter.", prefix="", what=what))
    return parts


def write_sweep_report(out: Path, force: bool = False) -> Path:
    """Write ``out/report.html`` and ``out/figures/*.png`` from the sweep's files (``force``: a user's
    file in the way is kept aside, :func:`couplers.publish.publish_members`)."""
    out = Path(out)
    with open(out / "sweep.toml", "rb") as fh:
        spec = tomllib.load(fh)["sweep"]
    grid_keys = list((spec.get("grid") or {}).keys())
    factors = bool(spec.get("factors"))
    keys = grid_keys + (["factor", "level"] if factors else [])
    curves = _read_checked(out / "curves.parquet", ["curve", *keys, "method", "x", "n_runs", "n_samples",
                                                    "rmse_pos_m", "rmse_vel_mps", "correct_pct", "wrong_pct",
                                                    "discarded_pct"])
    curves["method"] = curves["method"].astype(str)
    zones = _read_optional(out / "zones.parquet", [*keys, "method", "zone", "n_runs", "n_samples", "rmse_pos_m",
                                                   "p95_pos_m"])
    v2v = _read_optional(out / "v2v.parquet", [*keys, "n_runs", "degree", "vehicle_steps"])
    paired = _read_optional(out / "paired.parquet", [*keys, "zone", "a", "b", "mean", "ci_lo", "ci_hi", "seeds"])
    consistency = _read_optional(out / "consistency.parquet", [*keys, "method", "zone", "seeds", "anees", "band_lo",
                                                               "band_hi", "inside_band", "t_lo", "t_hi", "inside_95"])
    effects = _read_optional(out / "effects.parquet", [*grid_keys, "method", "term", "letters", "effect", "ci_low",
                                                       "ci_high", "aliases", "n_runs"])
    runs_text = _runs_text(curves[curves["curve"] == "overall"])
    seeds = spec.get("eval_seeds") or spec.get("seeds") or []
    seed_text = f"seeds {min(seeds)}–{max(seeds)}" if seeds else ""
    what = (f"<i>Sweep: {_esc(spec.get('name', ''))}, base config <code>{_esc(Path(str(spec.get('base', ''))).name)}"
            f"</code>, {_esc(seed_text or 'no seeds')}, methods {_esc(', '.join(spec.get('methods', [])))}.</i>")

    def build(tmp: Path) -> None:
        figdir = tmp / "figures"
        blocks = []
        split = (f"one panel per value of {_esc(_key_label(keys[0]))}" if keys else "all runs in one panel")
        lines = ("one line per method" + (" and value of " + ", ".join(_esc(_key_label(k)) for k in keys[1:])
                                          if len(keys) > 1 else ""))
        with matplotlib.rc_context(_RC):
            rows = [("time", "rmse_pos_m", "vehicle position RMSE"),
                    ("feature_time", "rmse_pos_m", "feature position RMSE")]
            if factors:  # one factor at a time: the study's own figures, not the Sec. V curves
                blocks += _study_blocks(curves, zones, v2v, spec, grid_keys, figdir, runs_text, seed_text, what)
            elif zones is not None and len(set(zones["zone"].astype(str)) - {"all"}) > 1 and grid_keys:
                blocks += _zone_blocks(zones, v2v, grid_keys, figdir, runs_text, seed_text, what)
            if len(curves[curves["curve"] == "time"]) and not factors:
                _fig_panels(curves, rows, keys, "time [s]", figdir / "rmse_time.png")
                has_feat = bool(len(curves[curves["curve"] == "feature_time"]))
                blocks.append(_figure_html(
                    "rmse_time.png", "Location accuracy versus time (paper Fig. 7)",
                    f"Root mean square of the vehicle position error at each time step over all vehicles and "
                    f"{runs_text} ({_esc(seed_text)})"
                    + ("; second row: the same for the feature position estimates (tracks scored against the "
                       "true feature they were most often paired with)" if has_feat else "")
                    + f". {split.capitalize()}, {lines}; a method whose curve does not depend on a swept key is "
                    "drawn once. How to read: lower is better; the gap to GNSS is the cooperative gain, the gap "
                    "to ICP with known association the cost of unknown association.", what=what))
            if len(curves[curves["curve"] == "distance"]) and not factors:
                _fig_panels(curves, [("distance", "rmse_pos_m", "vehicle position RMSE")], keys,
                            "distance to the junction centre [m]", figdir / "rmse_distance.png")
                blocks.append(_figure_html(
                    "rmse_distance.png", "Location accuracy versus distance to the junction (paper Figs. 8 and 10)",
                    f"Root mean square of the vehicle position error of all samples whose true position lies in "
                    f"each {spec.get('distance_bin_m', 20.0):g} m ring around the junction centre (plotted at the "
                    f"ring's middle), over all vehicles, time steps and {runs_text} ({_esc(seed_text)}). "
                    f"{split.capitalize()}, {lines}. How to read: near the centre all clusters are connected and "
                    "sense more features, so cooperative methods gain most there.", what=what))
            asc = curves[curves["curve"] == "association"]
            if len(asc) and asc["correct_pct"].notna().any() and not factors:
                _fig_association(curves, keys, figdir / "association.png")
                blocks.append(_figure_html(
                    "association.png", "Association of V2F measurements (paper Figs. 9 and 11)",
                    "Percentages of all V2F measurements, pooled over the runs of a setting, that were "
                    "associated correctly, wrongly, or discarded (tracks mapped to the true feature they were "
                    f"most often paired with over each run, outside the estimator), versus "
                    f"{_esc(_key_label(keys[0])) if keys else 'the single setting'}; {runs_text} "
                    f"({_esc(seed_text)}). How to read: eta_TH = 0.5 trades discarded measurements for fewer "
                    "wrong associations.", what=what))
        header, rows = _summary_rows(curves, keys)
        parts = [
            '<dl class="meta">' + "".join(f"<dt>{_esc(k)}</dt><dd>{_esc(v)}</dd>" for k, v in (
                ("sweep", spec.get("name", "")), ("base config", spec.get("base", "")),
                ("runs", spec.get("runs", "")), ("seeds", seed_text), ("methods", ", ".join(spec.get("methods", []))),
                ("swept", ", ".join(f"{k} = {list(v)}" for k, v in (spec.get("grid") or {}).items()) or "–"),
                ("fixed", ", ".join(f"{k} = {v}" for k, v in (spec.get("set") or {}).items()) or "–"),
                ("factors", "; ".join(f"{k}: " + ", ".join(lv["label"] + (" (preset)" if lv.get("preset") else "")
                                                           for lv in v)
                                      for k, v in (spec.get("factors") or {}).items()) or "–"),
            )) + "</dl>",
            "<h2>Summary per setting</h2>",
            "<p>Pooled over all runs of a setting: RMSE = square root of the mean squared error over all "
            "vehicles, time steps and runs; association percentages of all V2F measurements. Per-run numbers "
            "are in <code>sweep.parquet</code>, the curves in <code>curves.parquet</code>, each run's files in "
            "<code>runs/</code>.</p>",
            _table(header, rows, left_cols=len(keys) + 1),
        ]
        if spec.get("eval_seeds"):
            parts.append(f"<p>Scored on the evaluation seeds {_esc(str(spec['eval_seeds']))}; the tuning seeds "
                         f"{_esc(str(spec.get('tune_seeds')))} ran but are in no table or figure.</p>")
        if paired is not None and len(paired):
            parts += ["<h2>Paired differences per setting and zone</h2>",
                      "<p>Difference of the per-seed position RMSE of two methods on the same runs (same seed, "
                      "same traffic), mean over the seeds with its 95 % paired t interval (few seeds; a "
                      "difference of two RMSEs over many vehicle-steps is roughly normal); an interval that "
                      "holds 0 leaves the sign undetermined. From <code>paired.parquet</code>.</p>",
                      _table([*(_esc(_key_label(k)) for k in keys), "zone", "difference", "mean [m]",
                              "95 % interval [m]", "seeds"],
                             [[*(_esc(_value_label(r[k])) for k in keys), _esc(str(r["zone"])),
                               _esc(f"{method_label(r['a'])} − {method_label(r['b'])}"), f"{r['mean']:+.2f}",
                               f"[{r['ci_lo']:+.2f}, {r['ci_hi']:+.2f}]", str(int(r["seeds"]))]
                              for _, r in paired.iterrows()], left_cols=len(keys) + 2)]
        if consistency is not None and len(consistency):
            parts += ["<h2>Consistency across seeds</h2>",
                      "<p>Average NEES: the mean over the seeds of each run's time-averaged 2-D position NEES "
                      "(after the warm-up), per GNSS zone (\"all\" pools them); 2 for a consistent method. Its 95 % "
                      "band counts each run as one independent 2-dof sample, [χ²<sub>2S</sub>(0.025), "
                      "χ²<sub>2S</sub>(0.975)] / S for S seeds: samples within a run are correlated, the runs are not, "
                      "and a run's time average spreads at most as much as one sample, so the band is conservative "
                      "(<code>experiments/sweep/consistency.py</code>). Beside it, the 95 % t interval of the per-run "
                      "means, and the mean share of samples inside the reported 95 % ellipse (95 % when consistent). "
                      "From <code>consistency.parquet</code>.</p>",
                      _table([*(_esc(_key_label(k)) for k in keys), "method", "zone", "seeds", "average NEES",
                              "χ² band", "inside band", "t interval", "inside 95 % [%]"],
                             [[*(_esc(_value_label(r[k])) for k in keys), _method_cell(str(r["method"])),
                               _esc(str(r["zone"])), str(int(r["seeds"])), _fmt(r["anees"]),
                               f"[{r['band_lo']:.2f}, {r['band_hi']:.2f}]", "yes" if r["inside_band"] else "no",
                               "–" if not np.isfinite(r["t_lo"]) else f"[{r['t_lo']:.2f}, {r['t_hi']:.2f}]",
                               _fmt(100.0 * r["inside_95"], 1)]
                              for _, r in consistency.iterrows()], left_cols=len(keys) + 2)]
        if effects is not None and len(effects):
            parts += _effects_parts(effects, grid_keys, (out / "effects.png").exists(), what)
        parts.append("<h2>Figures</h2>")
        parts.extend(blocks if blocks else ["<p>No figures (no curves).</p>"])
        (tmp / "report.html").write_text(_page(f"coloc sweep report: {spec.get('name', '')}", "\n".join(parts)),
                                         encoding="utf-8")

    return _atomic_publish(out, build, force=force)
