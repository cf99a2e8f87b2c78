"""Realistic on-board perception: field of view, missed detections, range-dependent
noise, clutter and occlusion, turning true states into the V2F rows of a frame.

Opt-in through the ``[perception]`` config table; without it the coupler synthesises the paper's
idealised V2F (every feature within Rs, P_D = 1, no clutter) exactly as before.

Model, per step, for every vehicle i and every sensor s of :class:`PerceptionParams` ``sensors``:

* Mount point: the sensor sits ``mount_x_m`` metres along vehicle i's heading from the vehicle's
  reported position (``[scenario] reference_point``: SUMO's, the centre of the front bumper, where
  ``mount_x_m = 0``, the default, is the bumper itself; or the vehicle's centre, where a bumper sensor
  sits at half the length; negative values lie toward the rear). Range and field of view are measured from the mount point; the
  measurement is still reported relative to the vehicle position (model (4), z = x_F - x_V + n:
  the mounting offset is a known calibration).
* Field of view: a circular sector of radius ``range_m`` and opening ``fov_deg`` centred on the
  heading turned by ``yaw_deg`` (counter-clockwise, degrees), closed at its edges.
* Occlusion: a feature inside the field of view is not seen when the sight line (the segment from
  the mount point to the feature) intersects, edges included, the footprint of another SUMO vehicle
  (a length x width rectangle behind the front bumper, along the heading: every vehicle on the road,
  connected or not) or a building polygon (``buildings.geojson`` of the net folder). The observing
  vehicle never occludes its own sight lines, nor does a target that is itself a vehicle. Vehicles:
  the footprints listed in x buckets of their bounding boxes plus exact segment/rectangle tests (skipped
  for a footprint that lies wholly to one side of the line); buildings: a shapely 2 STRtree
  ``query(..., predicate="intersects")`` over the sight lines that meet a building's bounding box, all
  at once (the geometry: :mod:`couplers.sensing.occlusion`).
* Detection: a visible feature at distance d is detected with probability
  P_D(d) = pd_near + (pd_far - pd_near) d / range_m, linear in d from ``pd_near`` at 0 m to
  ``pd_far`` at the range. Eclipse MOSAIC's perception error models decide detection by distance
  the same way (``errormodels/DistanceModifier.java`` in eclipse/mosaic: an object is dropped when
  (d / viewing range)^2 >= u - offset, u ~ U(0, 1), i.e. P_D falls linearly in d^2 to 0 at the
  viewing range); here the profile is linear in d between two configurable end points.
  One uniform draw per (vehicle, sensor, feature in the field of view, step), from the detection
  stream, taken before occlusion so that switching occlusion on or off (or changing P_D) keeps the
  other draws (common random numbers across a sweep).
* Noise: sigma_p(d) = sigma_p_m (1 + sigma_growth d / range_m) per position axis (isotropic), and a
  constant sigma_v_mps per velocity axis; ``v2f_R`` holds, per row, the covariance actually used.
  One (4,) normal draw per candidate of the field of view, from the noise stream.
* Several sensors seeing one feature: merged. A vehicle reports one row per detected feature (its
  fused object list), the detection of the detecting sensor with the smallest sigma_p at that
  distance (ties: the sensor listed first). This keeps model (13)'s point-target assumption (at
  most one measurement per feature per vehicle and scan); the effective detection probability of
  a feature seen by several sensors is 1 - prod(1 - P_D,s).
* Clutter: per (vehicle, sensor, step) a Poisson(``clutter_per_scan``) number of false detections,
  uniform over the field-of-view sector's area (r = range sqrt(u), bearing uniform over the
  opening), looking like a static object (relative velocity -v_vehicle + noise), with the noise of
  their range; not subject to occlusion (they are the sensor's own false alarms); truth index -1.
  Counts, positions and their noise come from the clutter stream.

Random streams: one ``numpy.random.Generator`` per effect ("detect", "noise", "clutter",
"shuffle"), each seeded by ``SeedSequence([seed, 0x9E5, crc32(effect name)])``: independent of the
idealised sensors' streams (couplers.sensing.sensors.SensorNoise), so GNSS, prior and inertial noise are the
same draws with or without ``[perception]``, and adding an effect does not shift the others. :func:`perceive`
draws them inside its kernels (:mod:`couplers.sensing.streams`: numpy's numbers, in numpy's order).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import shapely

from coloc.core.detection import DetectionModel
from coloc.core.models import gnss_cov
from couplers.errors import InputError
from couplers.net.buildings import Buildings
from couplers.net.zones import CellGrid
from couplers.sensing import streams
from couplers.sensing.occlusion import (  # noqa: F401 (unit_heading: also this module's, as before)
    OccluderIndex,
    _segments_occluded_by_buildings,
    _segments_occluded_by_vehicles,
    unit_heading,
)
from couplers.sensing.perception_kernels import (  # noqa: F401 (CLASS_*: also this module's, as before)
    CLASS_PEDESTRIAN,
    CLASS_STATIC,
    _clutter_geometry,
    _clutter_rows,
    _clutter_xy,
    _detected_rows,
    _distinct_lines,
    _fov_select,
    _merge_detections,
    _pair_counts,
    _rows_stage,
    _sense_stage,
    _shuffled_rows,
    _sight_lines,
)
from couplers.sensing.rows import shuffle_within_owner
from couplers.sensing.streams import StreamHandles

PERCEPTION_STREAM_TAG = 0x9E5

def effect_rng(seed: int, tag: int, effect: str) -> np.random.Generator:
    """A generator of its own for one effect, keyed by the effect's name (stable across versions)."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(tag), zlib.crc32(effect.encode())]))


