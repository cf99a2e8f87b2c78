"""Infrastructure mode: road-side units (RSUs) with V2I range and a radar of unknown pose.

Builds the :class:`coloc.core.frame.InfraFrame` of each step from the true states (pure numpy,
no SUMO): V2I links (vehicles within ``range_m`` of an RSU, like the V2V links from true
positions), unlabelled radar detections in each radar's own frame, and per-vehicle odometry.

Random streams: one ``numpy.random.Generator`` of its own (seeded from the run seed with a
distinct spawn key), so a run with infrastructure keeps the vehicle sensors' noise of the
same run without it, and a run without infrastructure is untouched. The radar poses are
drawn once, at construction: offset ~ N(0, pose_offset_sigma^2 I2) from the RSU position and
rotation uniform in [-pi, pi).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from coloc.core.frame import InfraFrame
from coloc.core.vehicles import match_ids
from couplers.errors import InputError


@dataclass(frozen=True)
class InfraSetup:
    """RSUs of a run: ids and positions (R, 2) plus the sensor parameters."""

    rsu_ids: tuple[str, ...]
    rsu_xy: np.ndarray  # (R, 2)
    range_m: float = 70.0
    radar_sigma_m: float = 0.5
    pose_offset_sigma_m: float = 5.0
    odom_sigma_m: float = 0.1


def junction_positions(net_path: Path, ids: tuple[str, ...], config_path: Path, field: str) -> np.ndarray:
    """(x, y) of the named junctions of a SUMO net; an unknown id is an InputError naming ``field[i]``."""
    found: dict[str, tuple[float, float]] = {}
    wanted = set(ids)
    try:
        for _, elem in ET.iterparse(str(net_path), events=("end",)):
            if elem.tag == "junction":
                jid = elem.get("id")
                if jid in wanted:
                    found[jid] = (float(elem.get("x")), float(elem.get("y")))
                elem.clear()
    except (OSError, ET.ParseError) as exc:
        raise InputError(config_path, field, f"cannot read the net {net_path}: {exc}") from None
    for i, jid in enumerate(ids):
        if jid not in found:
            raise InputError(config_path, f"{field}[{i}]", f"no junction {jid!r} in {net_path}")
    return np.array([found[j] for j in ids], dtype=float).reshape(-1, 2)


def _rotation(theta: float) -> np.ndarray:
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


class InfraSynth:
    """Stateful synthesiser of InfraFrames (keeps the last true position of each vehicle for odometry)."""

    def __init__(self, setup: InfraSetup, seed: int):
        self.setup = setup
        self.rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x1F7A]))
        r = len(setup.rsu_ids)
        self.radar_xy = np.asarray(setup.rsu_xy, float) + setup.pose_offset_sigma_m * self.rng.standard_normal((r, 2))
        self.radar_theta = self.rng.uniform(-np.pi, np.pi, r)
        self._prev_ids = np.empty(0, dtype=object)
        self._prev_xy = np.empty((0, 2))

    def step(self, vehicle_ids: np.ndarray, entered: np.ndarray, xy_true: np.ndarray) -> tuple[InfraFrame, np.ndarray]:
        """InfraFrame of one step and the truth ``radar_vehicle`` (P,)."""
        s = self.setup
        n = xy_true.shape[0]
        n_rsu = len(s.rsu_ids)
        rsu = np.asarray(s.rsu_xy, float)
        d2 = ((xy_true[None, :, :] - rsu[:, None, :]) ** 2).sum(axis=2) if n else np.empty((n_rsu, 0))
        inside = d2 <= s.range_m**2  # (R, N)
        v2i = sp.csr_matrix(inside, dtype=bool)
        v2i.sort_indices()
        # Radar detections in the radar frame: q = R(theta)^T (p - s) + noise, shuffled within each RSU.
        owner, veh = np.nonzero(inside)  # grouped by RSU
        keys = self.rng.random(owner.size)
        order = np.lexsort((keys, owner))
        owner, veh = owner[order].astype(np.int64), veh[order].astype(np.int64)
        rel = xy_true[veh] - self.radar_xy[owner]
        c, si = np.cos(self.radar_theta[owner]), np.sin(self.radar_theta[owner])
        local = np.stack([c * rel[:, 0] + si * rel[:, 1], -si * rel[:, 0] + c * rel[:, 1]], axis=1)
        radar_z = local + s.radar_sigma_m * self.rng.standard_normal((owner.size, 2))
        # Odometry: true displacement since the last step + N(0, odom_sigma^2 I2); NaN when fresh.
        idx = match_ids(self._prev_ids, vehicle_ids)
        fresh = (idx < 0) | np.asarray(entered, bool)
        odom = np.full((n, 2), np.nan)
        noise = s.odom_sigma_m * self.rng.standard_normal((n, 2))
        ok = ~fresh
        odom[ok] = xy_true[ok] - self._prev_xy[idx[ok]] + noise[ok]
        self._prev_ids, self._prev_xy = np.asarray(vehicle_ids), np.array(xy_true, float)
        infra = InfraFrame(
            rsu_ids=np.array(s.rsu_ids, dtype=object),
            rsu_xy=rsu.copy(),
            v2i=v2i,
            radar_z=radar_z.reshape(-1, 2),
            radar_owner=owner,
            radar_var=float(s.radar_sigma_m**2),
            odom=odom,
            odom_var=float(s.odom_sigma_m**2),
        )
        return infra, veh
