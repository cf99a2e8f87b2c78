"""What ``joint_oracle`` is told of the world (experiments/oracle_world.py): the world's tables, only for a run
that has the oracle."""

from __future__ import annotations

import math
from pathlib import Path

from experiments.config import load_config
from experiments.oracle_world import oracle_world

ROOT = Path(__file__).resolve().parents[2]
#: The realistic presets' world before they took the satellite receiver: the "field" model, every field key at
#: its default (the values the presets wrote out).
FIELD_WORLD = {"gnss_error.model": "field"}


def test_realistic_preset_tells_the_field_model_and_the_first_fix():
    cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml",
                      overrides={"run.methods": ["gnss", "joint_oracle"], **FIELD_WORLD})
    w = oracle_world(cfg)
    ge = cfg.gnss_error
    assert (w.gnss, w.nlos) == ("field", True)
    assert (w.common_share, w.common_tau_s, w.field_share) == (ge.common_share, ge.common_tau_s, ge.field_share)
    assert (w.tau_s, w.local_corr_length_m, w.field_corr_length_m) == (ge.tau_s, ge.local_corr_length_m,
                                                                        ge.field_corr_length_m)
    assert w.vehicle_dim == 8 and w.common_dim == 2  # p, v, local GNSS error, accelerometer bias; common
    i = cfg.inertial
    assert (w.accel_turn_on_sigma, w.accel_bias_sigma, w.accel_bias_tau_s) == (
        i.accel_turn_on_sigma, i.accel_bias_sigma, i.accel_bias_tau_s)


def test_paper_config_is_white_and_only_with_the_oracle():
    cfg = load_config(ROOT / "experiments" / "arterial_tlr.toml")
    assert oracle_world(cfg) is None  # not among the methods: nothing read
    cfg = load_config(ROOT / "experiments" / "arterial_tlr.toml", overrides={"run.methods": ["joint_oracle"]})
    w = oracle_world(cfg)
    assert (w.gnss, w.nlos, w.vehicle_dim, w.common_dim, w.imu) == ("white", False, 4, 0, False)


def test_front_lever_is_half_the_net_folders_vehicle_length(tmp_path):
    """The oracle is told the world's kinematics: SUMO reports the front bumper and the body axis, so a turning
    bumper moves sideways at half the vehicle's length times the yaw rate. The arterial's vType car is 4.5 m
    long (sumo_nets/arterial/demand.rou.xml); a route file without a vType gets SUMO's default 5 m."""
    from experiments.oracle_world import _route_vtype_lengths

    cfg = load_config(ROOT / "experiments" / "arterial_tlr.toml", overrides={"run.methods": ["joint_oracle"]})
    assert oracle_world(cfg).front_lever_m == 2.25
    f = tmp_path / "r.rou.xml"
    f.write_text('<routes><vType id="a" length="4.0"/><vType id="p" vClass="pedestrian" length="0.2"/>'
                 '<vType id="b"/><vehicle id="x" depart="0"/><vType id="late" length="99"/></routes>')
    assert _route_vtype_lengths(f) == [4.0, 5.0]


def test_no_front_lever_when_the_world_reports_the_centre():
    """[scenario] reference_point = "centre" (the realistic presets): the reported point moves with the
    reported velocity, no slip to model."""
    cfg = load_config(ROOT / "experiments" / "arterial_tlr.toml",
                      overrides={"run.methods": ["joint_oracle"], "scenario.reference_point": "centre"})
    assert oracle_world(cfg).front_lever_m == 0.0
    cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml",
                      overrides={"run.methods": ["joint_oracle"], **FIELD_WORLD})
    assert cfg.scenario.reference_point == "centre" and oracle_world(cfg).front_lever_m == 0.0


def test_per_vehicle_world_has_no_shared_part():
    cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml",
                      overrides={"run.methods": ["joint_oracle"], "gnss_error.model": "per_vehicle",
                                 "scenario.start": "fast_start"})
    w = oracle_world(cfg)
    assert (w.gnss, w.common_dim, w.field_share) == ("per_vehicle", 0, 0.0)
    assert math.isinf(w.local_corr_length_m)