def _finite(value: float) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class SensorSpec:
    """One on-board sensor. Defaults: a front radar (see :data:`DEFAULT_SENSORS` for the sources)."""

    name: str = "front_radar"
    fov_deg: float = 120.0  # opening of the field of view, (0, 360]
    range_m: float = 80.0
    yaw_deg: float = 0.0  # boresight relative to the heading, counter-clockwise
    mount_x_m: float = 0.0  # along the heading from the reference point (front bumper or centre; negative: rearward)
    pd_near: float = 0.95  # detection probability at 0 m
    pd_far: float = 0.7  # detection probability at range_m
    clutter_per_scan: float = 1.0  # mean false detections per scan (Poisson)
    sigma_p_m: float = 0.1  # position noise per axis at 0 m
    sigma_growth: float = 3.0  # sigma_p(range) = sigma_p_m (1 + sigma_growth)
    sigma_v_mps: float = 0.1  # velocity noise per axis
    # Noise in the sensor's own coordinates (``[perception] detections = "range_bearing"``,
    # couplers.sensing.sensor_frame, where the defaults are sourced: Continental ARS 408-21, near range).
    sigma_r_m: float = 0.1  # range
    sigma_b_deg: float = 0.3  # bearing (azimuth)
    sigma_rdot_mps: float = 0.028  # range rate (radial velocity), 0.1 km/h

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(None, "name", "must be a non-empty string")
        if not (_finite(self.fov_deg) and 0.0 < self.fov_deg <= 360.0):
            raise InputError(None, "fov_deg", f"must be in (0, 360], got {self.fov_deg!r}")
        if not (_finite(self.range_m) and self.range_m > 0):
            raise InputError(None, "range_m", f"must be positive and finite, got {self.range_m!r}")
        for key in ("yaw_deg", "mount_x_m"):
            if not _finite(getattr(self, key)):
                raise InputError(None, key, "must be a finite number")
        for key in ("pd_near", "pd_far"):
            val = getattr(self, key)
            if not (_finite(val) and 0.0 <= val <= 1.0):
                raise InputError(None, key, f"must be a probability in [0, 1], got {val!r}")
        if not (_finite(self.clutter_per_scan) and self.clutter_per_scan >= 0):
            raise InputError(None, "clutter_per_scan", f"must be >= 0 and finite, got {self.clutter_per_scan!r}")
        for key in ("sigma_p_m", "sigma_v_mps", "sigma_r_m", "sigma_b_deg", "sigma_rdot_mps"):
            val = getattr(self, key)
            if not (_finite(val) and val > 0):
                raise InputError(None, key, f"must be positive and finite, got {val!r}")
        if not (_finite(self.sigma_growth) and self.sigma_growth >= 0):
            raise InputError(None, "sigma_growth", f"must be >= 0 and finite, got {self.sigma_growth!r}")


