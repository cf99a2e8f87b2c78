"""HTML building blocks of the reports: escaping, number formats, tables, figure blocks, the page."""

from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np

from experiments.report.load import _Run
from experiments.report.styles import _sorted_labels, method_color, method_label, order_methods


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


def _figure_html(fname: str, title: str, caption: str, prefix: str = "figures/", what: str = "") -> str:
    """A figure with its caption; ``what`` (what was run: config, seed or seeds, span, methods) ends the caption."""
    return (f'<figure id="{_esc(Path(fname).stem)}"><img src="{_esc(prefix + fname)}" alt="{_esc(title)}">'
            f"<figcaption><b>{_esc(title)}.</b> {caption}{' ' + what if what else ''}</figcaption></figure>")


def _what_was_run(run: _Run) -> str:
    """One sentence for every figure of a run: which config, seed, simulated span and methods."""
    cfg_run = run.config.get("run") or {}
    source = (run.config.get("provenance") or {}).get("config_source") or run.summary.get("config") or "?"
    dur = cfg_run.get("duration_s")
    span = f"{float(dur):g} s simulated" if dur is not None else "simulated span not recorded"
    methods = ", ".join(run.methods) or "none"
    return (f"<i>Run: <code>{_esc(Path(str(source)).name)}</code>, seed {_esc(run.seed)}, {_esc(span)}, "
            f"methods {_esc(methods)}.</i>")


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
        nees = s.get("nees_pos") or {}
        inside = nees.get("inside_95")
        rows.append([_method_cell(m), _fmt(s.get("rmse_pos_m")), _fmt(s.get("rmse_vel_mps")),
                     _fmt(s.get("p50_pos_m")), _fmt(s.get("p95_pos_m")), _fmt(nees.get("mean")),
                     _fmt(nees.get("median")), _fmt(None if inside is None else 100.0 * inside, 1),
                     _fmt(s.get("seconds"), 2)])
    return rows


def _nees_zone_table(methods: list[str], summary: dict) -> str:
    """Per GNSS zone: mean NEES / median NEES / % inside the 95 % ellipse (summary.json ``nees_pos``)."""
    blocks = {m: ((summary.get("methods") or {}).get(m) or {}).get("nees_pos") or {} for m in methods}
    labels = _sorted_labels(z for b in blocks.values() for z in (b.get("by_zone") or {}))
    if not labels:
        return "<p>No per-zone NEES in summary.json.</p>"
    header = ["method"] + [f"zone {_esc(z)}<br><small>mean / median NEES / % inside 95 %</small>" for z in labels]
    rows = []
    for m in methods:
        row = [_method_cell(m)]
        for z in labels:
            b = (blocks[m].get("by_zone") or {}).get(z)
            if not isinstance(b, dict):  # summaries written before the block had its median and share
                row.append("–" if b is None else _fmt(b))
                continue
            inside = b.get("inside_95")
            row.append(f"{_fmt(b.get('mean'))} / {_fmt(b.get('median'))} / "
                       f"{_fmt(None if inside is None else 100.0 * inside, 1)}")
        rows.append(row)
    return _table(header, rows)


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
