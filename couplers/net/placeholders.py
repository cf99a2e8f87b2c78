"""Which of a net folder's regions are a default layout rather than derived from data.

``coloc net import`` records where the GNSS zones and the analysis areas came from in the folder's
``scenario.toml`` ``[derived]`` (``zones``, ``areas``): from building density or the user's GeoJSON, or
a default layout when the input has no buildings (concentric rectangles over the net's bounding box)
and no areas were given (a 3 x 2 grid). A run's summary.json, its map legend and its captions say so
(:func:`placeholders`). Shipped folders (hand-made, no such record) have none.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

# The text the import writes in [derived] for a default layout (couplers.net.importer.regions).
_DEFAULT_PREFIX = {"zones": "default layout", "areas": "default partition"}
_WHAT = {"zones": "a default layout of concentric rectangles over the net's bounding box (no buildings in the "
                  "data), not derived from data",
         "areas": "a default grid over the net's bounding box, not derived from data"}


def placeholders(scenario: dict) -> dict[str, str]:
    """{"zones": why, "areas": why} for the regions of a scenario.toml (as a dict) that are a default
    layout; empty when both come from data."""
    derived = scenario.get("derived") or {}
    out = {}
    for key, prefix in _DEFAULT_PREFIX.items():
        text = derived.get(key)
        if isinstance(text, str) and text.startswith(prefix):
            out[key] = f"{_WHAT[key]} ({text})"
    return out


def folder_placeholders(net_dir: Path) -> dict[str, str]:
    """:func:`placeholders` of a net folder's scenario.toml (empty when it has none or it does not load)."""
    try:
        with open(Path(net_dir) / "scenario.toml", "rb") as fh:
            return placeholders(tomllib.load(fh))
    except (OSError, tomllib.TOMLDecodeError):
        return {}