#: Default sensor set.
#: * front radar, 120 deg / 80 m: wider and longer than the near-range beam of an automotive long-range
#:   radar (Continental ARS 408-21 datasheet: near range to 70 m within +-45 deg and only to 20 m at
#:   +-60 deg, far range +-9 deg to 250 m; experiments/arterial_tlr_realistic.toml uses 90 deg / 70 m);
#:   kept as the default so that configs without sensor tables keep their results. Accuracy near
#:   range 0.1 m in distance and ~0.3 deg at boresight, i.e. ~0.4 m across the beam at 70-80 m, hence
#:   sigma_p 0.1 m at 0 m growing 4x to the range (sigma_growth 3);
#: * surround, 360 deg / 30 m: short-range corner sensors seen as one surround field (assumption),
#:   same noise model.
#: pd_near / pd_far 0.95 / 0.7 (assumption, inside the sensing study's range P_D in {1, 0.9, 0.7});
#: profile linear in distance as MOSAIC's DistanceModifier; clutter 1 per scan (the sensing study's
#: centre value); sigma_p 0.1 m / sigma_v 0.1 m/s at 0 m: the paper's V2F noise (Sec. VI).
DEFAULT_SENSORS = (
    SensorSpec(name="front_radar", fov_deg=120.0, range_m=80.0),
    SensorSpec(name="surround", fov_deg=360.0, range_m=30.0),
)


DETECTION_KINDS = ("net_xy", "range_bearing")


@dataclass(frozen=True)
class PerceptionParams:
    """The ``[perception]`` table: the sensors of every vehicle and which occluders count."""

    sensors: tuple[SensorSpec, ...] = DEFAULT_SENSORS
    occlusion_vehicles: bool = True
    occlusion_buildings: bool = True  # uses the net folder's buildings.geojson when it has one
    # Other road users, persistent false alarms and the classifier's error (couplers.sensing.road_users,
    # where each is described; all off by default).
    road_users: bool = False
    persistent_clutter_per_km: float = 0.0
    persistent_clutter_pd: float = 0.9  # assumption: a guard rail / pole / parked car is a strong reflector
    class_error: float = 0.0  # idealisation: a perfect object classifier
    # What a detection reports: "net_xy", the relative state in the net frame (model (4) as the papers);
    # "range_bearing", range, bearing and range rate in the sensor's frame (couplers.sensing.sensor_frame).
    detections: str = "net_xy"
    # With "range_bearing": the range rate is the sensor's own, relative to its mount point moving with the
    # vehicle's velocity plus yaw rate x lever arm (mount_x_m ahead of the reference point), and estimators
    # convert it back with their own yaw rate (couplers.sensing.sensor_frame, coloc.core.detections). False:
    # relative to the vehicle's velocity (the lever arm's rotation neglected), as before.
    lever_arm_range_rate: bool = False

    def __post_init__(self):
        if self.detections not in DETECTION_KINDS:
            raise InputError(None, "detections", f"must be one of {', '.join(map(repr, DETECTION_KINDS))}, "
                                                 f"got {self.detections!r}")
        if self.lever_arm_range_rate is not False and self.lever_arm_range_rate is not True:
            raise InputError(None, "lever_arm_range_rate", f"must be true or false, got {self.lever_arm_range_rate!r}")
        if self.lever_arm_range_rate and self.detections != "range_bearing":
            raise InputError(None, "lever_arm_range_rate", "needs detections = \"range_bearing\" (a range rate in "
                                                           f"the sensor's frame), got detections = {self.detections!r}")
        if not isinstance(self.sensors, tuple) or not self.sensors:
            raise InputError(None, "sensors", "at least one sensor is needed")
        if not (_finite(self.persistent_clutter_per_km) and self.persistent_clutter_per_km >= 0):
            raise InputError(None, "persistent_clutter_per_km",
                             f"must be >= 0 and finite, got {self.persistent_clutter_per_km!r}")
        for key in ("persistent_clutter_pd", "class_error"):
            val = getattr(self, key)
            if not (_finite(val) and 0.0 <= val <= 1.0):
                raise InputError(None, key, f"must be a probability in [0, 1], got {val!r}")
        names = [s.name for s in self.sensors]
        if len(set(names)) != len(names):
            raise InputError(None, "sensors", f"sensor names must be unique, got {names}")

    @property
    def extended(self) -> bool:
        """Other road users, persistent clutter or a classifier error are on (couplers.sensing.road_users)."""
        return self.road_users or self.persistent_clutter_per_km > 0 or self.class_error > 0

    @cached_property
    def arrays(self) -> dict[str, np.ndarray]:
        """Per-sensor parameters as arrays (S,), for vectorised use over all sensors."""
        keys = ("fov_deg", "range_m", "yaw_deg", "mount_x_m", "pd_near", "pd_far", "clutter_per_scan",
                "sigma_p_m", "sigma_growth", "sigma_v_mps")
        return {k: np.array([getattr(s, k) for s in self.sensors], dtype=float) for k in keys}

    @cached_property
    def kernel_consts(self) -> dict:
        """Per-step constants of :func:`perceive`, computed once: the fields of view's cos(opening / 2) and
        full-circle flags, the mount groups (:func:`_mount_groups`), which sensors look along the heading
        (yaw 0: their boresight is the heading's unit vector) and the common clutter rate (None if the
        sensors' rates differ)."""
        a = self.arrays
        rates = a["clutter_per_scan"]
        return dict(
            cos_half=np.array([math.cos(math.radians(s.fov_deg) / 2.0) for s in self.sensors]),
            full=np.array([s.fov_deg >= 360.0 for s in self.sensors]),
            groups=_mount_groups(a["mount_x_m"]),
            along_heading=tuple(s.yaw_deg == 0.0 for s in self.sensors),
            along_heading_array=np.array([s.yaw_deg == 0.0 for s in self.sensors]),
            clutter_rate=float(rates[0]) if np.all(rates == rates[0]) else None,
        )

    @property
    def max_reach_m(self) -> float:
        """Distance from the vehicle position beyond which no sensor sees anything."""
        return max(s.range_m + abs(s.mount_x_m) for s in self.sensors)


