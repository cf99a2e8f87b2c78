"""Physical ranges of every numeric config key, checked on load.

The type checks of :mod:`experiments.config` let any finite number through; the dataclasses' own
checks refuse what breaks a formula (a negative sigma, a probability above 1). This table adds the
upper side and the rest: a value outside the range a real vehicle, sensor, net or machine has is
refused with one line naming the file, the dotted key, the value and the range, before it can reach
numba (integer overflow), numpy (a multi-terabyte allocation) or the estimators (NaN estimates).

Keys are dotted like the error messages, without list indices: ``perception.sensors.fov_deg`` is
every ``[[perception.sensors]]`` table's ``fov_deg``, ``v2x.pdr_los`` every element of that list.
The ranges are generous: every shipped config and sweep is well inside them
(``tests/experiments/test_ranges.py`` checks that, and that every numeric field of every table has a
range). ``inf`` is accepted only where a range says so (``inf_ok``: "always in range", the V2F/V2V
ranges of the controlled scenarios).

Caps that are not physics but the machine: particle and iteration counts are capped where one run
would no longer fit in the 24 GB of the reference machine or finish in a day; a duration at 7 days.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from pathlib import Path

from couplers.errors import InputError

#: Unit of a dimensionless number (as in experiments.configdoc).
NO_UNIT = "1"
WEEK_S = 7 * 24 * 3600.0
SEED_MAX = 2**31 - 1  # couplers.errors.seed_problem: SUMO's --seed is a signed 32-bit integer


@dataclass(frozen=True)
class Range:
    """``low <= value <= high`` (``<`` where ``low_open`` / ``high_open``), in ``unit``; ``why`` says where the
    bounds come from (one phrase). ``inf_ok``: +inf is accepted and means "always in range"."""

    low: float
    high: float
    unit: str
    why: str
    low_open: bool = False
    high_open: bool = False
    inf_ok: bool = False

    def contains(self, value: float) -> bool:
        if math.isnan(value):
            return False
        if math.isinf(value) and value > 0 and self.inf_ok:
            return True
        above = value > self.low if self.low_open else value >= self.low
        below = value < self.high if self.high_open else value <= self.high
        return above and below

    def bounds(self) -> str:
        """``[0, 50]``, ``(0, 1]``, ``[0, 10000] or inf``."""
        text = f"{'(' if self.low_open else '['}{_num(self.low)}, {_num(self.high)}{')' if self.high_open else ']'}"
        return text + (" or inf" if self.inf_ok else "")

    def text(self) -> str:
        """The bounds with the unit: ``[0, 50] m/s^2``."""
        unit = "" if self.unit == NO_UNIT else f" {self.unit}"
        if self.inf_ok:
            return self.bounds().replace(" or inf", unit + " or inf")
        return self.bounds() + unit


def _num(v) -> str:
    if isinstance(v, int) and not isinstance(v, bool):
        return str(v)
    return f"{v:g}"


# Shared ranges (one phrase of reason each).
SIGMA_M = Range(0.0, 1e3, "m", "a position noise beyond 1 km locates nothing")
SIGMA_MPS = Range(0.0, 100.0, "m/s", "a velocity noise beyond 100 m/s exceeds any road speed")
ACCEL = Range(0.0, 50.0, "m/s^2", "5 g: beyond what a road vehicle's acceleration reaches")
PROB = Range(0.0, 1.0, NO_UNIT, "a probability")
DURATION = Range(0.0, WEEK_S, "s", "at most 7 days")
POS_DURATION = Range(0.0, WEEK_S, "s", "positive, at most 7 days", low_open=True)
STEP = Range(0.001, 60.0, "s", "SUMO's time resolution is 1 ms; a step above a minute is no longer traffic")
SENSE_RANGE = Range(0.0, 1e4, "m", "10 km, beyond any on-board sensor or V2X link", low_open=True, inf_ok=True)
LINK_RANGE = Range(0.0, 1e5, "m", "100 km, beyond any radio link", inf_ok=True)
LENGTH = Range(0.0, 1e5, "m", "100 km: a road or area of a city scenario", low_open=True)
OFFSET = Range(-1e3, 1e3, "m", "a lateral offset within 1 km of the road axis")
GAIN_1_S = Range(0.0, 100.0, "1/s", "a controller gain above 100/s is faster than any vehicle responds")
PARTICLES_MAX = 100_000
PARTICLES_WHY = "10x the largest preset; the particle clouds and pair kernels must fit in 24 GB"
ITER = Range(0, 100_000, NO_UNIT, "1e5 iterations per step already take hours per step")
SPEED = Range(0.0, 100.0, "m/s", "360 km/h, above any road speed")
CORRELATION = Range(0.0, WEEK_S, "s", "a correlation time of at most 7 days")

_SENSING = {
    "accel_sigma": ACCEL,
    "v2f_range_m": SENSE_RANGE,
    "v2f_sigma_p": SIGMA_M,
    "v2f_sigma_v": SIGMA_MPS,
    "v2v_range_m": LINK_RANGE,
    "prior_sigma_p": SIGMA_M,
    "prior_sigma_v": SIGMA_MPS,
}

_SCENARIO_COMMON = {
    **_SENSING,
    "dt": STEP,
    "speed_kmh": Range(0.0, 360.0, "km/h", "above any road speed"),
    "sigma_along": ACCEL,
    "sigma_cross": ACCEL,
    "gnss_sigma_p": SIGMA_M,
    "gnss_sigma_v": SIGMA_MPS,
    "speed_gain": GAIN_1_S,
    "gap_gain": Range(0.0, 100.0, "1/s^2", "a controller gain above 100/s^2 is faster than any vehicle responds"),
    "rel_speed_gain": GAIN_1_S,
}

#: dotted key (list indices dropped) -> its range. Every int or float field of every config table is here.
RANGES: dict[str, Range] = {
    "run.seed": Range(0, SEED_MAX, NO_UNIT, "SUMO's --seed is a signed 32-bit integer"),
    "run.duration_s": DURATION,
    "scenario.step_s": STEP,
    "scenario.begin_s": Range(0.0, WEEK_S, "s", "a begin on the scenario's clock within its first week"),
    "analysis.warmup_s": Range(0.0, WEEK_S, "s", "a scoring warm-up within a week of the begin"),
    **{f"single_road.{k}": r for k, r in _SCENARIO_COMMON.items()},
    "single_road.n_vehicles": Range(1, 10_000, NO_UNIT, "vehicles in one lane of at most 100 km"),
    "single_road.headway_m": Range(0.0, 1e4, "m", "a spacing within 10 km", low_open=True),
    "single_road.feature_spacing_m": Range(0.0, 1e4, "m", "a spacing within 10 km"),
    "single_road.road_length_m": LENGTH,
    "single_road.sidewalk_offset_m": OFFSET,
    "single_road.duration_s": POS_DURATION,
    **{f"crossroad.{k}": r for k, r in _SCENARIO_COMMON.items()},
    "crossroad.vehicles_per_cluster": Range(1, 1000, NO_UNIT, "vehicles queued on one arm of at most 100 km"),
    "crossroad.arm_length_m": LENGTH,
    "crossroad.cluster_headway_m": Range(0.0, 1e4, "m", "a spacing within 10 km", low_open=True),
    "crossroad.lane_offset_m": OFFSET,
    "crossroad.n_features": Range(0, 100_000, NO_UNIT, "landmarks of a city district"),
    "crossroad.feature_disc_radius_m": Range(0.0, 1e5, "m", "100 km: a city scenario"),
    "crossroad.sidewalk_offset_m": OFFSET,
    "crossroad.feature_speed_mps": SPEED,
    "crossroad.area_ring_m": Range(1.0, 1e5, "m", "analysis rings of at least 1 m (a report row each) within 100 km"),
    "crossroad.max_duration_s": POS_DURATION,
    "crossroad.centre": Range(-1e7, 1e7, "m", "net coordinates within 10,000 km (projected map scale)"),
    **{f"sensors.{k}": r for k, r in _SENSING.items()},
    "motion.sigma_along": ACCEL,
    "motion.sigma_cross": ACCEL,
    "motion.heading_min_speed": SPEED,
    "icp.consensus_iterations": ITER,
    "icp.bpa_max_iterations": ITER,
    "icp.stop_pos_m": SIGMA_M,
    "icp.stop_vel_mps": SIGMA_MPS,
    "icp.feature_sigma_par": SIGMA_MPS,
    "icp.pedestrian_sigma_par": Range(0.0, 100.0, "m/s", "positive, below any road speed", low_open=True),
    "icp.feature_drop_after_s": DURATION,
    "icp.feature_velocity_prior_sigma": SIGMA_MPS,
    "icp.message_memory_s": DURATION,
    "lc.eta_threshold": Range(0.0, 1e6, NO_UNIT, "a threshold on a belief ratio; above 1e6 every track is detected"),
    "lc.detection_probability": PROB,
    "lc.gate_probability": PROB,
    "lc.new_feature_velocity_sigma": SIGMA_MPS,
    "lc.birth_probability": PROB,
    "lc.merge_gate_m": SIGMA_M,
    "lc.sensing_range_m": SENSE_RANGE,
    "lc.new_feature_rate": Range(0.0, 1e4, NO_UNIT, "untracked features in one vehicle's view"),
    "lc.new_feature_density": Range(0.0, 1e6, "1/(m^2 (m/s)^2)", "a density of new features; above 1e6 "
                                    "every measurement is new"),
    "lc.clutter_intensity": Range(0.0, 1e3, "1/m^2", "1000 false detections per m^2 and scan"),
    "lc.visibility": Range(0.0, 1.0, NO_UNIT, "a share, positive", low_open=True),
    "lc.survival_probability": PROB,
    "lc.confirm_existence": PROB,
    "lc.drop_existence": PROB,
    "lc.own_consistency_gate": PROB,
    "lc.relocalize_radius_m": SIGMA_M,
    "lc.relocalize_tolerance_m": Range(0.0, 1e3, "m", "a position tolerance beyond 1 km matches anything",
                                       low_open=True),
    "lc.relocalize_min_support": Range(1, 1000, NO_UNIT, "rows of one vehicle in one scan"),
    "lc.relocalize_min_gain": Range(0, 1000, NO_UNIT, "rows of one vehicle in one scan"),
    "lc.reset_map_margin": Range(0, 1000, NO_UNIT, "rows of one vehicle in one scan"),
    "lc.fix_map_margin": Range(0, 1000, NO_UNIT, "rows of one vehicle in one scan"),
    "lc.anchor_margin": Range(0, 1000, NO_UNIT, "rows of one vehicle in one scan"),
    "lc.bp_iterations": ITER,
    "lc.bp_tol": Range(0.0, 1.0, NO_UNIT, "a change of beliefs (probabilities)"),
    # 1e5 particles, ten times the largest preset (10000): the arterial's ~200 vehicles hold 0.64 GB a copy
    # of their states (4 doubles a particle), a step keeps several copies besides the pair kernels, which
    # grow faster, within the 24 GB of the reference machine.
    "pf.vehicle_particles": Range(1, PARTICLES_MAX, NO_UNIT, PARTICLES_WHY),
    "pf.feature_particles": Range(1, PARTICLES_MAX, NO_UNIT, PARTICLES_WHY),
    "pf.kernel_rel_tol": Range(0.0, 1.0, NO_UNIT, "a relative error"),
    "pf.kernel_cache_mb": Range(0.0, 24_576.0, "MB", "the 24 GB of the reference machine"),
    "pf.min_association_belief": PROB,
    "pf.sigma_along": ACCEL,
    "pf.sigma_cross": ACCEL,
    "infra.rsu_range_m": Range(0.0, 1e4, "m", "10 km, beyond any road-side radar", low_open=True),
    "infra.radar_sigma_m": SIGMA_M,
    "infra.radar_pose_offset_sigma_m": SIGMA_M,
    "infra.odom_sigma_m": SIGMA_M,
    "infra.rsu_bp_particles": Range(2, PARTICLES_MAX, NO_UNIT, PARTICLES_WHY),
    "infra.rsu_bp_detection_prob": PROB,
    "infra.rsu_bp_feature_drop_s": DURATION,
    "infra.rsu_bp_birth_max_std_m": Range(0.0, 1e4, "m", "10 km, beyond any position error", low_open=True),
    "infra.sme_max_vehicles": Range(1, 10_000, NO_UNIT, "vehicles in one RSU's range"),
    "infra.fg_window_steps": Range(2, 100_000, NO_UNIT, "a smoother window of at most 1e5 steps"),
    "perception.sensors.fov_deg": Range(0.0, 360.0, "deg", "a full turn"),
    "perception.sensors.range_m": Range(0.0, 1e4, "m", "10 km, beyond any on-board sensor"),
    "perception.sensors.yaw_deg": Range(-360.0, 360.0, "deg", "a full turn either way"),
    "perception.sensors.mount_x_m": Range(-100.0, 100.0, "m", "within a vehicle's length"),
    "perception.sensors.pd_near": PROB,
    "perception.sensors.pd_far": PROB,
    "perception.sensors.clutter_per_scan": Range(0.0, 1000.0, NO_UNIT, "false detections per scan; a radar "
                                                 "reports at most a few hundred targets a scan"),
    "perception.sensors.sigma_p_m": SIGMA_M,
    "perception.sensors.sigma_growth": Range(0.0, 1e3, NO_UNIT, "noise at the range at most 1000 times that at 0 m"),
    "perception.sensors.sigma_v_mps": SIGMA_MPS,
    "gnss_error.tau_s": CORRELATION,
    "gnss_error.nlos_rate_per_min": Range(0.0, 600.0, "1/min", "ten episodes a second"),
    "gnss_error.nlos_rate_per_density_per_min": Range(0.0, 600.0, "1/min", "ten episodes a second"),
    "gnss_error.nlos_density_radius_m": Range(0.0, 1e4, "m", "10 km around the vehicle"),
    "gnss_error.nlos_mean_duration_s": CORRELATION,
    "gnss_error.nlos_bias_mean_m": Range(0.0, 1e3, "m", "NLOS excess path lengths are tens to hundreds of metres"),
    "gnss_error.common_share": PROB,
    "gnss_error.common_tau_s": CORRELATION,
    "gnss_error.field_share": PROB,
    "gnss_error.field_corr_length_m": Range(0.0, 1e5, "m", "100 km: beyond it the field is one common part",
                                            low_open=True),
    "gnss_error.field_tau_s": CORRELATION,
    "gnss_error.field_features": Range(1, 4096, NO_UNIT, "random Fourier features: a few dozen give the "
                                       "correlation to a few per cent; thousands cost time, not accuracy"),
    "gnss_error.local_corr_length_m": Range(0.0, 1e5, "m", "100 km travelled", low_open=True),
    "gnss_error.nlos_cell_m": Range(0.0, 1e4, "m", "a cell of 10 km holds a whole city", low_open=True),
    "gnss_error.elevation_mask_deg": Range(0.0, 90.0, "deg", "an elevation above the horizon, below the zenith",
                                           high_open=True),
    "gnss_error.antenna_height_m": Range(0.0, 100.0, "m", "an antenna on a vehicle, not on a mast", low_open=True),
    "gnss_error.constellation_time_s": DURATION,
    "gnss_error.sv_clock_orbit_m": Range(0.0, 100.0, "m", "broadcast clock and orbit errors are metres; 100 m is a "
                                         "failed satellite"),
    "gnss_error.iono_vertical_m": Range(0.0, 100.0, "m", "vertical ionospheric delays stay below ~50 m even in "
                                        "storms"),
    "gnss_error.tropo_zenith_m": Range(0.0, 10.0, "m", "the whole zenith tropospheric delay is ~2.4 m"),
    "gnss_error.sv_tau_s": CORRELATION,
    "gnss_error.code_noise_a_m": SIGMA_M,
    "gnss_error.code_noise_b_m": SIGMA_M,
    "gnss_error.multipath_m": SIGMA_M,
    "gnss_error.multipath_corr_length_m": Range(0.0, 1e5, "m", "100 km travelled", low_open=True),
    "gnss_error.rx_ure_m": SIGMA_M,
    "gnss_error.rx_iono_m": SIGMA_M,
    "gnss_error.rx_tropo_m": SIGMA_M,
    "gnss_error.rx_code_a_m": SIGMA_M,
    "gnss_error.rx_code_b_m": SIGMA_M,
    "gnss_error.doppler_noise_mps": SIGMA_MPS,
    "gnss_error.rx_doppler_mps": Range(0.0, 100.0, "m/s", "a range-rate noise beyond 100 m/s exceeds any road speed",
                                       low_open=True),
    "gnss_error.raim_pfa": Range(0.0, 1.0, NO_UNIT, "a false-alarm probability (0: no fault exclusion)",
                                 high_open=True),
    "v2x.penetration_rate": PROB,
    "v2x.pdr_distance_m": Range(0.0, 1e5, "m", "100 km, beyond any radio link"),
    "v2x.pdr_los": PROB,
    "v2x.pdr_nlos": PROB,
    "v2x.rounds_per_step": Range(1, 1_000_000, NO_UNIT, "broadcast rounds per step"),
    "inertial.accel_noise_density": Range(0.0, 10.0, "m/s^2/sqrt(Hz)", "1 g/sqrt(Hz), far above any MEMS IMU"),
    "inertial.accel_bias_sigma": ACCEL,
    "inertial.accel_bias_tau_s": CORRELATION,
    "inertial.accel_turn_on_sigma": ACCEL,
    "inertial.gyro_noise_density": Range(0.0, 100.0, "deg/s/sqrt(Hz)", "far above any MEMS gyroscope"),
    "inertial.gyro_bias_sigma": Range(0.0, 360.0, "deg/s", "a turn a second"),
    "inertial.gyro_bias_tau_s": CORRELATION,
    "inertial.gyro_turn_on_sigma": Range(0.0, 360.0, "deg/s", "a turn a second"),
    "perception.sensors.sigma_r_m": Range(0.0, 1e3, "m", "a range noise beyond 1 km locates nothing", low_open=True),
    "perception.sensors.sigma_b_deg": Range(0.0, 180.0, "deg", "half a turn", low_open=True),
    "perception.sensors.sigma_rdot_mps": Range(0.0, 100.0, "m/s", "a range-rate noise beyond 100 m/s exceeds any road speed",
                                               low_open=True),
    "perception.persistent_clutter_per_km": Range(0.0, 1e4, "1/km", "a false-alarm source every 10 cm of road"),
    "perception.persistent_clutter_pd": PROB,
    "perception.class_error": PROB,
    "gnss_model.bias_share": Range(0.0, 1.0, NO_UNIT, "a share of the reported variance; 1 would leave no white "
                                   "noise", high_open=True),
    "gnss_model.bias_tau_s": Range(0.0, WEEK_S, "s", "a correlation time of at most 7 days", low_open=True),
    "gnss_model.max_exclusions": Range(0, 1_000_000, NO_UNIT, "consecutive excluded fixes"),
    "gnss_model.adaptive_window_s": Range(0.0, WEEK_S, "s", "a time constant of at most 7 days (0: off)"),
    "gnss_model.innovation_gate": Range(0.0, 1.0, NO_UNIT, "a probability level; 1 would gate nothing",
                                        high_open=True),
    "fusion.belief_innovation_gate": Range(-1.0, 1.0, NO_UNIT, "a probability level, or -1 for [gnss_model]'s",
                                           high_open=True),
    "fusion.belief_max_exclusions": Range(-1, 1_000_000, NO_UNIT, "consecutive excluded fixes, or -1 for "
                                          "[gnss_model]'s"),
    "gnss_model.common_share": Range(0.0, 1.0, NO_UNIT, "a share of the reported variance", high_open=True),
    "gnss_model.common_tau_s": Range(0.0, WEEK_S, "s", "a correlation time of at most 7 days", low_open=True),
    "gnss_model.velocity_gate": Range(0.0, 1.0, NO_UNIT, "a probability level; 1 would test nothing",
                                      high_open=True),
    "gnss_model.common_sigma_m": Range(0.0, 100.0, "m", "a receiver's open-sky error is metres; 100 m is a "
                                       "receiver without a fix"),
    "gnss_model.local_share": Range(0.0, 1.0, NO_UNIT, "a share of the reported variance", high_open=True),
    "gnss_model.local_length_m": Range(0.0, 1e5, "m", "a correlation length of at most 100 km", low_open=True),
    "gnss_model.local_tau_s": Range(0.0, WEEK_S, "s", "a correlation time of at most 7 days", low_open=True),
    "gnss_model.degraded_above_m": Range(0.0, 100.0, "m", "a reported per-axis std; 100 m is a receiver without "
                                         "a fix (0: off)"),
    "gnss_model.degraded_position_scale": Range(0.0, 100.0, NO_UNIT, "a factor on the reported std",
                                                low_open=True),
    "gnss_model.degraded_velocity_scale": Range(0.0, 100.0, NO_UNIT, "a factor on the reported std",
                                                low_open=True),
}
# [estimator_sensors]: the estimators' own datasheet table has the keys (and so the ranges) of the world's sensors.
RANGES.update({"estimator_sensors.sensors." + k[len("perception.sensors."):]: r for k, r in list(RANGES.items())
               if k.startswith("perception.sensors.")})

WORKERS = Range(1, 1024, NO_UNIT, "worker processes of one machine")

#: Numeric command-line options: (command function, argparse dest) -> range (``--seed`` and ``run --duration``
#: go through the config's ranges). Checked by experiments.cli before the command starts.
OPTION_RANGES: dict[tuple[str, str], Range] = {
    ("cmd_run", "workers"): Range(0, 64, NO_UNIT, "estimator worker processes: at most one per method"),
    ("cmd_sweep", "workers"): WORKERS,
    ("cmd_tune", "workers"): WORKERS,
    ("cmd_net_import", "features"): Range(1, 100_000, NO_UNIT, "landmarks of a city; a net folder needs one"),
    ("cmd_net_import", "demand"): Range(0.0, 1e5, "veh/h", "beyond the capacity of any city net"),
    ("cmd_net_import", "demand_scale"): Range(0.0, 1e3, NO_UNIT, "a factor on the demand"),
    ("cmd_net_import", "fringe_factor"): Range(0.0, 1e6, NO_UNIT, "randomTrips' weight of the fringe edges"),
    ("cmd_net_import", "duration"): POS_DURATION,
    ("cmd_net_import", "max_density_scale"): Range(0.0, 1e3, NO_UNIT, "a factor on the demand"),
    ("cmd_net_import", "calibration_s"): POS_DURATION,
    # building density over a cell smaller than a building measures single buildings (the import also caps
    # the number of cells over the net: couplers.net.importer.regions.ZONE_CELLS_MAX)
    ("cmd_net_import", "zone_cell"): Range(10.0, 1e5, "m", "a cell between 10 m and 100 km"),
    ("cmd_net_import", "occlusion_s"): Range(0.0, 86400.0, "s", "0 (not measured) up to a simulated day"),
    ("cmd_net_check", "max_feature_distance"): Range(0.0, 1e4, "m", "10 km, beyond any on-board sensor"),
}

_INDEX = re.compile(r"\[\d+\]")


def range_key(where: str) -> str:
    """The table key of a dotted field as errors name it: ``perception.sensors[1].fov_deg`` ->
    ``perception.sensors.fov_deg``, ``v2x.pdr_los[3]`` -> ``v2x.pdr_los``."""
    return _INDEX.sub("", where)


def check_range(value, where: str, path: Path | None, table: dict[str, Range] | None = None) -> None:
    """Raise an :class:`InputError` when the number ``value`` of field ``where`` lies outside its range
    (no range: nothing checked; :func:`tests.experiments.test_ranges` makes sure every field has one)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return
    r = (RANGES if table is None else table).get(range_key(where))
    if r is None or r.contains(value):
        return
    unit = "" if r.unit == NO_UNIT else f" {r.unit}"
    hint = ""
    if value < r.low or (r.low_open and value == r.low):  # say which side, as the dataclasses' own checks do
        hint = ": must be positive" if r.low == 0 and r.low_open else f": must be >= {_num(r.low)}"
    raise InputError(path, where, f"{_num(value)}{unit} is outside {r.text()}{hint} ({r.why})")


