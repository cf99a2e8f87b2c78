"""Realistic V2X: market penetration, packet delivery by distance with a separate
curve through buildings, and a budget of broadcast rounds per step. Opt-in through the ``[v2x]``
config table (SUMO scenarios only); without it the coupler builds frames exactly as before.

Model:

* Penetration: every SUMO vehicle is equipped or not, once for its whole trip, by a uniform
  u(vehicle id, seed) in [0, 1) taken from a keyed BLAKE2b hash of the id (``hashlib``, stable across
  processes and Python versions, unlike the salted ``hash()``): equipped iff u < ``penetration_rate``.
  For one seed the equipped set of a lower rate is a subset of that of a higher rate (nested sets:
  penetration curves keep their vehicles and are far less noisy), and the draw is independent of
  every other random stream. Unequipped vehicles are left out of the frame (not estimated, no GNSS /
  V2F rows, not in ``neighbors``); they stay in SUMO's traffic statistics and, with ``[perception]``,
  still occlude sight lines (the coupler hands every SUMO vehicle's footprint to the perception).
* Link model: the packet delivery ratio (PDR) of a V2V link is a function of its length d, linearly
  interpolated in the table (``pdr_distance_m``, ``pdr_los``), 0 beyond the last distance; a link
  whose straight segment between the two vehicle positions intersects a building of the net folder's
  ``buildings.geojson`` takes ``pdr_nlos`` instead (one shapely 2 STRtree query for all links of a
  step, :func:`couplers.sensing.occlusion.occluded_by_buildings`; a net without buildings: every link is
  LOS). The V2V neighbourhood ``neighbors`` keeps its meaning (pairs within ``sensors.v2v_range_m``);
  the channel is a layer on top: each directed entry j -> i of ``neighbors`` gets a delivery
  probability, and every message on it in every round is delivered independently with that
  probability (losses are directed: i may hear j while j misses i).
* Rounds: ``rounds_per_step`` broadcast rounds fit in one step (an integer >= 1, or "unlimited",
  the default; the frame carries 0 for unlimited, coloc.core.v2x).
* ``channel = "ideal"`` replaces the delivery curves by 1 on every link within Rc: the penetration and
  the round budget alone (the ideal arm of the penetration study).

What the frame carries: :class:`coloc.core.v2x.V2xFrame` (probabilities aligned with ``neighbors``,
the round budget, a per-step seed); estimators realise round r with
:func:`coloc.core.v2x.round_deliveries`, from ``SeedSequence([step seed, r])``.

Random streams: equipment is the keyed hash above (no generator); the per-step channel seeds come
from their own generator ``SeedSequence([seed, 0x5A2, crc32("rounds")])`` (as the perception's
effects, couplers.sensing.perception.effect_rng), one 63-bit integer per step. GNSS, prior, inertial, V2F and
perception streams are untouched: with every vehicle equipped the frame's other fields are identical
to a run without ``[v2x]``.

Default delivery table (derived, not read off a measured curve): 3GPP TR 37.885 V15.3.0 (2019),
"Study on evaluation methodology of new Vehicle-to-Everything (V2X) use cases for LTE and NR",
Table 6.2.1-1, V2V sidelink, urban: LOS PL = 38.77 + 16.7 log10 d + 18.2 log10 fc (shadowing
sigma 3 dB), NLOS (building) PL = 36.85 + 30 log10 d + 18.9 log10 fc (sigma 4 dB), fc = 5.9 GHz (the
same formulas as ns-3's ThreeGppV2vUrbanPropagationLossModel); link budget 23 dBm transmit power
(TR 37.885's UE power), 3 dBi antenna gain at each end, receiver sensitivity -82 dBm (IEEE 802.11-2016
Table 17-18, 10 MHz channel, 6 Mb/s QPSK 1/2, the default rate of the ITS-G5 / DSRC control channel),
i.e. 111 dB maximum coupling loss; a packet is received when its SNR margin after log-normal
shadowing and Rayleigh block fading per packet is positive, averaged over both:
PDR(d) = E_X[exp(-10^((PL(d) + X - 111) / 10))], X ~ N(0, sigma^2) (Gauss-Hermite quadrature,
:func:`derived_pdr`; PL evaluated at max(d, 3 m), the model's lower validity bound). Not modelled:
interference and channel congestion (what makes measured urban PDRs fall faster), the time
correlation of shadowing (13 m / 10 m decorrelation distance in TR 37.885 Table 6.2.3-1: real losses
come in bursts, here they are independent per packet), vehicle blockage (NLOSv). Rayleigh fading is
pessimistic for LOS links (Rician in reality) by a few percent at 250 m. Give a measured table for
another radio or a congested channel.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from coloc.core.v2x import UNLIMITED_ROUNDS, V2xFrame
from coloc.core.vehicles import match_ids
from couplers.errors import InputError
from couplers.net.buildings import Buildings
from couplers.sensing.occlusion import occluded_by_buildings
from couplers.sensing.perception import effect_rng

V2X_STREAM_TAG = 0x5A2
_EQUIP_PERSON = b"coloc.v2x.equip"  # BLAKE2b personalisation: this hash is the equipment draw only

# --- the default delivery table (see the module docstring) ---------------------------------------
CARRIER_GHZ = 5.9
LINK_BUDGET_DB = 23.0 + 3.0 + 3.0 + 82.0  # Tx power + two antenna gains - receiver sensitivity
LOS_SHADOWING_DB = 3.0
NLOS_SHADOWING_DB = 4.0
MIN_DISTANCE_M = 3.0  # TR 37.885 Table 6.2.1-1: pathloss valid from 3 m


def pathloss_db(d: np.ndarray, los: bool) -> np.ndarray:
    """TR 37.885 Table 6.2.1-1, V2V urban pathloss (dB) at distance d (m), LOS or NLOS (building)."""
    d = np.maximum(np.asarray(d, dtype=float), MIN_DISTANCE_M)
    if los:
        return 38.77 + 16.7 * np.log10(d) + 18.2 * math.log10(CARRIER_GHZ)
    return 36.85 + 30.0 * np.log10(d) + 18.9 * math.log10(CARRIER_GHZ)


def derived_pdr(d: np.ndarray, los: bool, nodes: int = 40) -> np.ndarray:
    """PDR at distance d: probability that the SNR margin after log-normal shadowing and Rayleigh block
    fading is positive, E_X[exp(-10^(-(budget - PL - X) / 10))] by Gauss-Hermite quadrature."""
    x, w = np.polynomial.hermite_e.hermegauss(nodes)
    w = w / w.sum()
    sigma = LOS_SHADOWING_DB if los else NLOS_SHADOWING_DB
    margin = LINK_BUDGET_DB - (pathloss_db(d, los)[..., None] + sigma * x)
    return np.exp(-(10.0 ** (-margin / 10.0))) @ w


# Check against a field measurement: PDR > 0.9 up to 45-70 m around the corner at three urban junctions
# (Clayton, Stocker, Alwane, Hassan, Radio Science 54, 468-479, 2019); DEFAULT_PDR_NLOS falls below 0.9
# at 38 m, on the lossy side (docs/validation/v2x.md).
DEFAULT_PDR_DISTANCE_M = (0.0, 25.0, 50.0, 75.0, 100.0, 125.0, 150.0, 200.0, 250.0, 300.0, 400.0, 500.0, 750.0,
                          1000.0)
#: :func:`derived_pdr` at DEFAULT_PDR_DISTANCE_M, rounded to 3 decimals (tests/couplers/test_v2x.py checks it).
DEFAULT_PDR_LOS = (1.0, 1.0, 0.999, 0.997, 0.996, 0.994, 0.992, 0.987, 0.981, 0.974, 0.959, 0.941, 0.889, 0.83)
DEFAULT_PDR_NLOS = (1.0, 0.974, 0.828, 0.585, 0.354, 0.193, 0.098, 0.023, 0.005, 0.001, 0.0, 0.0, 0.0, 0.0)


CHANNELS = ("curves", "ideal")
UNLIMITED = "unlimited"  # [v2x] rounds_per_step: as many rounds as a method wants


def _finite(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class V2xParams:
    """The ``[v2x]`` table (model and default sources in the module docstring)."""

    penetration_rate: float = 1.0  # share of SUMO vehicles equipped, (0, 1]
    pdr_distance_m: tuple[float, ...] = DEFAULT_PDR_DISTANCE_M
    pdr_los: tuple[float, ...] = DEFAULT_PDR_LOS
    pdr_nlos: tuple[float, ...] = DEFAULT_PDR_NLOS
    rounds_per_step: int | str = UNLIMITED  # broadcast rounds per step (>= 1), or "unlimited"
    # "curves": delivery by distance from pdr_los / pdr_nlos; "ideal": every link within Rc delivers every
    # round (penetration and round budget alone, e.g. the ideal arm of the penetration study)
    channel: str = "curves"

    def __post_init__(self):
        if not (_finite(self.penetration_rate) and 0.0 < self.penetration_rate <= 1.0):
            raise InputError(None, "penetration_rate", f"must be in (0, 1], got {self.penetration_rate!r}")
        dist = self.pdr_distance_m
        if not isinstance(dist, tuple) or not dist:
            raise InputError(None, "pdr_distance_m", "needs at least one distance")
        for i, d in enumerate(dist):
            if not (_finite(d) and d >= 0):
                raise InputError(None, f"pdr_distance_m[{i}]", f"must be >= 0 and finite, got {d!r}")
            if i and not d > dist[i - 1]:
                raise InputError(None, f"pdr_distance_m[{i}]",
                                 f"distances must increase strictly, got {dist[i - 1]!r} then {d!r}")
        for key in ("pdr_los", "pdr_nlos"):
            curve = getattr(self, key)
            if not isinstance(curve, tuple) or len(curve) != len(dist):
                raise InputError(None, key, f"needs one value per distance of pdr_distance_m ({len(dist)}), "
                                            f"got {len(curve) if isinstance(curve, tuple) else curve!r}")
            for i, p in enumerate(curve):
                if not (_finite(p) and 0.0 <= p <= 1.0):
                    raise InputError(None, f"{key}[{i}]", f"must be a probability in [0, 1], got {p!r}")
                if i and p > curve[i - 1]:
                    raise InputError(None, f"{key}[{i}]", f"delivery must not increase with distance, got "
                                                          f"{curve[i - 1]!r} then {p!r}")
        if self.channel not in CHANNELS:
            raise InputError(None, "channel", f"must be one of {', '.join(CHANNELS)}, got {self.channel!r}")
        r = self.rounds_per_step
        if r != UNLIMITED and (isinstance(r, bool) or not isinstance(r, int) or r < 1):
            raise InputError(None, "rounds_per_step", f'must be an integer >= 1, or "{UNLIMITED}", got {r!r}')

    @property
    def round_budget(self) -> int:
        """The frame's ``rounds_per_step`` (coloc.core.v2x): the budget, 0 for unlimited."""
        return UNLIMITED_ROUNDS if self.rounds_per_step == UNLIMITED else int(self.rounds_per_step)