def detection_model(params: PerceptionParams, heading_min_speed: float, visibility: float = 1.0) -> DetectionModel:
    """The sensors as the estimators' :class:`coloc.core.detection.DetectionModel` (datasheet
    values only: field of view, range, mounting, detection profile; ``visibility``: the estimator's
    expected share of in-view tracks not occluded, ``[lc] visibility``)."""
    a = params.arrays
    return DetectionModel(*(tuple(float(v) for v in a[k]) for k in
                            ("fov_deg", "range_m", "yaw_deg", "mount_x_m", "pd_near", "pd_far")),
                          heading_min_speed=heading_min_speed, visibility=visibility)


class PerceptionNoise:
    """The perception's own streams, one per effect (see the module docstring)."""

    STREAMS = ("detect", "noise", "clutter", "shuffle")

    def __init__(self, seed: int):
        for name in self.STREAMS:
            setattr(self, name, effect_rng(seed, PERCEPTION_STREAM_TAG, name))
        self.handles = StreamHandles(self, self.STREAMS)  # the same streams drawn in perceive's kernels


@dataclass(frozen=True)
class Detections:
    """The V2F rows of one step with realistic perception (coupler side; the frame takes the first
    three arrays and ``feature``; ``sensor`` and ``klass`` are what a frame field would carry)."""

    z: np.ndarray  # (O, 4) relative feature measurement
    owner: np.ndarray  # (O,) int, row of the measuring vehicle, rows shuffled within a vehicle
    R: np.ndarray  # (O, 4, 4) covariance actually used
    feature: np.ndarray  # (O,) int, true feature index, -1 for clutter (truth)
    sensor: np.ndarray  # (O,) int, index into PerceptionParams.sensors
    klass: np.ndarray  # (O,) int8, CLASS_STATIC / CLASS_PEDESTRIAN
    # Counts of this step (truth-side diagnostics): (vehicle, feature) pairs inside at least one
    # field of view, of those hidden from every sensor by occlusion, visible but missed, detected.
    stats: dict = field(default_factory=dict)
    # (O,) int8, what each row truly is (couplers.sensing.road_users KIND_*); None: not computed.
    kind: np.ndarray | None = None