def check_ranges_of(obj, where: str, path: Path | None, table: dict[str, Range] | None = None) -> None:
    """:func:`check_range` on every number (and every number of a list, of lists) of a section dataclass ``obj``
    (or of a dict of its fields' values)."""
    values = obj if isinstance(obj, dict) else {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    for name, value in values.items():
        check_nested(value, f"{where}.{name}" if where else name, path, table)


def check_nested(value, where: str, path: Path | None, table: dict[str, Range] | None = None) -> None:
    """:func:`check_range` on a number or on every number of a (nested) list, named ``where[i][j]``."""
    if isinstance(value, (tuple, list)):
        for i, v in enumerate(value):
            check_nested(v, f"{where}[{i}]", path, table)
    else:
        check_range(value, where, path, table)


def check_options(command: str, args) -> None:
    """The numeric options of ``command`` (an argparse namespace ``args``) in :data:`OPTION_RANGES`; errors name
    the option (``--zone-cell``)."""
    for (cmd, dest), r in OPTION_RANGES.items():
        value = getattr(args, dest, None) if cmd == command else None
        if value is None:
            continue
        option = "--" + dest.replace("_", "-")
        for i, v in enumerate(value if isinstance(value, (tuple, list)) else (value,)):
            where = f"{option}[{i}]" if isinstance(value, (tuple, list)) else option
            check_range(v, where, None, {range_key(where): r})