# --- penetration ----------------------------------------------------------------------------------


def equipment_uniform(vehicle_ids, seed: int) -> np.ndarray:
    """(N,) u(id, seed) in [0, 1): the first 53 bits of BLAKE2b(id) keyed with the seed."""
    key = int(seed).to_bytes(8, "little", signed=False)
    out = np.empty(len(vehicle_ids))
    for k, vid in enumerate(vehicle_ids):  # once per vehicle of a run (V2xChannel caches the result)
        h = hashlib.blake2b(str(vid).encode(), digest_size=8, key=key, person=_EQUIP_PERSON).digest()
        out[k] = (int.from_bytes(h, "little") >> 11) * 2.0 ** -53
    return out


def equipped(vehicle_ids, seed: int, rate: float) -> np.ndarray:
    """(N,) bool: the vehicle carries a V2X unit (nested in ``rate`` for one seed)."""
    return equipment_uniform(vehicle_ids, seed) < rate


# --- link model -----------------------------------------------------------------------------------


def delivery_probability(d: np.ndarray, nlos: np.ndarray, params: V2xParams) -> np.ndarray:
    """PDR of links of length ``d`` (m), from the NLOS curve where ``nlos``; 0 beyond the last distance."""
    xp = np.asarray(params.pdr_distance_m, dtype=float)
    d = np.asarray(d, dtype=float)
    los_p = np.interp(d, xp, np.asarray(params.pdr_los, dtype=float), right=0.0)
    nlos_p = np.interp(d, xp, np.asarray(params.pdr_nlos, dtype=float), right=0.0)
    return np.where(np.asarray(nlos, dtype=bool), nlos_p, los_p)