# --- geometry -------------------------------------------------------------------------------------


def sensor_origins(xy: np.ndarray, heading: np.ndarray, spec: SensorSpec) -> np.ndarray:
    """(N, 2) mount points of ``spec`` on vehicles reported at ``xy`` (their reference point)."""
    return np.asarray(xy, dtype=float) + spec.mount_x_m * unit_heading(heading)


def _fov_all(origins: np.ndarray, heading: np.ndarray, owner: np.ndarray, target: np.ndarray,
             sensors: tuple[SensorSpec, ...]):
    """:func:`fov candidates <fov_candidates>` of every sensor at once (``origins`` (S, N, 2)): (rows, distances,
    sensors)."""
    heading = np.asarray(heading, dtype=float)
    boresight = np.stack([unit_heading(heading + math.radians(spec.yaw_deg)) for spec in sensors])
    return _fov_select(np.ascontiguousarray(origins, dtype=np.float64), boresight.reshape(len(sensors), -1, 2),
                       np.asarray(owner, dtype=np.int64), np.ascontiguousarray(target, dtype=np.float64),
                       np.array([spec.range_m for spec in sensors], dtype=float),
                       np.array([math.cos(math.radians(spec.fov_deg) / 2.0) for spec in sensors]),
                       np.array([spec.fov_deg >= 360.0 for spec in sensors]))


def sensor_boresights(params, heading: np.ndarray, n: int) -> np.ndarray:
    """(sensors, n, 2): each sensor's boresight per vehicle, the heading turned by its yaw; the rows of the sensors
    along the heading are left for the caller to take the direction of travel (not written)."""
    boresight = np.empty((len(params.sensors), n, 2))
    for s, spec in enumerate(params.sensors):
        if not params.kernel_consts["along_heading"][s]:
            boresight[s] = unit_heading(heading + math.radians(spec.yaw_deg))
    return boresight


def _fov_params(origins: np.ndarray, heading: np.ndarray, direction: np.ndarray, owner: np.ndarray,
                target: np.ndarray, params: "PerceptionParams"):
    """:func:`_fov_all` with the constants of ``params.kernel_consts``, and the boresight of a sensor with
    yaw 0 taken from ``direction`` (the heading's unit vector, computed once a step) instead of the unit
    vector of heading + 0.0: the two differ at most in the sign of a zero, which :func:`_fov_select`'s
    comparison does not see."""
    k = params.kernel_consts
    boresight = np.empty((len(params.sensors),) + direction.shape)
    for s, spec in enumerate(params.sensors):
        boresight[s] = direction if k["along_heading"][s] else unit_heading(heading + math.radians(spec.yaw_deg))
    return _fov_select(origins, boresight, owner, target, params.arrays["range_m"], k["cos_half"], k["full"])


def fov_candidates(origin: np.ndarray, heading: np.ndarray, owner: np.ndarray, target: np.ndarray, spec: SensorSpec):
    """Rows k whose ``target[k]`` (M, 2) is inside the field of view of ``spec`` mounted at ``origin``
    (N, 2) on vehicle ``owner[k]`` with ``heading`` (N,). Returns (rows (C,), distances (C,))."""
    rows, dist, _ = _fov_all(np.asarray(origin, dtype=float)[None], heading, owner, target, (spec,))
    return rows, dist


def detection_probability(dist: np.ndarray, spec) -> np.ndarray:
    """P_D(d) = pd_near + (pd_far - pd_near) d / range (linear in distance, clipped to the range).
    ``spec``: a SensorSpec, or a mapping of per-row parameter arrays (``PerceptionParams.arrays``
    indexed by each row's sensor)."""
    g = spec.__getitem__ if isinstance(spec, dict) else spec.__getattribute__
    frac = np.clip(np.asarray(dist, dtype=float) / g("range_m"), 0.0, 1.0)
    return g("pd_near") + (g("pd_far") - g("pd_near")) * frac