def test_field_coefficient_states_reproduce_the_worlds_field():
    """The oracle carries the world's field as coefficient states on the world's own frequencies: with the
    world's coefficients, its basis gives the world's field at any point (to rounding), and another seed's
    frequencies do not."""
    import numpy as np

    from couplers.sensing.gnss_error import FieldErrorProcess

    cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml",
                      overrides={"run.methods": ["joint_oracle"], "run.seed": 7, **FIELD_WORLD})
    w = oracle_world(cfg)
    assert w.field_dim == 4 * cfg.gnss_error.field_features and w.tail_dim == 2 + w.field_dim
    proc = FieldErrorProcess(cfg.gnss_error, 7, 0.75)
    xy = np.random.default_rng(0).uniform(-500, 2000, (40, 2))
    world = proc.field_at(xy)
    mine = np.einsum("nak,k->na", w.field_basis(xy), proc.coef.ravel())
    assert np.allclose(mine, world, atol=1e-12)
    other = FieldErrorProcess(cfg.gnss_error, 8, 0.75)
    assert not np.allclose(np.einsum("nak,k->na", w.field_basis(xy), other.coef.ravel()), other.field_at(xy),
                           atol=1e-3)


def test_satellite_world_tells_the_receivers_structure_and_turns_the_channel_on():
    """The presets' satellite receiver: the oracle is told the constellation's size, the satellites' common
    errors and the receiver's own (the [gnss_error] values), and only a run with the oracle gets the channel."""
    from couplers.sensing.gnss_sky import Sky
    from experiments.oracle_world import NLOS_D_MEAN_M, oracle_sensors

    plain = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml")
    assert oracle_world(plain) is None and oracle_sensors(plain) is plain.sensors
    assert not plain.sensors.gnss_error.oracle_channel
    cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml", overrides={"run.methods": ["joint_oracle"]})
    ge = cfg.gnss_error
    assert ge.model == "satellites" and ge.nlos == "reflect"
    w = oracle_world(cfg)
    assert (w.gnss, w.sv_count, w.satellite_dim) == ("satellites", Sky.build().size, 2 * Sky.build().size + 1)
    assert (w.sv_tau_s, w.sv_clock_orbit_m, w.iono_vertical_m, w.tropo_zenith_m) == (
        ge.sv_tau_s, ge.sv_clock_orbit_m, ge.iono_vertical_m, ge.tropo_zenith_m)
    assert (w.code_noise_a_m, w.multipath_m, w.multipath_corr_length_m) == (ge.code_noise_a_m, ge.multipath_m,
                                                                            ge.multipath_corr_length_m)
    assert w.nlos_d_mean_m == NLOS_D_MEAN_M > 0 and not w.nlos  # no gate: the reflected signals are told
    assert w.tail_dim == w.satellite_dim and w.common_dim == w.field_dim == 0
    assert oracle_sensors(cfg).gnss_error.oracle_channel and not cfg.sensors.gnss_error.oracle_channel


def _with_oracle_table(tmp_path, channel: str | None):
    text = (f'extends = "{(ROOT / "experiments" / "arterial_tlr_realistic.toml").resolve()}"\n'
            '[run]\nmethods = ["gnss", "joint_oracle"]\n')
    if channel is not None:
        text += f'[oracle]\ngnss_channel = "{channel}"\n'
    path = tmp_path / f"cfg_{channel}.toml"
    path.write_text(text)
    return load_config(path)


def test_fix_channel_tells_the_fix_level_world_and_leaves_the_frames_alone(tmp_path):
    """[oracle] gnss_channel = "fix": the fix-level world (one common state, the local error sized by the
    calibrated report, the gate on, the satellites' correlation time) and the frames of a run without the oracle
    (no channel); "receiver" is the table's absence (the oracle as before, byte for byte)."""
    from experiments.oracle_world import FIX_COMMON_SIGMA_M, FIX_LOCAL_SCALE, oracle_sensors

    absent, receiver, fix = (_with_oracle_table(tmp_path, c) for c in (None, "receiver", "fix"))
    assert oracle_world(absent) == oracle_world(receiver)
    assert oracle_world(absent).field_omega == oracle_world(receiver).field_omega  # compare=False field
    assert oracle_sensors(receiver).gnss_error.oracle_channel
    w = oracle_world(fix)
    assert (w.gnss, w.common_dim, w.satellite_dim, w.tail_dim) == ("fix", 2, 0, 2)
    assert w.fix_common_sigma_m == FIX_COMMON_SIGMA_M and w.fix_local_scale == FIX_LOCAL_SCALE
    assert w.common_tau_s == fix.gnss_error.sv_tau_s and w.nlos and w.gate_threshold < math.inf
    assert w.vehicle_dim == oracle_world(receiver).vehicle_dim  # the same block layout: [p, v, l, bias]
    assert oracle_sensors(fix) is fix.sensors and not fix.sensors.gnss_error.oracle_channel
