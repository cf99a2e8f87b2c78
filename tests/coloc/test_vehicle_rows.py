"""Rows the classifier labels as vehicles never become landmark tracks (coloc.core.vehicle_rows): ICP-DA-LC and
ICP known DA give the same estimate, to the byte, with and without them, and leave them unassigned; the
estimators' sensor model comes from [estimator_sensors], not from [perception]."""

from dataclasses import replace
from pathlib import Path

import numpy as np

from coloc.core.models import MotionParams
from coloc.core.vehicle_rows import CLASS_VEHICLE
from coloc.inference.params import IcpParams
from coloc.methods.icp_da_lc import IcpDaLc, LcParams
from coloc.methods.icp_known_da import IcpKnownDA
from netfixture import arterial_config
from scenes import road_frames

MOTION = MotionParams(sigma_along=0.08, sigma_cross=0.08)


def _with_vehicle_rows(frame, rng):
    """The frame with, per vehicle, a detection of the vehicle ahead (class vehicle, truth -1) inserted at
    random places; the frame's own rows class static."""
    o = frame.v2f_z.shape[0]
    n = frame.n_vehicles
    owner = np.arange(n - 1)
    rel = frame.truth.x_true[owner + 1] - frame.truth.x_true[owner]
    z = rel + rng.normal(0, 0.1, rel.shape)
    all_owner = np.concatenate([frame.v2f_owner, owner])
    order = np.argsort(all_owner, kind="stable")  # the frame's rows in their order, then the vehicle rows
    R = np.concatenate([frame.v2f_R, np.broadcast_to(np.diag([0.01, 0.01, 0.01, 0.01]), (owner.size, 4, 4))])
    cls = np.concatenate([np.zeros(o, np.int8), np.full(owner.size, CLASS_VEHICLE, np.int8)])
    feat = np.concatenate([frame.truth.v2f_feature, np.full(owner.size, -1)])
    out = replace(frame, v2f_z=np.concatenate([frame.v2f_z, z])[order], v2f_owner=all_owner[order],
                  v2f_R=R[order], v2f_class=cls[order], truth=replace(frame.truth, v2f_feature=feat[order]))
    return out, order >= o


def test_vehicle_rows_never_become_landmark_tracks():
    frames = road_frames(steps=10)
    rng = np.random.default_rng(7)
    plain = [replace(f, v2f_class=np.zeros(f.v2f_z.shape[0], np.int8)) for f in frames]
    mixed = [_with_vehicle_rows(f, rng) for f in plain]
    params = IcpParams(motion=MOTION)
    for make in (lambda: IcpDaLc(params=params, lc=LcParams()), lambda: IcpKnownDA(params=params)):
        a, b = make(), make()
        for f, (g, is_vehicle) in zip(plain, mixed):
            if isinstance(a, IcpKnownDA):
                ea = a.step_with_association(f, f.truth.v2f_feature)
                # a vehicle row handed a landmark's index (as if the oracle had one) is still dropped
                assoc = np.where(is_vehicle, 0, g.truth.v2f_feature)
                eb = b.step_with_association(g, assoc)
            else:
                ea, eb = a.step(f.without_truth()), b.step(g.without_truth())
            assert ea.mean.tobytes() == eb.mean.tobytes() and ea.cov.tobytes() == eb.cov.tobytes()
            assert np.array_equal(ea.feature_track_ids, eb.feature_track_ids)
            assert eb.v2f_assignment.shape == (g.v2f_z.shape[0],)
            assert np.all(eb.v2f_assignment[is_vehicle] == -1)
            assert np.array_equal(eb.v2f_assignment[~is_vehicle], ea.v2f_assignment)


ESTIMATOR = ("[estimator_sensors]\n[[estimator_sensors.sensors]]\nname = 'radar'\nfov_deg = 90.0\nrange_m = 70.0\n"
             "pd_near = 0.9\npd_far = 0.6\nclutter_per_scan = 1.0\n[[estimator_sensors.sensors]]\nname = 'around'\n"
             "fov_deg = 360.0\nrange_m = 30.0\nclutter_per_scan = 1.0\n")


def _perception(fov, rng_m, pd):
    return ("[lc]\nsensor_fov = true\n[perception]\n[[perception.sensors]]\nname = 'front'\n"
            f"fov_deg = {fov}\nrange_m = {rng_m}\npd_near = {pd}\npd_far = {pd}\nclutter_per_scan = 3.0\n")


def test_estimators_read_estimator_sensors_not_perception():
    from experiments.config import config_from_dict
    from experiments.config_toml import config_to_toml
    import tomllib

    from experiments.runner import estimator_detection_model, method_params

    models, lcs = [], []
    for fov, rng_m, pd in ((120.0, 80.0, 0.95), (60.0, 150.0, 0.5)):
        cfg = config_from_dict(arterial_config(_perception(fov, rng_m, pd) + ESTIMATOR), Path("/x/cfg.toml"))
        models.append(estimator_detection_model(cfg))
        lcs.append(cfg.lc)
        assert method_params(cfg).detection == models[-1]
        again = config_from_dict(tomllib.loads(config_to_toml(cfg, {"git": "test"})), Path("/x/cfg.toml"))
        assert again.lc == cfg.lc and again.estimator_sensors == cfg.estimator_sensors
    assert models[0] == models[1] and lcs[0] == lcs[1]  # the world's sensors changed, the estimator's model did not
    m = models[0]
    assert m.fov_deg == (90.0, 360.0) and m.range_m == (70.0, 30.0) and m.pd_near == (0.9, 0.95)
    # clutter: 2 per scan over the union of a 90 deg / 70 m sector and a 30 m disc (exact 5969 m^2)
    exact = np.pi * 70**2 / 4 + np.pi * 30**2 - np.pi * 30**2 / 4
    assert abs(lcs[0].clutter_intensity - 2.0 / exact) / (2.0 / exact) < 1e-3
    assert lcs[0].sensing_range_m == 70.0
    # without [estimator_sensors]: the [perception] sensors as before
    plain = config_from_dict(arterial_config(_perception(60.0, 150.0, 0.5)), Path("/x/cfg.toml"))
    assert estimator_detection_model(plain).range_m == (150.0,)


def test_detections_by_kind_from_the_truth():
    """summary.json ``detections``: Truth.v2f_kind when set, else features (pedestrians by class) and clutter."""
    from coloc.core.frame import Truth
    from experiments.runner import DETECTION_KINDS, detection_kinds

    base = dict(x_true=np.zeros((1, 4)), features_true=np.zeros((3, 4)), zone=np.array(["A"]),
                area=np.array(["a"]))
    t = Truth(v2f_feature=np.array([0, -1, 2, -1, 1]), feature_class=np.array([0, 0, 1], np.int8), **base)
    assert dict(zip(DETECTION_KINDS, detection_kinds(t).tolist())) == {
        "landmark": 2, "clutter": 2, "persistent_clutter": 0, "vehicle": 0, "pedestrian": 1}
    t = Truth(v2f_feature=np.array([0, -1, -1, -1]), v2f_kind=np.array([0, 3, 2, 3], np.int8), **base)
    assert detection_kinds(t).tolist() == [1, 0, 1, 2, 0]