def range_sigma(dist: np.ndarray, spec) -> np.ndarray:
    """Position noise per axis at distance d: sigma_p_m (1 + sigma_growth d / range) (``spec`` as above)."""
    g = spec.__getitem__ if isinstance(spec, dict) else spec.__getattribute__
    frac = np.clip(np.asarray(dist, dtype=float) / g("range_m"), 0.0, 1.0)
    return g("sigma_p_m") * (1.0 + g("sigma_growth") * frac)


def clutter_points(origins: np.ndarray, heading: np.ndarray, params: PerceptionParams, rng: np.random.Generator):
    """False detections of every sensor on every vehicle: Poisson(clutter_per_scan) per (vehicle,
    sensor), uniform over the field-of-view sector's area. ``origins`` (S, N, 2): the sensors' mount
    points. Returns (vehicle row (C,), sensor (C,), point (C, 2), distance to the mount point (C,))."""
    owner, sensor, r, ang = _clutter_polar(origins.shape[1], heading, params, rng)
    return owner, sensor, _clutter_xy(origins, owner, sensor, r, unit_heading(ang)), r


def _clutter_polar(n: int, heading: np.ndarray, params: PerceptionParams, rng: np.random.Generator):
    """The clutter draws: (vehicle row, sensor, distance, bearing) of every false detection."""
    a = params.arrays
    n_sensors = len(params.sensors)
    rate = params.kernel_consts["clutter_rate"]
    if rate is not None:  # one rate for all: numpy's scalar path, the same draws in the same order (tested)
        counts = rng.poisson(rate, size=(n, n_sensors)).ravel()
    else:
        counts = rng.poisson(np.broadcast_to(a["clutter_per_scan"], (n, n_sensors))).ravel()
    c = int(counts.sum())
    u_r = rng.random(c)  # distance: uniform in area, P(r' <= r) = (r / R)^2
    u_a = rng.random(c)  # bearing: uniform over the opening
    return _clutter_geometry(counts, n_sensors, u_r, u_a, np.asarray(heading, dtype=np.float64), a["range_m"],
                             a["yaw_deg"], a["fov_deg"])


# --- one step -------------------------------------------------------------------------------------


def _mount_groups(mount_x_m: np.ndarray) -> np.ndarray:
    """(S,) the first sensor with the same mount point as each sensor."""
    return np.array([int(np.flatnonzero(mount_x_m == m)[0]) for m in mount_x_m], dtype=np.int64)


