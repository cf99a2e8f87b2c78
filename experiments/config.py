"""Experiment configs: TOML, validated on load, saved fully resolved next to results.

Every table maps onto a frozen dataclass; unknown keys and wrong types are
errors naming the file and the dotted field. A config may inherit another with
a top-level ``extends = "other.toml"`` (:mod:`experiments.config_extends`: tables
merged, arrays and scalars replaced); the saved config is the merged one.

Scenario kinds (``[scenario] kind``):

* ``"sumo"``: SUMO traffic on a net folder (``scenario.net_dir``).
* ``"single_road"`` / ``"crossroad"``: the controlled scenarios of Brambilla
  Sec. V-A / V-B (:mod:`couplers.scenarios`), parameterised by the table of the
  same name, whose keys are the fields of ``SingleRoadParams`` /
  ``CrossroadParams``. These scenarios carry their own truth model and sensors,
  so the estimators must use the same model (1):

  - ``[sensors]`` is taken from the scenario table (same field names); a
    ``[sensors]`` value that differs from it is refused (set it in the scenario
    table instead);
  - ``[motion] sigma_along / sigma_cross`` and ``[scenario] step_s`` are taken
    from the scenario table when not given; given values that differ are
    refused (an estimator with another driving noise than the truth is not
    what the paper evaluates);
  - ``[icp] feature_sigma_par`` is vf / 100 (the paper's model (2) for moving
    features, Sec. V-B) when the crossroad's features move and the key is not
    given.

  The saved config spells the derived values out with a comment saying where
  they come from. SUMO-only keys (``net_dir``, ``control``, ``ballistic``) are
  refused for these kinds.

``[lc]`` holds the ICP-DA-LC parameters (the fields of
:class:`coloc.methods.icp_da_lc.LcParams`); ``lc.sensing_range_m`` defaults to the V2F
range ``sensors.v2f_range_m`` in force (for a scenario kind, the scenario's).
``[infra]`` (optional, SUMO only) switches on the infrastructure mode:
road-side units at the junctions ``rsu_junctions`` of the net (checked against the net
file), V2I range = radar range ``rsu_range_m``, radar and odometry noise, and the settings
of the methods ``rsu_bp``, ``sme`` and ``fg_topology_new``, which need it. It is not one of
``SECTIONS`` (those are always present and written) but one of ``OPTIONAL_SECTIONS``: a config
without it resolves and runs exactly as before; its keys can be overridden (``infra.KEY``, e.g. by
a sweep) when the config has the table (an override does not create it).
``[pf]`` holds the ICP-DA-PF settings (:class:`coloc.methods.icp_da_pf.PfParams`
without the seed: its generators take ``run.seed``); ICP-DA-PF also uses
``[icp]`` and ``[lc]`` (association, tracks). ``icp_known_da_pf`` is the same
estimator told the true association by the runner (the particle counterpart of
``icp_known_da``), with the same settings.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from coloc.core.models import IMU_HEADINGS, MotionParams
from coloc.inference.params import BUDGET_SPLITS, FEATURE_MESSAGES, PEDESTRIAN_SIGMA_PAR, STOP_RULES
from coloc.methods.icp_da_lc import LcParams
from coloc.methods.coop_fusion import FusionParams
from coloc.methods.gnss_bias import GnssModelParams
from coloc.methods.icp_da_pf import PfParams
from coloc.methods.registry import GNSS, METHODS, runnable_methods
from couplers.errors import InputError, read_toml, seed_problem
from couplers.sensing.gnss_error import GnssErrorParams
from couplers.sensing.inertial import InertialParams
from couplers.sensing.pedestrians import FeaturesParams
from couplers.sensing.perception import PerceptionParams
from couplers.scenarios import STARTS, CrossroadParams, SingleRoadParams
from couplers.traffic.reference_point import REFERENCE_POINTS
from experiments.estimator_sensors import EstimatorSensors
from experiments.occlusion import check_building_occlusion
from couplers.sensing.sensors import SensorParams
from couplers.sensing.v2x import V2xParams
from experiments.config_extends import KEY as EXTENDS
from experiments.config_extends import chain_text, origin_of, resolve_extends
from experiments.ranges import check_ranges_of
from experiments.oracle_world import OracleSection, validate_oracle
from experiments.warmup_start import validate_warmup_start

SCENARIO_KINDS = ("sumo", "single_road", "crossroad")
#: scenario kind -> the table (and dataclass) describing it; "sumo" uses [scenario] net_dir.
SCENARIO_TABLES: dict[str, type] = {"single_road": SingleRoadParams, "crossroad": CrossroadParams}
SUMO_ONLY_KEYS = ("net_dir", "control", "ballistic", "begin_s", "start", "reference_point")


@dataclass(frozen=True)
class RunSection:
    name: str
    seed: int = 1
    duration_s: float = 3600.0
    methods: tuple[str, ...] = (GNSS.name,)


@dataclass(frozen=True)
class ScenarioSection:
    kind: str = "sumo"
    net_dir: str = ""  # relative to the config file, resolved to an absolute path on load
    control: str = "tlr"
    step_s: float = 0.75
    ballistic: bool = True
    # The scenario's begin on its own clock (s, e.g. 25200 = 07:00): the run simulates
    # [begin_s, begin_s + run.duration_s]. Not given: the net folder's [sumo] begin (0 without one).
    begin_s: float | None = None
    # The prior of an entering vehicle (SUMO scenarios; the controlled ones have [single_road] / [crossroad]
    # start): "fast_start" (N(truth, sensors.prior_sigma_p/v), the paper's) or "gnss_fix" (its receiver's fix
    # of that step, error included, with the covariance the receiver reports).
    start: str = "fast_start"
    # The point of a vehicle the world reports (SUMO scenarios; couplers.traffic.reference_point.REFERENCE_POINTS):
    # "front_bumper" (SUMO's position, the paper configs') or "centre" (half the length behind it).
    reference_point: str = "front_bumper"


@dataclass(frozen=True)
class IcpSection:
    """Gaussian ICP (BPA-L with consensus), coloc.inference.params.IcpParams; motion comes from [motion]."""

    consensus_iterations: int = 20
    bpa_max_iterations: int = 10
    stop_pos_m: float = 0.1  # BPA-L stopping rule, Brambilla Sec. V-A
    stop_vel_mps: float = 0.1
    feature_sigma_par: float = 0.01  # m/s per step, model (2) for static features
    # m/s per step, model (2) for pedestrian tracks ([features] pedestrians; coloc.inference.params)
    pedestrian_sigma_par: float = PEDESTRIAN_SIGMA_PAR
    feature_drop_after_s: float = 10.0
    # Velocity prior of a newborn track, N(0, s^2 I) m/s; 0 = uniform (the paper's reset).
    feature_velocity_prior_sigma: float = 0.0
    message_memory_s: float = 10.0  # latest message per vehicle kept apart this long (coloc.inference.feature_store)
    # What a track stores of each vehicle: "own" (own-sensor belief, default) or "bpa" (final (19)).
    feature_message: str = "own"
    # BPA-L stopping rule: "vehicles" (ours) or "vehicles_and_features" (Sec. V-A as written).
    stop_on: str = "vehicles"
    # How the consensus exchanges of a step share a [v2x] round budget: "greedy" or "even".
    budget_split: str = "greedy"


@dataclass(frozen=True)
class PfSection:
    """ICP-DA-PF, coloc.methods.icp_da_pf.PfParams; its generators are seeded with [run] seed."""

    vehicle_particles: int = 1000
    feature_particles: int = 1000
    # "tree" (k-d tree pruned, exact to kernel_rel_tol per entry), "brute" or "fast" (float32 and 16-bit kept
    # kernel matrices, every sum within 1e-3 relative, coloc.kernels.pf_fast)
    kernel: str = "tree"
    kernel_rel_tol: float = 1e-6
    # Memory for the kernel matrices kept through BPA-L's iterations (tree kernel; 0 = none kept).
    kernel_cache_mb: float = 2048.0
    min_association_belief: float = 1e-6
    # Particle double sums as kernel density estimates ("prior", kernel R + h^2 Cov; "shrunk", the same
    # with Liu-West shrunk centres that keep the set's covariance) or bare ("none").
    message_bandwidth: str = "prior"
    recursion: str = "latest_message"  # or "paper", the literal recursion (23)-(24)
    regularize: bool = True  # Liu-West jitter after resampling
    # Driving noise of model (1) for the vehicle particles, m/s^2 (absent: [motion]'s); see PfParams.
    sigma_along: float | None = None
    sigma_cross: float | None = None
    # BPA-L's stopping rule over the whole net ("net", the paper) or per connected component ("component")
    bpa_stop: str = "net"


@dataclass(frozen=True)
class InfraSection:
    """Infrastructure mode (optional ``[infra]`` table): RSUs at junctions of the net, their V2I
    range (= radar range), the radar and odometry noise (couplers.sensing.infra) and the settings of the
    infrastructure methods (coloc.methods.infra.InfraMethodParams). Only for ``scenario.kind = "sumo"``."""

    rsu_junctions: tuple[str, ...] = ()
    rsu_range_m: float = 70.0
    radar_sigma_m: float = 0.5
    radar_pose_offset_sigma_m: float = 5.0
    odom_sigma_m: float = 0.1
    rsu_bp_particles: int = 200
    rsu_bp_detection_prob: float = 0.9
    rsu_bp_feature_drop_s: float = 5.0
    rsu_bp_birth_max_std_m: float = 1.5
    sme_max_vehicles: int = 12
    fg_window_steps: int = 8


@dataclass(frozen=True)
class ReportSection:
    track_area: str = "5"  # analysis area of the along/cross-track figure (paper Fig. 18b)
    # Several areas, one along/cross-track figure each (paper Fig. 18a/b in TLR, Fig. 19 in VSR);
    # empty: (track_area,). Give one of the two keys; the resolved config has both, track_area
    # the first of track_areas.
    track_areas: tuple[str, ...] = ()
    figures: bool = True

    @property
    def track_figure_areas(self) -> tuple[str, ...]:
        """The areas that get an along/cross-track figure."""
        return self.track_areas or (self.track_area,)


@dataclass(frozen=True)
class AnalysisSection:
    """[analysis], optional: how a run is scored (estimates.parquet keeps every row either way)."""
    # Scored statistics (summary.json, the reports' CDFs, the sweeps' tables) leave out the estimates
    # with t < scenario.begin_s + warmup_s: the net fills from empty at the begin (0: score everything).
    warmup_s: float = 0.0
    # What runs during the warm-up: "sensed" (everything, its rows not scored) or "traffic" (SUMO alone;
    # sensing and estimation start after it): experiments.warmup_start, docs/protocol.md "Warm-up".
    warmup_start: str = "sensed"


@dataclass(frozen=True)
class Config:
    path: Path
    run: RunSection
    scenario: ScenarioSection = field(default_factory=ScenarioSection)
    sensors: SensorParams = field(default_factory=SensorParams)
    motion: MotionParams = field(default_factory=MotionParams)
    icp: IcpSection = field(default_factory=IcpSection)
    lc: LcParams = field(default_factory=LcParams)
    pf: PfSection = field(default_factory=PfSection)
    single_road: SingleRoadParams = field(default_factory=SingleRoadParams)
    crossroad: CrossroadParams = field(default_factory=CrossroadParams)
    report: ReportSection = field(default_factory=ReportSection)
    infra: InfraSection | None = None  # [infra], optional; not in SECTIONS (written only when given)
    # [perception] / [gnss_error] (realistic sensing), optional, SUMO only; also handed to the coupler as
    # sensors.perception / sensors.gnss_error (the runner passes [sensors] to the coupler).
    perception: PerceptionParams | None = None
    gnss_error: GnssErrorParams | None = None
    # [v2x] (realistic V2X), optional, SUMO only: penetration, packet delivery, round budget; handed to the
    # coupler as sensors.v2x like the sensing tables.
    v2x: V2xParams | None = None
    # [inertial], optional, SUMO only: a body-frame IMU per vehicle (couplers.sensing.inertial);
    # handed to the coupler as sensors.inertial. Not with [infra] (the infrastructure methods take the
    # net-frame input).
    inertial: InertialParams | None = None
    # [features], optional, SUMO only: SUMO pedestrians as moving features; handed to
    # the coupler as sensors.features.
    features: FeaturesParams | None = None
    # [estimator_sensors], optional: the estimators' own sensor model (experiments.estimator_sensors); not
    # handed to the coupler.
    estimator_sensors: EstimatorSensors | None = None
    # [gnss_model], optional: the integrator's receiver error model for the gnss method (and fg_topology_new, sme)
    # (coloc.methods.gnss_bias); never read from [gnss_error], the world's table.
    gnss_model: GnssModelParams | None = None
    # [fusion], optional: consistent (split covariance intersection) fusion in icp_known_da, icp_da_lc,
    # icp_da_pf and rsu_bp, with [gnss_model]'s receiver model (coloc.methods.coop_fusion, coloc.methods.pf_fusion);
    # in sme, covariance intersection for a re-entering vehicle (coloc.methods.infra).
    fusion: FusionParams | None = None
    # [analysis], optional: the scoring warm-up (experiments.scoring.scored_from).
    analysis: AnalysisSection | None = None
    # [oracle], optional: the oracle's own settings (experiments.oracle_world).
    oracle: OracleSection | None = None
    # (dotted field or table name, comment) pairs written into the saved config:
    # where a derived value comes from.
    notes: tuple[tuple[str, str], ...] = ()

    @property
    def net_dir(self) -> Path:
        return Path(self.scenario.net_dir)

    @property
    def is_controlled_scenario(self) -> bool:
        return self.scenario.kind in SCENARIO_TABLES

    def scenario_params(self) -> SingleRoadParams | CrossroadParams:
        """Parameters of a controlled scenario (``scenario.kind`` single_road or crossroad)."""
        if not self.is_controlled_scenario:
            raise ValueError(f"scenario kind {self.scenario.kind!r} has no scenario parameters")
        return getattr(self, self.scenario.kind)


SECTIONS: dict[str, type] = {
    "run": RunSection,
    "scenario": ScenarioSection,
    "single_road": SingleRoadParams,
    "crossroad": CrossroadParams,
    "sensors": SensorParams,
    "motion": MotionParams,
    "icp": IcpSection,
    "lc": LcParams,
    "pf": PfSection,
    "report": ReportSection,
}

#: Tables a config may leave out (then the Config field is None and nothing is written for them).
OPTIONAL_SECTIONS: dict[str, type] = {"infra": InfraSection, "perception": PerceptionParams,
                                      "gnss_error": GnssErrorParams, "v2x": V2xParams,
                                      "inertial": InertialParams, "features": FeaturesParams,
                                      "estimator_sensors": EstimatorSensors,
                                      "gnss_model": GnssModelParams, "fusion": FusionParams,
                                      "analysis": AnalysisSection, "oracle": OracleSection}
#: Optional tables of the coupler (realistic sensing, realistic V2X), carried to it inside
#: [sensors].
SENSING_SECTIONS = ("perception", "gnss_error", "v2x", "inertial", "features")



def _allows_infinity(where: str) -> bool:
    """Ranges may be ``inf`` (TOML ``inf``): "always in range", e.g. the single road's V2V links."""
    return where.split("[")[0].endswith("_range_m")


