"""Controlled scenarios of Brambilla et al. Sec. V: the single road (V-A) and the crossroad (V-B).

They yield the same :class:`coloc.core.frame.Frame` s as the SUMO coupler, so every
estimator and report runs on them unchanged. Only the true motion is generated
here; every measurement (fast-start prior, inertial input, GNSS, V2F, V2V graph,
row shuffling) comes from :func:`couplers.sensing.sensors.synthesize_frame` with a
:class:`couplers.sensing.sensors.SensorNoise` seeded by the same seed.

True motion (model (1)), for every vehicle and step::

    x_t = A x_{t-1} + B (a_{t-1} + e_{t-1}),   e ~ N(0, R(h) diag(s_along^2, s_cross^2) R(h)^T)

so the residual ``x_t - A x_{t-1} - B a_{t-1} = B e`` has covariance exactly
Q = B R diag R^T B^T, oriented to the heading h = atan2(vy, vx) of the true
velocity at t-1 (Sec. V-B, "defined according to the vehicle motion
direction"). ``a_{t-1}`` is a small along-track input that keeps the
description of the paper true over the run (speed ~ v_ref, headway ~ h): a
speed-keeping term plus, for a follower, gap and relative-speed terms. It is
what the frame reports as ``accel`` (plus ``accel_sigma`` noise, default 0:
the paper puts all randomness in w). Set ``speed_gain = gap_gain =
rel_speed_gain = 0`` for the literal "zero mean acceleration" of Sec. V-A (line 2261)
(then velocities are random walks and headways drift by tens of metres over
the run). With the input known to the estimator, its error statistics do not
depend on the input, so this choice changes geometry only, not the model.

Features follow model (2): x_F,t = A x_F,t-1 + G eta, G = [Ts I; I],
eta ~ N(0, R(h_F) diag(sv_par^2, sv_perp^2) R(h_F)^T), h_F the heading of the
feature's velocity at t-1; sv_par = vf / 100, sv_perp = sv_par / 2 (Sec. V-B),
so static features (vf = 0) stay exactly still.

Randomness: motion draws come from ``default_rng(SeedSequence([seed, 0x5CE, k]))``
streams (k = one per purpose), measurement noise from ``SensorNoise(seed)``.
Same params + seed -> identical frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
from scipy.spatial import cKDTree

from coloc.core.frame import Frame
from coloc.core.models import input_matrix, transition_matrix
from couplers.sensing.sensors import SensorNoise, SensorParams, synthesize_frame

KMH = 1.0 / 3.6
_STREAM_TAG = 0x5CE
_DRIVE, _FEATURE_INIT, _FEATURE_DRIVE = 0, 1, 2
FEATURE_LAYOUTS = ("sidewalks", "disc")
#: How a vehicle's first fix is drawn (``_Common.start``).
STARTS = ("fast_start", "gnss_fix")


def _stream(seed: int, purpose: int) -> np.random.Generator:
    return np.random.default_rng(np.random.SeedSequence([int(seed), _STREAM_TAG, purpose]))


@dataclass(frozen=True)
class _Common:
    """Fields shared by both scenarios (defaults overridden per scenario)."""

    dt: float
    speed_kmh: float
    sigma_along: float
    sigma_cross: float
    gnss_sigma_p: float
    gnss_sigma_v: float
    v2f_sigma_p: float
    v2f_sigma_v: float
    v2f_range_m: float
    v2v_range_m: float
    # The fix a vehicle starts from at its first frame (``start``). Sec. V states no
    # initialisation; Sec. VI-A (seed 003, lines 2636-2646) uses, for the arterial, a
    # receiver in fast-start condition centred on the true state with sp 2 m, sv 0.1 m/s.
    # "fast_start" (ours for Sec. V too): that prior with prior_sigma_p / prior_sigma_v;
    # "gnss_fix" (the paper preset's): a first receiver fix of the scenario's GNSS accuracy,
    # N(x_true, diag(gnss_sigma_p^2 I, gnss_sigma_v^2 I)), independent of the step's GNSS
    # measurement; prior_sigma_p / prior_sigma_v are then not used.
    start: str = "fast_start"
    prior_sigma_p: float = 2.0
    prior_sigma_v: float = 0.1
    accel_sigma: float = 0.0  # m/s^2 noise on the reported inertial input (paper: 0)
    # Along-track input a_{t-1} = kv (v_ref - v) [+ kg (gap - h) + kr (v_lead - v)] for followers.
    speed_gain: float = 0.2  # 1/s
    gap_gain: float = 0.1  # 1/s^2
    rel_speed_gain: float = 0.5  # 1/s

    @property
    def speed_mps(self) -> float:
        return self.speed_kmh * KMH

    def sensor_params(self) -> SensorParams:
        gnss_fix = self.start == "gnss_fix"
        return SensorParams(
            accel_sigma=self.accel_sigma,
            v2f_range_m=self.v2f_range_m,
            v2f_sigma_p=self.v2f_sigma_p,
            v2f_sigma_v=self.v2f_sigma_v,
            v2v_range_m=self.v2v_range_m,
            prior_sigma_p=self.gnss_sigma_p if gnss_fix else self.prior_sigma_p,
            prior_sigma_v=self.gnss_sigma_v if gnss_fix else self.prior_sigma_v,
        )

    def _check_common(self) -> None:
        if self.start not in STARTS:
            raise ValueError(f"{type(self).__name__}.start must be one of {STARTS}, got {self.start!r}")
        positive = ("dt", "speed_kmh", "gnss_sigma_p", "gnss_sigma_v", "v2f_sigma_p", "v2f_sigma_v")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"{type(self).__name__}.{name} must be > 0, got {getattr(self, name)!r}")
        nonneg = ("sigma_along", "sigma_cross", "v2f_range_m", "v2v_range_m", "prior_sigma_p",
                  "prior_sigma_v", "accel_sigma", "speed_gain", "gap_gain", "rel_speed_gain")
        for name in nonneg:
            if not getattr(self, name) >= 0:
                raise ValueError(f"{type(self).__name__}.{name} must be >= 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class SingleRoadParams(_Common):
    """Sec. V-A (seed 003, lines 2256-2345): two connected vehicles, one lane, two static features.

    Road along +x, lane centre on y = 0, vehicles drive towards +x starting
    with the follower at x = 0 and the leader ``headway_m`` ahead (front to
    front). The paper gives neither the road length nor the duration nor the
    V2F range for this scenario (Fig. 7 is "versus time" only; the text says
    the PF transient occurs "in the first two seconds of V2F sensing" (line 2379), i.e.
    sensing starts after the run starts). Our choice: a 200 m road travelled
    in ceil(200 / v) = 29 s (frames t = 0..29), the features mid-road on the
    right sidewalk (y = -sidewalk_offset_m) at x = L/2 -+ df/2, and Rs = 50 m
    (the paper's urban value) so both features are seen together for about
    the middle half of the pass and not at all at the start.
    """

    dt: float = 1.0
    n_vehicles: int = 2
    speed_kmh: float = 25.0
    headway_m: float = 5.0
    sigma_along: float = 0.2
    sigma_cross: float = 0.001
    gnss_sigma_p: float = 8.0
    gnss_sigma_v: float = 0.1
    feature_spacing_m: float = 3.0  # df; the paper uses 0.5, 3 and 6 m
    road_length_m: float = 200.0  # not in the paper (our choice)
    sidewalk_offset_m: float = 3.0  # lateral distance of the features from the lane centre (our choice)
    v2f_sigma_p: float = 0.2
    v2f_sigma_v: float = 0.1
    v2f_range_m: float = 50.0  # not in the paper for Sec. V-A (our choice, see above)
    v2v_range_m: float = math.inf  # "two interconnected vehicles": always connected
    duration_s: float | None = None  # None: ceil(road_length / speed)

    def __post_init__(self) -> None:
        self._check_common()
        if self.n_vehicles < 1:
            raise ValueError(f"SingleRoadParams.n_vehicles must be >= 1, got {self.n_vehicles!r}")
        if not (self.feature_spacing_m >= 0 and self.road_length_m > 0 and self.headway_m >= 0):
            raise ValueError("SingleRoadParams: feature_spacing_m, headway_m must be >= 0 and road_length_m > 0")

    @property
    def n_steps(self) -> int:
        """Number of frames (t = 0 .. n_steps - 1)."""
        d = self.duration_s if self.duration_s is not None else math.ceil(self.road_length_m / self.speed_mps)
        return int(round(d / self.dt)) + 1

    def features(self) -> np.ndarray:
        """True feature states (2, 4): static, on the sidewalk, spaced df along the road, mid-road."""
        mid = 0.5 * self.road_length_m
        half = 0.5 * self.feature_spacing_m
        return np.array([[mid - half, -self.sidewalk_offset_m, 0.0, 0.0],
                         [mid + half, -self.sidewalk_offset_m, 0.0, 0.0]])


@dataclass(frozen=True)
class CrossroadParams(_Common):
    """Sec. V-B (seed 003, lines 2408-2480): 12 vehicles in 4 clusters of 3 crossing a junction.

    Junction centre at (0, 0); the area's edges are 250 m from it in every
    direction, so each lane is 500 m long (lines 2414-2417). Vehicles are
    "driving straight ahead along their respective lanes approaching a
    cross-junction" (line 2412): one cluster per arm, all four heading to the
    centre (+x, -x, +y, -y), right-hand traffic (lane centre ``lane_offset_m``
    right of the road axis), going straight through and leaving at the opposite
    edge. All clusters start together (the paper's Fig. 1 shows them
    converging; it gives no stagger), the rear vehicle of each cluster on the
    area edge, so all 12 enter at t = 0 and meet near the centre. A vehicle is
    removed from the frames once it is past the far edge; the run ends when all
    have left (about 500 m / 13.9 m/s = 36 s). The spacing inside a cluster is
    not given in the paper: ``cluster_headway_m`` (our choice, 15 m).

    Features: ``n_features`` "randomly deployed on the sidewalks" with initial
    location "uniformly distributed within a circle of radius 150 m" (lines
    2452-2456): ``feature_layout = "sidewalks"`` (the default) draws them
    uniformly on the sidewalks inside the disc. The paper gives no road
    geometry: each road has one lane per direction (lane centre
    ``lane_offset_m`` from the axis) and its sidewalks are the lines
    ``sidewalk_offset_m`` (our choice, 4.75 m: the lane centre plus the single
    road's 3 m) either side of the axis, from the junction corner to the disc
    edge: eight equally long half-lines. ``"disc"`` draws them uniformly over
    the whole disc instead (our first reading: at Nf = 60, 2 % of the features
    have another within 3 m against 27 % on the sidewalks, so far less
    association ambiguity). Static if
    ``feature_speed_mps`` = 0, else initial speed vf along the sidewalk in a
    random direction ("disc": uniform random heading) and model (2) noise
    sv_par = vf / 100 along the motion, sv_perp = sv_par / 2 (lines 2456-2478).
    Moving features are not confined to the disc (the paper says nothing).
    """

    dt: float = 1.0
    vehicles_per_cluster: int = 3
    arm_length_m: float = 250.0
    speed_kmh: float = 50.0
    cluster_headway_m: float = 15.0  # not in the paper (our choice)
    lane_offset_m: float = 1.75  # half a 3.5 m lane (our choice)
    sigma_along: float = 0.35
    sigma_cross: float = 0.001
    gnss_sigma_p: float = 9.0
    gnss_sigma_v: float = 0.25
    n_features: int = 20  # the paper sweeps 3, 10, 20, 60
    feature_disc_radius_m: float = 150.0
    feature_layout: str = "sidewalks"  # "sidewalks" (the paper, line 2452) or "disc" (uniform in the disc)
    sidewalk_offset_m: float = 4.75  # sidewalk line from the road axis (our choice: lane centre + 3 m)
    feature_speed_mps: float = 0.0  # vf; the paper uses 0 (static), 1, 2, 5
    v2f_sigma_p: float = 0.1
    v2f_sigma_v: float = 0.1
    v2f_range_m: float = 75.0
    v2v_range_m: float = 250.0
    area_ring_m: float = 25.0  # width of the distance rings used as ``truth.area`` labels
    max_duration_s: float | None = None  # None: 2 x the nominal crossing time
    centre: tuple[float, float] = field(default=(0.0, 0.0))

    N_CLUSTERS = 4  # one per arm (class constant, not a field)

    def __post_init__(self) -> None:
        self._check_common()
        if self.vehicles_per_cluster < 1 or self.n_features < 0:
            raise ValueError("CrossroadParams: vehicles_per_cluster must be >= 1 and n_features >= 0")
        if not (self.arm_length_m > 0 and self.feature_disc_radius_m >= 0 and self.feature_speed_mps >= 0
                and self.area_ring_m > 0 and self.cluster_headway_m >= 0):
            raise ValueError("CrossroadParams: arm_length_m, area_ring_m must be > 0; "
                             "feature_disc_radius_m, feature_speed_mps, cluster_headway_m >= 0")
        if self.feature_layout not in FEATURE_LAYOUTS:
            raise ValueError(f"CrossroadParams: feature_layout must be one of {', '.join(FEATURE_LAYOUTS)}")
        if self.feature_layout == "sidewalks" and not (
                0.0 <= self.sidewalk_offset_m < self.feature_disc_radius_m / math.sqrt(2.0)):
            raise ValueError("CrossroadParams: sidewalk_offset_m must be >= 0 and leave sidewalk inside the "
                             "feature disc (below feature_disc_radius_m / sqrt(2))")

    @property
    def n_vehicles(self) -> int:
        return self.N_CLUSTERS * self.vehicles_per_cluster

    @property
    def path_length_m(self) -> float:
        return 2.0 * self.arm_length_m

    @property
    def max_steps(self) -> int:
        d = self.max_duration_s
        if d is None:
            d = 2.0 * (self.path_length_m + self.vehicles_per_cluster * self.cluster_headway_m) / self.speed_mps
        return int(math.ceil(d / self.dt)) + 1


# ---------------------------------------------------------------------------
# Shared motion engine


@dataclass(frozen=True)
class _Fleet:
    ids: np.ndarray  # (M,) object
    x0: np.ndarray  # (M, 4) initial true states
    lane_dir: np.ndarray  # (M, 2) unit vector of the lane
    leader: np.ndarray  # (M,) int index of the vehicle ahead in the lane, -1 for none
    start: np.ndarray  # (M, 2) point where the lane enters the area
    headway: float


def along_track_input(x: np.ndarray, fleet: _Fleet, params: _Common) -> np.ndarray:
    """The inertial input a_{t-1} (M, 2): speed keeping, plus gap keeping for followers."""
    u = fleet.lane_dir
    v_al = np.einsum("ij,ij->i", x[:, 2:], u)
    a = params.speed_gain * (params.speed_mps - v_al)
    f = np.flatnonzero(fleet.leader >= 0)
    if f.size:
        lead = fleet.leader[f]
        gap = np.einsum("ij,ij->i", x[lead, :2] - x[f, :2], u[f])
        a[f] += params.gap_gain * (gap - fleet.headway) + params.rel_speed_gain * (v_al[lead] - v_al[f])
    return a[:, None] * u


def _rotated_noise(rng: np.random.Generator, heading: np.ndarray, s_par: float, s_perp: float) -> np.ndarray:
    """Samples of N(0, R(h) diag(s_par^2, s_perp^2) R(h)^T), (M, 2)."""
    n = rng.standard_normal((heading.size, 2))
    c, s = np.cos(heading), np.sin(heading)
    along, cross = s_par * n[:, 0], s_perp * n[:, 1]
    return np.stack([c * along - s * cross, s * along + c * cross], axis=1)


def _heading(x: np.ndarray) -> np.ndarray:
    return np.arctan2(x[:, 3], x[:, 2])


class _World:
    """True vehicle and feature states, stepped by models (1) and (2)."""

    def __init__(self, fleet: _Fleet, features0: np.ndarray, feature_s_par: float,
                 params: _Common, seed: int):
        self.fleet, self.params = fleet, params
        self.x = fleet.x0.astype(float).copy()
        self.accel = np.zeros((self.x.shape[0], 2))  # a_{t-1}; zero before the first step
        self.features = features0.astype(float).copy()
        self.f_par, self.f_perp = feature_s_par, 0.5 * feature_s_par
        self.drive = _stream(seed, _DRIVE)
        self.feat_drive = _stream(seed, _FEATURE_DRIVE)
        self.A = transition_matrix(params.dt)
        self.B = input_matrix(params.dt)
        self.G = np.vstack([params.dt * np.eye(2), np.eye(2)])

    def step(self) -> None:
        p = self.params
        a = along_track_input(self.x, self.fleet, p)
        e = _rotated_noise(self.drive, _heading(self.x), p.sigma_along, p.sigma_cross)
        self.x = self.x @ self.A.T + (a + e) @ self.B.T
        self.accel = a
        if self.features.shape[0] and self.f_par > 0:
            eta = _rotated_noise(self.feat_drive, _heading(self.features), self.f_par, self.f_perp)
            self.features = self.features @ self.A.T + eta @ self.G.T


def _frames(world: _World, n_steps: int, present_fn, area_fn, seed: int,
            feature_ids: np.ndarray) -> Iterator[Frame]:
    p = world.params
    sensors = p.sensor_params()
    noise = SensorNoise(seed)
    seen = np.zeros(world.x.shape[0], dtype=bool)
    gone = np.zeros_like(seen)
    static_tree = None
    static = world.f_par == 0
    if static and world.features.shape[0]:
        static_tree = cKDTree(world.features[:, :2])
    for k in range(n_steps):
        if k:
            world.step()
        present = present_fn(world.x) & ~gone
        gone |= seen & ~present  # a vehicle that left never comes back
        if gone.all():
            return
        idx = np.flatnonzero(present)
        entered = ~seen[idx]
        seen[idx] = True
        x_true = world.x[idx].copy()
        n = idx.size
        feats = world.features.copy()
        tree = static_tree if static else (cKDTree(feats[:, :2]) if feats.shape[0] else None)
        yield synthesize_frame(
            t=k * p.dt,
            dt=p.dt,
            vehicle_ids=world.fleet.ids[idx],
            entered=entered,
            x_true=x_true,
            accel_true=np.where(entered[:, None], 0.0, world.accel[idx]),
            heading=_heading(x_true),
            gnss_sigma_p=np.full(n, p.gnss_sigma_p),
            gnss_sigma_v=np.full(n, p.gnss_sigma_v),
            features_true=feats,
            feature_tree=tree,
            params=sensors,
            noise=noise,
            zone=np.full(n, "-", dtype=object),
            area=area_fn(x_true),
            feature_ids=feature_ids,
        )


# ---------------------------------------------------------------------------
# Scenarios


def _single_road_fleet(p: SingleRoadParams) -> _Fleet:
    n = p.n_vehicles
    # Vehicle 0 leads; vehicle i follows i - 1; the last one starts at x = 0.
    s0 = (n - 1 - np.arange(n)) * p.headway_m
    x0 = np.zeros((n, 4))
    x0[:, 0] = s0
    x0[:, 2] = p.speed_mps
    return _Fleet(
        ids=np.array([f"v{i}" for i in range(n)], dtype=object),
        x0=x0,
        lane_dir=np.tile([1.0, 0.0], (n, 1)),
        leader=np.arange(n) - 1,
        start=np.zeros((n, 2)),
        headway=p.headway_m,
    )


def single_road_frames(params: SingleRoadParams, seed: int) -> Iterator[Frame]:
    """Frames of the single-road scenario (Sec. V-A); all vehicles present in every frame."""
    fleet = _single_road_fleet(params)
    world = _World(fleet, params.features(), 0.0, params, seed)
    n = fleet.ids.size
    return _frames(
        world, params.n_steps,
        present_fn=lambda x: np.ones(n, dtype=bool),
        area_fn=lambda x: np.full(x.shape[0], "-", dtype=object),
        seed=seed,
        feature_ids=np.array(["F0", "F1"], dtype=object),
    )


# Travel directions of the four clusters: towards +x (from the west arm), -x, +y, -y.
_ARM_DIRS = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
_ARM_NAMES = ("W", "E", "S", "N")  # arm each cluster comes from


def _crossroad_fleet(p: CrossroadParams) -> _Fleet:
    m = p.vehicles_per_cluster
    c = np.asarray(p.centre, dtype=float)
    ids, x0, dirs, leader, start = [], [], [], [], []
    for a, (u, name) in enumerate(zip(_ARM_DIRS, _ARM_NAMES)):
        right = np.array([u[1], -u[0]])
        entry = c - p.arm_length_m * u + p.lane_offset_m * right
        for k in range(m):  # k = 0 leads; the rear vehicle (k = m-1) starts on the area edge
            s = (m - 1 - k) * p.cluster_headway_m
            ids.append(f"{name}{k}")
            x0.append(np.concatenate([entry + s * u, p.speed_mps * u]))
            dirs.append(u)
            leader.append(a * m + k - 1 if k else -1)
            start.append(entry)
    return _Fleet(np.array(ids, dtype=object), np.array(x0), np.array(dirs),
                  np.array(leader), np.array(start), p.cluster_headway_m)


def initial_features(params: CrossroadParams, seed: int) -> np.ndarray:
    """Initial feature states (Nf, 4), laid out as ``params.feature_layout`` says (class docstring).

    "sidewalks": uniform on the eight sidewalk half-lines inside the disc, speed vf along
    the sidewalk, either way; "disc": uniform in the disc, speed vf with uniform heading.
    """
    rng = _stream(seed, _FEATURE_INIT)
    nf = params.n_features
    c = np.asarray(params.centre, dtype=float)
    if params.feature_layout == "disc":
        r = params.feature_disc_radius_m * np.sqrt(rng.random(nf))
        phi = rng.uniform(0.0, 2.0 * np.pi, nf)
        psi = rng.uniform(0.0, 2.0 * np.pi, nf)
        xy = c + np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)
        v = params.feature_speed_mps * np.stack([np.cos(psi), np.sin(psi)], axis=1)
        return np.hstack([xy, v])
    w = params.sidewalk_offset_m
    s_max = math.sqrt(params.feature_disc_radius_m ** 2 - w * w)  # where the sidewalk leaves the disc
    arm = rng.integers(0, len(_ARM_DIRS), nf)
    side = rng.choice(np.array([-1.0, 1.0]), nf)
    s = rng.uniform(w, s_max, nf)  # from the junction corner (s = w) outwards
    way = rng.choice(np.array([-1.0, 1.0]), nf)
    u = np.asarray(_ARM_DIRS, dtype=float)[arm]
    normal = np.stack([u[:, 1], -u[:, 0]], axis=1)
    xy = c + s[:, None] * u + (side * w)[:, None] * normal
    v = (params.feature_speed_mps * way)[:, None] * u
    return np.hstack([xy, v])


def ring_labels(distance: np.ndarray, ring_m: float) -> np.ndarray:
    """Distance-ring label of each distance, e.g. "25-50" (metres)."""
    lo = np.floor(np.asarray(distance, dtype=float) / ring_m) * ring_m
    return np.array([f"{a:g}-{a + ring_m:g}" for a in lo], dtype=object)


def crossroad_frames(params: CrossroadParams, seed: int) -> Iterator[Frame]:
    """Frames of the crossroad scenario (Sec. V-B); vehicles leave past the far edge."""
    fleet = _crossroad_fleet(params)
    feats = initial_features(params, seed)
    world = _World(fleet, feats, params.feature_speed_mps / 100.0, params, seed)
    c = np.asarray(params.centre, dtype=float)

    def present(x: np.ndarray) -> np.ndarray:
        s = np.einsum("ij,ij->i", x[:, :2] - fleet.start, fleet.lane_dir)
        return (s >= 0.0) & (s <= params.path_length_m)

    def area(x: np.ndarray) -> np.ndarray:
        return ring_labels(np.hypot(x[:, 0] - c[0], x[:, 1] - c[1]), params.area_ring_m)

    return _frames(world, params.max_steps, present, area, seed,
                   np.array([f"F{i}" for i in range(params.n_features)], dtype=object))


def scenario_frames(params: SingleRoadParams | CrossroadParams, seed: int) -> Iterator[Frame]:
    """Frames of the scenario described by ``params`` (dispatch on its type)."""
    if isinstance(params, SingleRoadParams):
        return single_road_frames(params, seed)
    if isinstance(params, CrossroadParams):
        return crossroad_frames(params, seed)
    raise TypeError(f"scenario_frames: unknown scenario parameters {type(params).__name__}")


def distance_to_centre(frame: Frame, centre: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Distance (N,) of each vehicle's true position to the junction centre (scoring only: reads truth)."""
    if frame.truth is None:
        raise ValueError("distance_to_centre needs a frame with truth (it scores, it does not estimate)")
    xy = frame.truth.x_true[:, :2]
    return np.hypot(xy[:, 0] - centre[0], xy[:, 1] - centre[1])