def perceive(
    *,
    x_true: np.ndarray,
    heading: np.ndarray,
    features_true: np.ndarray,
    pair_owner: np.ndarray,
    pair_feature: np.ndarray,
    params: PerceptionParams,
    noise: PerceptionNoise,
    occluder_corners: np.ndarray | None = None,
    observer_occluder: np.ndarray | None = None,
    buildings: Buildings | None = None,
    feature_class: np.ndarray | None = None,
    direction: np.ndarray | None = None,
    reference: bool = False,
    boresight: np.ndarray | None = None,
) -> Detections:
    """The V2F rows of one step.

    ``pair_owner`` / ``pair_feature``: candidate (vehicle, feature) pairs covering every pair within
    ``params.max_reach_m`` (couplers.sensing.sensors.features_in_range). ``occluder_corners`` (K, 4, 2):
    footprints of every vehicle on the road; ``observer_occluder`` (N,): the footprint row of each
    measuring vehicle (-1 if it has none). ``feature_class`` (K,): the class of each feature
    (None: all static); a detection carries its feature's class, clutter ``CLASS_STATIC``. ``direction``
    (N, 2): ``unit_heading(heading)`` when the caller has it (the SUMO coupler: ``VehicleStates.direction``);
    ``boresight``: :func:`sensor_boresights` of ``heading`` when the caller has it.

    Two numba stages around numpy's trigonometry and shapely's building query (the kernels of
    :func:`perceive_reference`, same operations in the same order, the same draws from each stream in the same
    order, drawn inside the kernels through :mod:`couplers.sensing.streams`): the clutter and candidate draws,
    field of view, clutter geometry, sight lines and their occlusion (:func:`_sense_stage`); detections,
    merge, rows and the shuffle within each vehicle (:func:`_rows_stage`). Where numba's draws do not equal
    numpy's (``streams.available()`` False), or with ``reference``, :func:`perceive_reference` runs instead.
    """
    n = x_true.shape[0]
    heading = np.asarray(heading, dtype=np.float64)
    if observer_occluder is None:
        observer_occluder = np.full(n, -1, dtype=np.int64)
    if direction is None:
        direction = unit_heading(heading)
    if reference or not streams.available():
        return _perceive_stages(x_true, heading, features_true, pair_owner, pair_feature, params, noise,
                                occluder_corners, observer_occluder, buildings, feature_class, direction)
    a, k = params.arrays, params.kernel_consts
    if boresight is None:
        boresight = sensor_boresights(params, heading, n)
    xf = np.ascontiguousarray(x_true, dtype=np.float64)
    ft = np.ascontiguousarray(features_true, dtype=np.float64)
    pair_owner = np.asarray(pair_owner, dtype=np.int64)
    pair_feature = np.asarray(pair_feature, dtype=np.int64)

    use_vehicles = bool(params.occlusion_vehicles and occluder_corners is not None and len(occluder_corners)
                        and pair_owner.size)
    corners = (np.ascontiguousarray(occluder_corners, dtype=np.float64).reshape(-1, 4, 2) if use_vehicles
               else _NO_CORNERS)
    use_buildings = bool(params.occlusion_buildings and buildings is not None and len(buildings))
    if use_buildings:
        g, bb = buildings.cells, buildings.boxes
        grid = (g.x0, g.y0, g.cell, g.values, bb.start, bb.ids, bb.boxes, bb.margin)
    else:
        grid = _NO_BUILDINGS
    h = noise.handles
    (origins, pair, dist, sensor, c_owner, c_sensor, c_dist, c_ang, cw, u, w, line_of, clear, seg,
     need) = _sense_stage(
        h["clutter"], h["detect"], h["noise"], a["clutter_per_scan"], xf, np.ascontiguousarray(direction,
                                                                                                dtype=np.float64),
        a["mount_x_m"], boresight, k["along_heading_array"], ft, pair_owner, pair_feature, a["range_m"],
        k["cos_half"], k["full"], heading, a["yaw_deg"], a["fov_deg"], k["groups"],
        np.asarray(observer_occluder, dtype=np.int64), use_vehicles, corners, use_buildings, *grid)
    if need.size:  # the sight lines that meet a building's box: shapely's exact test
        lines = shapely.linestrings(seg[need].reshape(-1, 2, 2))
        clear[need[buildings.tree.query(lines, predicate="intersects")[0]]] = False

    # Detection by P_D(d), merge, the detection and clutter rows (numpy's cos / sin of the clutter bearings),
    # the shuffle within each vehicle.
    classed = feature_class is not None
    z, owner, R, feature, sensor_rows, klass, n_fov, n_vis, n_det = _rows_stage(
        h["shuffle"], pair, dist, sensor, pair_owner.size, clear, line_of, u, w, pair_owner, pair_feature, ft, xf,
        a["range_m"], a["pd_near"], a["pd_far"], a["sigma_p_m"], a["sigma_growth"], a["sigma_v_mps"], origins,
        c_owner, c_sensor, c_dist, np.cos(c_ang), np.sin(c_ang), cw,
        np.asarray(feature_class, dtype=np.int8) if classed else _NO_CLASSES, classed)
    c = c_owner.size
    stats = dict(in_fov=n_fov, occluded=n_fov - n_vis, missed=n_vis - n_det, detected=n_det, clutter=c)
    return Detections(z=z, owner=owner, R=R, feature=feature, sensor=sensor_rows, klass=klass, stats=stats)


_NO_CORNERS = np.empty((0, 4, 2))
_NO_CLASSES = np.empty(0, dtype=np.int8)
_NO_BUILDINGS = (0.0, 0.0, 1.0, np.zeros((1, 1), dtype=np.bool_), np.zeros(2, dtype=np.int64),
                 np.empty(0, dtype=np.int64), np.empty((0, 4)), 0.0)


def perceive_reference(**inputs) -> Detections:
    """:func:`perceive` as a sequence of separate kernels with numpy between them (the reference of its
    fused stages: ``tests/couplers/test_frame_kernels.py`` compares the two; arguments: see :func:`perceive`)."""
    return perceive(**inputs, reference=True)