def link_nlos(xy: np.ndarray, neighbors: sp.csr_matrix, buildings: Buildings | None) -> np.ndarray:
    """(E,) bool per CSR entry of ``neighbors``: the segment between the two vehicles crosses a building.

    Each undirected pair is tested once (one STRtree query for all), then both entries take its result."""
    e = neighbors.indices.size
    if e == 0 or buildings is None or len(buildings) == 0:
        return np.zeros(e, dtype=bool)
    n = neighbors.shape[0]
    row = np.repeat(np.arange(n, dtype=np.int64), np.diff(neighbors.indptr))
    col = neighbors.indices.astype(np.int64)
    lo, hi = np.minimum(row, col), np.maximum(row, col)
    pairs, inverse = np.unique(lo * n + hi, return_inverse=True)
    a, b = pairs // n, pairs % n
    return occluded_by_buildings(xy[a], xy[b], buildings)[inverse.reshape(-1)]


def link_lengths(xy: np.ndarray, neighbors: sp.csr_matrix) -> np.ndarray:
    """(E,) distance between the two vehicles of each CSR entry."""
    n = neighbors.shape[0]
    row = np.repeat(np.arange(n, dtype=np.int64), np.diff(neighbors.indptr))
    return np.hypot(*(xy[row] - xy[neighbors.indices]).T)


