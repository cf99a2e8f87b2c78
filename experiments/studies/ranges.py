"""Physical ranges of the numbers of the study configs (a ``[study]`` table; experiments/studies/), as
:data:`experiments.ranges.RANGES` holds those of a run config.

rsu_bp's keys are the fields of its dataclasses (loaded by :func:`experiments.config.section_from_table`),
sme's and fg_topology's those of their ``SPEC`` (:func:`experiments.studies.study_config.resolve`);
``tests/experiments/test_ranges.py`` checks that every number of each has a range.
"""

from __future__ import annotations

from experiments.ranges import (ACCEL, ITER, LENGTH, NO_UNIT, PARTICLES_MAX, PARTICLES_WHY, RANGES, SIGMA_MPS, SPEED,
                                STEP, WORKERS, Range)

SEED = RANGES["run.seed"]
RUNS = Range(1, 100_000, NO_UNIT, "Monte Carlo runs: 1e5 already take days")
STEPS = Range(1, 1_000_000, NO_UNIT, "steps of one run")
VAR_M2 = Range(0.0, 1e6, "m^2", "a variance of (1 km)^2", low_open=True)
INTENSITY = Range(0.0, 1e4, "m^2/s^3", "a white-acceleration intensity of (100 m/s^2)^2 s", low_open=True)
COUNT_RUNS = Range(0, 100_000, NO_UNIT, "Monte Carlo runs: 1e5 already take days")
STUDY_RANGES: dict[str, dict[str, Range]] = {
    "rsu_bp": {
        "study.seed": SEED,
        "study.runs": RUNS,
        "study.workers": WORKERS,
        "study.init_spread": Range(1.0, 1e6, NO_UNIT, "a factor on a covariance"),
        "study.scenario.n_steps": STEPS,
        "study.scenario.dt": STEP,
        "study.scenario.process_intensity": INTENSITY,
        "study.scenario.gnss_var": VAR_M2,
        "study.scenario.v2f_var": VAR_M2,
        "study.scenario.n_features": Range(0, 10_000, NO_UNIT, "features around one RSU"),
        "study.scenario.init_var": VAR_M2,
        "study.filter.n_particles": Range(2, PARTICLES_MAX, NO_UNIT, PARTICLES_WHY),
        "study.filter.da_iterations": ITER,
        "study.filter.correction_iterations": ITER,
        "study.filter.dt": STEP,
        "study.filter.process_intensity": INTENSITY,
        "study.filter.vehicle_init_velocity_std": SIGMA_MPS,
        "study.filter.feature_init_velocity_std": SIGMA_MPS,
        "study.sweep.v2f_var": VAR_M2,
        "study.sweep.v2f_var_runs": COUNT_RUNS,
        "study.sweep.n_features": Range(0, 10_000, NO_UNIT, "features around one RSU"),
        "study.sweep.n_features_runs": COUNT_RUNS,
    },
    "sme": {
        "study.seed": SEED,
        "study.runs": RUNS,
        "study.n_steps": STEPS,
        "study.example_run": COUNT_RUNS,
        "scenario.initial_state": Range(-1e7, 1e7, "m, m/s", "net coordinates within 10,000 km"),
        "scenario.dt": STEP,
        "scenario.process_sigma": ACCEL,
        "scenario.prior_pos_var": VAR_M2,
        "scenario.prior_vel_var": Range(0.0, 1e4, "m^2/s^2", "a velocity variance of (100 m/s)^2", low_open=True),
        "scenario.sensor_poses": Range(-1e7, 1e7, "m, m, deg", "net coordinates within 10,000 km"),
        "sensors.gps_var": VAR_M2,
        "sensors.sensor_var": VAR_M2,
    },
    "fg_topology": {
        "study.seed": SEED,
        "study.runs": RUNS,
        "study.vehicles": Range(2, 1000, NO_UNIT, "vehicles of one factor graph"),
        "study.workers": WORKERS,
        "study.example_run": COUNT_RUNS,
        "scenario.n_steps": STEPS,
        "scenario.dt": STEP,
        "scenario.accel_sigma": ACCEL,
        "scenario.start_box_m": LENGTH,
        "scenario.speed_min": SPEED,
        "scenario.speed_max": SPEED,
        "scenario.sensor_box_m": Range(0.0, 1e5, "m", "100 km: a city scenario"),
        "sensors.odom_var": VAR_M2,
        "sensors.gps_var": VAR_M2,
        "sensors.radar_var": VAR_M2,
        "solver.max_iterations": ITER,
        "solver.relative_error_tol": Range(0.0, 1.0, NO_UNIT, "a relative error", low_open=True),
        "solver.absolute_error_tol": Range(0.0, 1e6, NO_UNIT, "a squared error of the factor graph", low_open=True),
    },
}