def _perceive_stages(x_true, heading, features_true, pair_owner, pair_feature, params, noise, occluder_corners,
                     observer_occluder, buildings, feature_class, direction) -> Detections:
    """The body of :func:`perceive_reference` (``heading``, ``observer_occluder`` and ``direction`` as
    :func:`perceive` completed them)."""
    n = x_true.shape[0]
    xy = x_true[:, :2]
    a = params.arrays
    origins = xy[None, :, :] + a["mount_x_m"][:, None, None] * direction[None, :, :]  # (S, N, 2)

    # Candidates: (sensor, pair) with the feature inside the sensor's field of view, sensor after sensor.
    target = features_true[pair_feature, :2]
    pair, dist, sensor = _fov_params(origins, heading, direction, np.asarray(pair_owner, dtype=np.int64),
                                     np.ascontiguousarray(target, dtype=np.float64), params)
    # One draw per candidate, before occlusion (common random numbers across P_D / occlusion settings).
    u = noise.detect.random(pair.size)
    w = noise.noise.standard_normal((pair.size, 4))

    # Occlusion of each distinct sight line once: sensors on one mount point share their sight lines.
    owner_c = pair_owner[pair]
    line, line_of = _distinct_lines(pair, sensor, params.kernel_consts["groups"], pair_owner.size)
    clear = np.ones(line.size, dtype=bool)
    seg = _sight_lines(origins, sensor[line], owner_c[line], target[pair[line]])
    if params.occlusion_vehicles and occluder_corners is not None and len(occluder_corners) and pair.size:
        clear &= ~_segments_occluded_by_vehicles(seg, OccluderIndex.build(occluder_corners),
                                                 observer_occluder[owner_c[line]])
    if params.occlusion_buildings and buildings is not None and len(buildings) and clear.any():
        clear[clear] &= ~_segments_occluded_by_buildings(seg[clear], buildings)
    visible = clear[line_of]
    # Detection by P_D(d); merge: one row per detected pair, from the detecting sensor with the smallest sigma_p.
    detected = np.empty(pair.size, dtype=bool)
    sig, first = _merge_detections(pair, dist, sensor, detected, pair_owner.size, a["range_m"], a["pd_near"],
                                   a["pd_far"], a["sigma_p_m"], a["sigma_growth"], u, visible)
    t_owner, t_feat, t_sensor, t_sig, t_sv, t_z = _detected_rows(
        first, pair, sensor, pair_owner, pair_feature, np.ascontiguousarray(features_true, dtype=np.float64),
        np.ascontiguousarray(x_true, dtype=np.float64), w, sig, a["sigma_v_mps"])

    # Clutter of every sensor on every vehicle (own stream; never occluded): static objects.
    c_owner, c_sensor, c_dist, c_ang = _clutter_polar(n, heading, params, noise.clutter)
    cw = noise.clutter.standard_normal((c_owner.size, 4))
    c_z, c_sig, c_sv = _clutter_rows(origins, c_owner, c_sensor, c_dist, np.cos(c_ang), np.sin(c_ang),
                                     np.ascontiguousarray(x_true, dtype=np.float64), cw, a["range_m"],
                                     a["sigma_p_m"], a["sigma_growth"], a["sigma_v_mps"])

    # Detections then clutter, shuffled within each vehicle (one uniform key per row); R, stats in kernels.
    perm = shuffle_within_owner(np.concatenate([t_owner, c_owner]), noise.shuffle)
    t_klass = (np.zeros(t_feat.size, dtype=np.int8) if feature_class is None
               else np.asarray(feature_class, dtype=np.int8)[t_feat])
    z, owner, R, feature, sensor_rows, klass = _shuffled_rows(perm, t_z, c_z, t_owner, c_owner, t_feat, t_sensor,
                                                              c_sensor, t_sig, c_sig, t_sv, c_sv, t_klass)
    n_fov, n_vis = _pair_counts(pair, visible, pair_owner.size)
    stats = dict(in_fov=n_fov, occluded=n_fov - n_vis, missed=n_vis - int(first.size), detected=int(first.size),
                 clutter=int(c_owner.size))
    return Detections(z=z, owner=owner, R=R, feature=feature, sensor=sensor_rows, klass=klass, stats=stats)