class V2xChannel:
    """The ``[v2x]`` state of one run: who is equipped (cached per vehicle id) and the per-step seeds."""

    STREAMS = ("rounds",)

    def __init__(self, params: V2xParams, seed: int, buildings: Buildings | None = None):
        self.params = params
        self.seed = int(seed)
        self.buildings = buildings
        for name in self.STREAMS:
            setattr(self, name, effect_rng(seed, V2X_STREAM_TAG, name))
        self._ids = np.empty(0, dtype=object)
        self._equipped = np.empty(0, dtype=bool)

    def equipped(self, ids: np.ndarray) -> np.ndarray:
        """(N,) bool for the vehicles on the road; hashes only the ids not seen at the previous step."""
        ids = np.asarray(ids, dtype=object)
        idx = match_ids(self._ids, ids)
        out = np.empty(ids.size, dtype=bool)
        known = idx >= 0
        out[known] = self._equipped[idx[known]]
        new = np.flatnonzero(~known)
        if new.size:
            out[new] = equipped(ids[new], self.seed, self.params.penetration_rate)
        self._ids, self._equipped = ids, out
        return out

    def frame(self, xy: np.ndarray, neighbors: sp.csr_matrix) -> V2xFrame:
        """The channel of one step for the frame's vehicles at ``xy`` (N, 2) with V2V graph ``neighbors``."""
        if self.params.channel == "ideal":
            prob = np.ones(neighbors.nnz)
        else:
            nlos = link_nlos(xy, neighbors, self.buildings)
            prob = delivery_probability(link_lengths(xy, neighbors), nlos, self.params)
        step_seed = int(self.rounds.integers(0, 2**63 - 1, dtype=np.int64))
        return V2xFrame(delivery_prob=prob, rounds_per_step=self.params.round_budget, seed=step_seed)
