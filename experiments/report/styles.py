"""Styles of the reports: each method's display name and colour, method order, matplotlib settings."""

from __future__ import annotations

import re
import zlib

import numpy as np

from coloc.methods.registry import METHODS


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
    """Known methods in the order of docs/architecture.md "Method names" first, then unknown ones alphabetically."""
    ms = {str(m) for m in methods}
    known = [m for m in _METHOD_ORDER if m in ms]
    return known + sorted(ms - set(known))


def _natural_key(s: str):
    return [(0, int(p), "") if p.isdigit() else (1, 0, p) for p in re.split(r"(\d+)", str(s)) if p]


def _sorted_labels(values) -> list[str]:
    return sorted({str(v) for v in values}, key=_natural_key)