def _check_value(value, annotation, where: str, path: Path):
    """Coerce/validate one TOML value against a dataclass annotation.

    ``X | None`` fields take an X (TOML has no null: leave the key out for None);
    ``tuple[T, ...]`` takes a list, ``tuple[T, T]`` a list of exactly two.
    """
    origin = typing.get_origin(annotation)
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(path, where, f"expected a number, got {value!r}")
        if math.isnan(value) or (math.isinf(value) and not (value > 0 and _allows_infinity(where))):
            raise InputError(path, where, "must be finite")
        return float(value)
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(path, where, f"expected an integer, got {value!r}")
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise InputError(path, where, f"expected true or false, got {value!r}")
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise InputError(path, where, f"expected a string, got {value!r}")
        return value
    if origin is tuple:
        args = typing.get_args(annotation)
        if not isinstance(value, list):
            raise InputError(path, where, f"expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            inner_types = [args[0]] * len(value)
        else:
            if len(value) != len(args):
                raise InputError(path, where, f"expected a list of {len(args)} values, got {len(value)}")
            inner_types = list(args)
        return tuple(_check_value(v, t, f"{where}[{i}]", path) for i, (v, t) in enumerate(zip(value, inner_types)))
    if dataclasses.is_dataclass(annotation):  # a sub-table, e.g. [[perception.sensors]]
        return section_from_table(annotation, value, where, path)
    if origin in (typing.Union, types.UnionType):
        inner = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(inner) == 1:
            return _check_value(value, inner[0], where, path)
        if all(a in (int, str) for a in inner):  # e.g. [v2x] rounds_per_step: an integer or "unlimited"
            if isinstance(value, str) or (isinstance(value, int) and not isinstance(value, bool)):
                return value
            raise InputError(path, where, f"expected an integer or a string, got {value!r}")
        raise TypeError(f"unsupported annotation {annotation} for {where}")
    raise TypeError(f"unsupported annotation {annotation} for {where}")


def section_from_table(cls: type, table: dict, name: str, path: Path, ranges: dict | None = None):
    """A section dataclass from a TOML table; numbers checked against ``ranges`` (default: the run config's,
    :data:`experiments.ranges.RANGES`)."""
    if not isinstance(table, dict):
        raise InputError(path, name, "expected a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise InputError(path, f"{name}.{unknown[0]}", f"unknown key (known: {', '.join(sorted(fields))})")
    kwargs = {}
    for key, f in fields.items():
        if key in table:
            kwargs[key] = _check_value(table[key], hints[key], f"{name}.{key}", path)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise InputError(path, f"{name}.{key}", "required key missing")
    try:
        obj = cls(**kwargs)
    except InputError as exc:  # a dataclass validating itself names the field it refuses
        if exc.path is not None:
            raise
        raise InputError(path, f"{name}.{exc.field}" if exc.field else name, exc.message) from None
    except (ValueError, TypeError) as exc:
        # The dataclass's own checks (__post_init__): name the key that fails on its own.
        for key in kwargs:
            try:
                cls(**{key: kwargs[key]})
            except (ValueError, TypeError):
                raise InputError(path, f"{name}.{key}", str(exc)) from None
        raise InputError(path, name, str(exc)) from None
    except ArithmeticError:  # a value far out of its range broke the dataclass's own checks
        check_ranges_of(kwargs, name, path, ranges)
        raise
    # The physical range of every number (experiments.ranges), after the dataclass's own checks, whose
    # messages are the more specific ones.
    check_ranges_of(obj, name, path, ranges)
    return obj


def _validate(cfg: Config) -> None:
    p = cfg.path
    for i, m in enumerate(cfg.run.methods):
        if m not in METHODS or not METHODS[m].runnable:
            raise InputError(p, f"run.methods[{i}]",
                             f"unknown method {m!r} (available: {', '.join(runnable_methods())})")
    if not cfg.run.methods:
        raise InputError(p, "run.methods", "at least one method is needed")
    if len(set(cfg.run.methods)) != len(cfg.run.methods):
        raise InputError(p, "run.methods", "a method is listed twice")
    if cfg.run.duration_s <= 0:
        raise InputError(p, "run.duration_s", "must be positive")
    if (why := seed_problem(cfg.run.seed)) is not None:
        raise InputError(p, "run.seed", why)
    try:
        PfParams(**dataclasses.asdict(cfg.pf))
    except ValueError as exc:
        raise InputError(p, "pf", str(exc)) from None
    if cfg.scenario.kind not in SCENARIO_KINDS:
        raise InputError(p, "scenario.kind",
                         f"unknown scenario kind {cfg.scenario.kind!r} (available: {', '.join(SCENARIO_KINDS)})")
    if not cfg.scenario.step_s > 0:
        raise InputError(p, "scenario.step_s", "must be positive")
    for name in ("accel_sigma", "v2f_range_m", "v2f_sigma_p", "v2f_sigma_v", "v2v_range_m", "prior_sigma_p", "prior_sigma_v"):
        val = getattr(cfg.sensors, name)
        if val < 0 or (val == 0 and name.startswith(("prior", "v2f_sigma"))):
            raise InputError(p, f"sensors.{name}", "must be positive")
    if cfg.icp.consensus_iterations < 0:
        raise InputError(p, "icp.consensus_iterations", "must be >= 0")
    if cfg.icp.bpa_max_iterations < 1:
        raise InputError(p, "icp.bpa_max_iterations", "must be >= 1")
    for name in ("feature_velocity_prior_sigma", "message_memory_s"):
        if getattr(cfg.icp, name) < 0:
            raise InputError(p, f"icp.{name}", "must be >= 0")
    if cfg.icp.feature_message not in FEATURE_MESSAGES:
        raise InputError(p, "icp.feature_message",
                         f"unknown value {cfg.icp.feature_message!r} (available: {', '.join(FEATURE_MESSAGES)})")
    if cfg.icp.stop_on not in STOP_RULES:
        raise InputError(p, "icp.stop_on", f"unknown value {cfg.icp.stop_on!r} (available: {', '.join(STOP_RULES)})")
    if cfg.icp.budget_split not in BUDGET_SPLITS:
        raise InputError(p, "icp.budget_split",
                         f"unknown value {cfg.icp.budget_split!r} (available: {', '.join(BUDGET_SPLITS)})")
    for name in ("stop_pos_m", "stop_vel_mps", "feature_sigma_par", "pedestrian_sigma_par", "feature_drop_after_s"):
        if not getattr(cfg.icp, name) > 0:
            raise InputError(p, f"icp.{name}", "must be positive")
    for name in ("sigma_along", "sigma_cross"):
        if not getattr(cfg.motion, name) > 0:
            raise InputError(p, f"motion.{name}", "must be positive")
    if cfg.motion.imu_heading not in IMU_HEADINGS:
        raise InputError(p, "motion.imu_heading",
                         f"unknown value {cfg.motion.imu_heading!r} (available: {', '.join(IMU_HEADINGS)})")
    if cfg.scenario.kind == "sumo":
        if not cfg.scenario.net_dir:
            raise InputError(p, "scenario.net_dir", "required for a SUMO scenario")
        if not (Path(cfg.scenario.net_dir) / "scenario.toml").is_file():
            raise InputError(p, "scenario.net_dir", f"no net folder (scenario.toml) at {cfg.scenario.net_dir}")
        _check_begin_against_demand(cfg)
        if cfg.scenario.start not in STARTS:
            raise InputError(p, "scenario.start", f"unknown value {cfg.scenario.start!r} (available: {', '.join(STARTS)})")
        if cfg.scenario.reference_point not in REFERENCE_POINTS:
            raise InputError(p, "scenario.reference_point", f"unknown value {cfg.scenario.reference_point!r} "
                             f"(available: {', '.join(REFERENCE_POINTS)})")
    validate_warmup_start(cfg)
    validate_oracle(cfg)
    _validate_pedestrians(cfg)
    _validate_infra(cfg)
    if cfg.gnss_error is not None and cfg.gnss_error.model == "satellites" and cfg.scenario.kind == "sumo":
        from couplers.sensing.gnss_satellites import check_building_heights

        check_building_heights(cfg.scenario.net_dir)  # every building needs its height (file and field named)


def _validate_pedestrians(cfg: Config) -> None:
    """[features] pedestrians: a net folder with persons, and methods that know feature classes."""
    if cfg.features is None or not cfg.features.pedestrians:
        return
    p = cfg.path
    ok = [n for n in runnable_methods() if METHODS[n].feature_classes]
    for i, m in enumerate(cfg.run.methods):
        if not METHODS[m].feature_classes:
            raise InputError(p, f"run.methods[{i}]", f"method {m!r} has no per-class feature model: not supported "
                             f"with [features] pedestrians = true (use {', '.join(ok)})")
    if cfg.infra is not None:
        raise InputError(p, "features.pedestrians", "not supported together with [infra]")
    from couplers.net.folder import load_net_folder

    if load_net_folder(cfg.scenario.net_dir).persons is None:
        raise InputError(p, "features.pedestrians", f"the net folder {cfg.scenario.net_dir} has no persons file "
                         "([files] persons in its scenario.toml; e.g. sumo_nets/arterial_ped)")


def _validate_infra(cfg: Config) -> None:
    """[infra] values, its junctions in the net, and the infrastructure methods needing it."""
    p = cfg.path
    inf = cfg.infra
    for i, m in enumerate(cfg.run.methods):
        if METHODS[m].infrastructure and inf is None:
            raise InputError(p, f"run.methods[{i}]", f"method {m!r} needs an [infra] table (road-side units)")
    if inf is None:
        return
    if cfg.scenario.kind != "sumo":
        raise InputError(p, "infra", "infrastructure mode needs scenario.kind = \"sumo\"")
    if not inf.rsu_junctions:
        raise InputError(p, "infra.rsu_junctions", "at least one junction is needed")
    if len(set(inf.rsu_junctions)) != len(inf.rsu_junctions):
        raise InputError(p, "infra.rsu_junctions", "a junction is listed twice")
    for name in ("rsu_range_m", "radar_sigma_m", "odom_sigma_m", "rsu_bp_feature_drop_s",
                 "rsu_bp_birth_max_std_m"):
        if not getattr(inf, name) > 0 or math.isinf(getattr(inf, name)):
            raise InputError(p, f"infra.{name}", "must be positive and finite")
    if inf.radar_pose_offset_sigma_m < 0:
        raise InputError(p, "infra.radar_pose_offset_sigma_m", "must be >= 0")
    if not 0 < inf.rsu_bp_detection_prob <= 1:
        raise InputError(p, "infra.rsu_bp_detection_prob", "must be in (0, 1]")
    for name, low in (("rsu_bp_particles", 2), ("sme_max_vehicles", 1), ("fg_window_steps", 2)):
        if getattr(inf, name) < low:
            raise InputError(p, f"infra.{name}", f"must be >= {low}")
    from couplers.sensing.infra import junction_positions
    from couplers.net.folder import load_net_folder

    junction_positions(load_net_folder(cfg.scenario.net_dir).net, inf.rsu_junctions, p, "infra.rsu_junctions")


def _derive_from_scenario(sections: dict, data: dict, path: Path) -> list[tuple[str, str]]:
    """Make sensors, motion, step and feature model equal to the controlled scenario's own.

    Explicitly given values that differ are refused (see the module docstring).
    Returns the notes for the saved config.
    """
    kind = sections["scenario"].kind
    params = sections[kind]
    notes: list[tuple[str, str]] = []
    for key in SUMO_ONLY_KEYS:
        if key in data.get("scenario", {}):
            also = f"; set {kind}.start instead" if key == "start" else ""
            raise InputError(path, f"scenario.{key}", f"only for scenario.kind = \"sumo\" (this is {kind!r}){also}")
    for other in SCENARIO_TABLES:
        if other != kind and other in data:
            raise InputError(path, other, f"table given but scenario.kind is {kind!r}")

    if params.start == "gnss_fix":
        for key in ("prior_sigma_p", "prior_sigma_v"):
            if key in data.get(kind, {}):
                raise InputError(path, f"{kind}.{key}", f"not used with {kind}.start = \"gnss_fix\" (the first fix "
                                 f"has the GNSS accuracy); leave it out or set start = \"fast_start\"")
        notes.append((f"{kind}.start", "gnss_fix: sensors.prior_sigma_p/v = the GNSS sigmas"))
    given = data.get("sensors", {})
    sensors = params.sensor_params()
    for f in dataclasses.fields(SensorParams):
        mine = getattr(sensors, f.name)
        if f.name in given and getattr(sections["sensors"], f.name) != mine:
            raise InputError(path, f"sensors.{f.name}",
                             f"the {kind} scenario senses with its own parameters ({kind}.{f.name} = {mine!r}); "
                             f"set {kind}.{f.name} instead, or leave [sensors] out")
    sections["sensors"] = sensors
    notes.append(("sensors", f"= the [{kind}] scenario's sensing parameters (couplers.scenarios)"))

    given = data.get("motion", {})
    motion = sections["motion"]
    for key in ("sigma_along", "sigma_cross"):
        mine = getattr(params, key)
        if key in given and getattr(motion, key) != mine:
            raise InputError(path, f"motion.{key}",
                             f"must equal {kind}.{key} = {mine!r}: the estimators use the scenario's own "
                             f"model (1); leave it out to take it from [{kind}]")
        notes.append((f"motion.{key}", f"= {kind}.{key} (the scenario's model (1) driving noise)"))
    sections["motion"] = dataclasses.replace(motion, sigma_along=params.sigma_along, sigma_cross=params.sigma_cross)

    if "step_s" in data.get("scenario", {}) and sections["scenario"].step_s != params.dt:
        raise InputError(path, "scenario.step_s", f"must equal {kind}.dt = {params.dt!r} (the scenario's Ts)")
    sections["scenario"] = dataclasses.replace(sections["scenario"], step_s=params.dt)
    notes.append(("scenario.step_s", f"= {kind}.dt"))
    notes.append(("run.duration_s", "caps the run; the scenario also ends by itself"))

    vf = getattr(params, "feature_speed_mps", 0.0)
    if vf > 0 and "feature_sigma_par" not in data.get("icp", {}):
        # Paper Sec. V-B: sv_par = vf / 100 for features moving at vf (model (2)).
        sections["icp"] = dataclasses.replace(sections["icp"], feature_sigma_par=vf / 100.0)
        notes.append(("icp.feature_sigma_par", f"= {kind}.feature_speed_mps / 100 (paper Sec. V-B)"))
    return notes


def _net_folder_clock(sections: dict, data: dict, path: Path) -> list[tuple[str, str]]:
    """``scenario.begin_s`` / ``scenario.step_s`` / ``run.duration_s`` not given: the net folder's ``[sumo]``
    begin / step_length / end - begin (:class:`couplers.net.folder.SumoClock`); returns the notes."""
    from couplers.net.folder import read_sumo_clock

    scen = sections["scenario"]
    given_scen, given_run = data.get("scenario", {}), data.get("run", {})
    if scen.begin_s is not None and not (scen.begin_s >= 0 and math.isfinite(scen.begin_s)):
        raise InputError(path, "scenario.begin_s", "must be a finite time >= 0 s")
    toml = Path(scen.net_dir) / "scenario.toml" if scen.net_dir else None
    if toml is None or not toml.is_file():  # reported by _validate
        return []
    clock = read_sumo_clock(read_toml(toml), toml)
    notes = []
    if "begin_s" not in given_scen:
        sections["scenario"] = dataclasses.replace(sections["scenario"], begin_s=clock.begin)
        if clock.begin:
            notes.append(("scenario.begin_s", "= the net folder's [sumo] begin"))
    if "step_s" not in given_scen and clock.step_length is not None and clock.step_length != scen.step_s:
        sections["scenario"] = dataclasses.replace(sections["scenario"], step_s=clock.step_length)
        notes.append(("scenario.step_s", "= the net folder's [sumo] step_length"))
    begin = sections["scenario"].begin_s
    if "duration_s" not in given_run and clock.end is not None and clock.end > begin \
            and clock.end - begin != sections["run"].duration_s:
        sections["run"] = dataclasses.replace(sections["run"], duration_s=clock.end - begin)
        notes.append(("run.duration_s", "= the net folder's [sumo] end - scenario.begin_s"))
    return notes


def _check_begin_against_demand(cfg: Config) -> None:
    """A begin after the demand's last departure is refused (nothing would drive); begin 0 is not checked."""
    begin = cfg.scenario.begin_s
    if not begin:
        return
    from couplers.net.folder import load_net_folder
    from couplers.net.importer.sumocfg import clock, demand_departures

    folder = load_net_folder(cfg.scenario.net_dir)
    dep = demand_departures(folder.route_files)
    if dep.last is not None and begin > dep.last:
        raise InputError(cfg.path, "scenario.begin_s", f"{begin:g} s ({clock(begin)}) is after the last departure "
                         f"of the demand of {folder.root.name} ({dep.last:g} s, {clock(dep.last)}): "
                         "nothing would drive")


def config_from_dict(data: dict, path: Path, overrides: dict | None = None) -> Config:
    """The validated config of the tables ``data`` read from ``path`` (its ``extends`` chain merged in first,
    :mod:`experiments.config_extends`); an error about an inherited key names the file that wrote it."""
    if EXTENDS in data:
        data = resolve_extends(data, path)
    try:
        cfg = _config_from_dict(data, path, overrides)
    except InputError as exc:
        origin = origin_of(data, exc.field)
        if (origin is None or exc.path is None or Path(exc.path).resolve() != Path(path).resolve()
                or origin.resolve() == Path(path).resolve() or exc.field.split("[")[0] in (overrides or {})):
            raise
        raise InputError(origin, exc.field, exc.message) from None
    check_building_occlusion(cfg, data, overrides)  # names this file: it chose the net folder
    return cfg



def _config_from_dict(data: dict, path: Path, overrides: dict | None = None) -> Config:
    chain = chain_text(data)
    # A saved (resolved) config carries its provenance; it is informative, not input.
    data = {k: v for k, v in data.items() if k != "provenance"}
    unknown = sorted(set(data) - set(SECTIONS) - set(OPTIONAL_SECTIONS))
    if unknown:
        raise InputError(path, unknown[0], f"unknown table (known: {', '.join([*SECTIONS, *OPTIONAL_SECTIONS])})")
    for name, table in data.items():
        if not isinstance(table, dict):
            raise InputError(path, name, "expected a table")
    data = {k: dict(v) for k, v in data.items()}
    for dotted, value in (overrides or {}).items():
        sec, key = dotted.split(".")
        if sec in OPTIONAL_SECTIONS and sec not in data:
            raise InputError(path, dotted, f"the config has no [{sec}] table: add one to it to set its keys")
        data.setdefault(sec, {})[key] = value
    if "run" not in data:
        raise InputError(path, "run", "required table missing")
    for name in SENSING_SECTIONS:
        if name in data.get("sensors", {}):
            raise InputError(path, f"sensors.{name}", f"not a [sensors] key: give a [{name}] table")
    sections = {name: section_from_table(cls, data.get(name, {}), name, path) for name, cls in SECTIONS.items()}
    scen = sections["scenario"]
    if scen.kind not in SCENARIO_KINDS:
        raise InputError(path, "scenario.kind",
                         f"unknown scenario kind {scen.kind!r} (available: {', '.join(SCENARIO_KINDS)})")
    if scen.net_dir:
        net_dir = (path.parent / scen.net_dir).resolve()
        sections["scenario"] = dataclasses.replace(scen, net_dir=str(net_dir))
    notes: list[tuple[str, str]] = []
    if scen.kind in SCENARIO_TABLES:
        notes += _derive_from_scenario(sections, data, path)
    else:
        for name in SCENARIO_TABLES:
            if name in data:
                raise InputError(path, name, f"table given but scenario.kind is {scen.kind!r}")
        notes += _net_folder_clock(sections, data, path)
    if not sections["sensors"].v2f_range_m > 0:  # before it becomes lc.sensing_range_m below
        where = f"{scen.kind}.v2f_range_m" if scen.kind in SCENARIO_TABLES else "sensors.v2f_range_m"
        raise InputError(path, where, "must be positive (the V2F sensing range Rs, m)")
    if "sensing_range_m" not in data.get("lc", {}):
        sections["lc"] = dataclasses.replace(sections["lc"], sensing_range_m=sections["sensors"].v2f_range_m)
        notes.append(("lc.sensing_range_m", "= sensors.v2f_range_m (the V2F range Rs in force)"))
    rep = sections["report"]
    if len(set(rep.track_areas)) != len(rep.track_areas):
        raise InputError(path, "report.track_areas", "an area is listed twice")
    if rep.track_areas and "track_area" in data.get("report", {}) and rep.track_area != rep.track_areas[0]:
        # (a saved config has both, track_area = the first of track_areas)
        raise InputError(path, "report.track_areas", "give report.track_area or report.track_areas, not both")
    # Resolved: both keys, track_area the first of track_areas.
    sections["report"] = dataclasses.replace(rep, track_area=rep.track_figure_areas[0],
                                             track_areas=rep.track_figure_areas)
    for name, cls in OPTIONAL_SECTIONS.items():
        if name in data:
            sections[name] = section_from_table(cls, data[name], name, path)
    notes += _attach_sensing(sections, path, data.get("lc", {}))
    notes += _attach_estimator_sensors(sections, path, data.get("lc", {}))
    lc = sections["lc"]
    if lc.new_feature_density == 0:
        derived = lc.new_feature_rate / (math.pi * lc.sensing_range_m**2)
        notes.append(("lc.new_feature_density", f"0: derived, new_feature_rate / (pi Rs^2) = {derived:.3g} per m^2 "
                      "times the velocity density of an untracked feature (coloc.methods.icp_da_lc, step 3)"))
    if chain is not None:
        notes.append((EXTENDS, chain))
    cfg = Config(path=path.resolve(), notes=tuple(notes), **sections)
    _validate(cfg)
    return cfg


def _attach_sensing(sections: dict, path: Path, lc_given: dict) -> list[tuple[str, str]]:
    """Hand [perception] / [gnss_error] / [v2x] / [inertial] to the coupler inside [sensors] (SUMO scenarios only).
    With [perception], ``lc.sensing_range_m`` (not given in ``lc_given``) becomes the sensors' reach."""
    if sections["lc"].sensor_fov and sections.get("perception") is None and sections.get("estimator_sensors") is None:
        raise InputError(path, "lc.sensor_fov", "needs a [perception] table (the sensors whose field of view "
                                                "the estimator expects)")
    given = {name: sections[name] for name in SENSING_SECTIONS if sections.get(name) is not None}
    if not given:
        return []
    if sections["scenario"].kind != "sumo":
        name = next(iter(given))
        if name == "features":
            raise InputError(path, "features.pedestrians", "SUMO pedestrians need scenario.kind = \"sumo\" (this is "
                             f"{sections['scenario'].kind!r}; its moving features are [crossroad] feature_speed_mps)")
        what = "realistic V2X" if name == "v2x" else "realistic sensing"
        raise InputError(path, name, f"{what} needs scenario.kind = \"sumo\" "
                                     f"(this is {sections['scenario'].kind!r}): the controlled scenarios "
                                     f"keep the paper's idealisation")
    if "v2x" in given and sections.get("infra") is not None:
        raise InputError(path, "v2x", "not supported together with [infra] yet (the RSU radars would have to "
                                      "see the unequipped vehicles too)")
    if "inertial" in given and sections.get("infra") is not None:
        raise InputError(path, "inertial", "not supported together with [infra]: the infrastructure methods "
                                           "(rsu_bp, sme, fg_topology_new) take the net-frame input")
    sections["sensors"] = dataclasses.replace(sections["sensors"], **given)
    notes = []
    if "perception" in given:
        notes.append(("sensors.v2f_range_m", "not used for V2F rows: the [perception] sensors' ranges apply"))
        if "sensing_range_m" not in lc_given:
            reach = given["perception"].max_reach_m
            sections["lc"] = dataclasses.replace(sections["lc"], sensing_range_m=reach)
            notes.append(("lc.sensing_range_m", "= the [perception] sensors' largest reach (range + mount offset)"))
    return notes


def _attach_estimator_sensors(sections: dict, path: Path, lc_given: dict) -> list[tuple[str, str]]:
    """With [estimator_sensors]: ``lc.clutter_intensity`` and ``lc.sensing_range_m`` (when not given) from it."""
    est = sections.get("estimator_sensors")
    if est is None:
        return []
    if sections["scenario"].kind != "sumo":
        raise InputError(path, "estimator_sensors", "needs scenario.kind = \"sumo\" (the estimators' model of "
                                                    "the [perception] sensors)")
    notes, lc = [], sections["lc"]
    if "clutter_intensity" not in lc_given:
        lc = dataclasses.replace(lc, clutter_intensity=est.clutter_intensity())
        notes.append(("lc.clutter_intensity", "= the [estimator_sensors]' clutter per scan over the union of their "
                      f"fields of view ({est.coverage_area_m2:.0f} m^2)"))
    if "sensing_range_m" not in lc_given:
        lc = dataclasses.replace(lc, sensing_range_m=est.max_reach_m)
        notes.append(("lc.sensing_range_m", "= the [estimator_sensors]' largest reach (range + mount offset)"))
    sections["lc"] = lc
    return notes


def load_config(path: str | Path, overrides: dict | None = None) -> Config:
    """Read and validate a config; ``overrides`` maps "section.key" to a value (command-line options)."""
    path = Path(path)
    return config_from_dict(read_toml(path, "config file"), path, overrides)
