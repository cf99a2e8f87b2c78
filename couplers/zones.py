"""Vectorised point-in-polygon lookups: GNSS class and analysis area of each vehicle."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import shapely

from couplers.netfolder import Region


@dataclass(frozen=True)
class RegionIndex:
    """Look up which region contains each point; the first region listed wins on shared borders."""

    regions: tuple[Region, ...]

    @property
    def names(self) -> np.ndarray:
        return np.array([r.name for r in self.regions], dtype=object)

    def locate(self, xy: np.ndarray) -> np.ndarray:
        """Index of the containing region for each point (N,), -1 outside all regions."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        if xy.shape[0] == 0:
            return np.empty(0, dtype=np.int64)
        # A handful of prepared polygons, each tested against all points at once.
        hits = np.stack([shapely.intersects_xy(r.polygon, xy[:, 0], xy[:, 1]) for r in self.regions])
        first = np.argmax(hits, axis=0)
        return np.where(hits[first, np.arange(xy.shape[0])], first, -1).astype(np.int64)

    def names_at(self, xy: np.ndarray, outside: str = "") -> np.ndarray:
        idx = self.locate(xy)
        names = np.append(self.names, outside)
        return names[idx]


def gnss_sigma_for_zone(zones: RegionIndex, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Zone-dependent GNSS accuracy (model (3), Brambilla Sec. VI-A): (zone names, sigma_p, sigma_v).

    Points outside every zone get the worst class of the layout (a conservative
    choice; ``coloc net check`` flags nets whose zones leave roads uncovered).
    """
    idx = zones.locate(xy)
    sp = np.array([r.sigma_p for r in zones.regions])
    sv = np.array([r.sigma_v for r in zones.regions])
    worst = int(np.argmax(sp))
    idx = np.where(idx < 0, worst, idx)
    return zones.names[idx], sp[idx], sv[idx]
