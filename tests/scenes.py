"""Scenes shared by the tests: frames without SUMO, and the frame edits the estimator contracts
need (truth scrambled, vehicles removed, added or reordered).

* :func:`road_frames`: vehicles driving east on one lane by model (1), static features on both
  sides, measurements by ``couplers.sensing.sensors`` (seeded); with ``inertial`` the body-frame IMU of
  ``couplers.sensing.inertial`` (``frame.imu``, ``frame.accel`` NaN) as the SUMO coupler makes it.
* :func:`infra_frames`: vehicles along the x axis (two lanes, both directions) through the range
  of one or two road-side units, static features along the road; measurements from the coupler's
  own synthesis (``couplers.sensing.sensors.synthesize_frame``, ``couplers.sensing.infra.InfraSynth``).
* :func:`scrambled`, :func:`select_vehicles`: edits of a frame.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from coloc.core.frame import Frame
from coloc.core.inertial import ImuFrame
from coloc.core.models import input_matrix, transition_matrix
from couplers.sensing.inertial import InertialParams, InertialProcess
from couplers.sensing.infra import InfraSetup, InfraSynth
from couplers.sensing.sensors import SensorNoise, SensorParams, synthesize_frame


def road_frames(seed=1, n=5, steps=15, n_feat=4, v2f_range=30.0, v2v_range=250.0, gnss_sp=8.0, gnss_sv=0.2,
             leave=None, enter=None, spacing=10.0, inertial: InertialParams | None = None,
                accel_sigma: float = SensorParams.accel_sigma):
    """Frames of n vehicles 10 m apart at 10 m/s east; features at x = 20, 50, ... y = +-6 m.

    ``leave=(i, t)``: vehicle i is gone from step t on; ``enter=(i, t)``: vehicle i appears at step t.
    ``inertial``: frames carry the body-frame IMU (``[inertial]``) and a NaN ``accel``.
    """
    rng = np.random.default_rng(seed)
    dt = 1.0
    a_mat, b_mat = transition_matrix(dt), input_matrix(dt)
    x = np.zeros((n, 4))
    x[:, 0] = np.arange(n) * spacing
    x[:, 2] = 10.0
    feats = np.zeros((n_feat, 4))
    feats[:, 0] = 20 + 30 * np.arange(n_feat)
    feats[:, 1] = np.where(np.arange(n_feat) % 2, -6.0, 6.0)
    tree = cKDTree(feats[:, :2])
    params = SensorParams(v2f_range_m=v2f_range, v2v_range_m=v2v_range, accel_sigma=accel_sigma)
    noise = SensorNoise(seed)
    imu = InertialProcess(inertial, seed, dt) if inertial is not None else None
    ids = np.array([f"v{i}" for i in range(n)], dtype=object)
    frames = []
    for t in range(steps):
        acc = np.zeros((n, 2))
        acc[:, 0] = rng.normal(0, 0.3, n)
        if t > 0:
            x = x @ a_mat.T + acc @ b_mat.T
        entered = np.full(n, t == 0)
        cur = np.ones(n, bool)
        if leave is not None and t >= leave[1]:
            cur[leave[0]] = False
        if enter is not None:
            cur[enter[0]] = t >= enter[1]
            entered[enter[0]] = t == enter[1]
        sel = np.flatnonzero(cur)
        m = sel.size
        f = synthesize_frame(
            t=float(t), dt=dt, vehicle_ids=ids[sel], entered=entered[sel], x_true=x[sel],
            accel_true=acc[sel], heading=np.zeros(m), gnss_sigma_p=np.full(m, gnss_sp),
            gnss_sigma_v=np.full(m, gnss_sv), features_true=feats, feature_tree=tree, params=params,
            noise=noise, zone=np.full(m, "A", dtype=object), area=np.full(m, "road", dtype=object),
        )
        if imu is not None:
            f = replace(f, imu=imu.step(ids[sel], entered[sel], np.zeros(m), acc[sel]),
                        accel=np.full((m, 2), np.nan))
        frames.append(f)
    return frames


def infra_frames(n_steps=40, n_veh=6, seed=3, features=True, rsu_x=(0.0,), gnss_sigma=3.0, dt=0.75,
                 spacing=22.0, start=-90.0):
    rng = np.random.default_rng(seed + 100)
    params = SensorParams()
    noise = SensorNoise(seed)
    setup = InfraSetup(rsu_ids=tuple(f"R{i}" for i in range(len(rsu_x))),
                       rsu_xy=np.array([[x, 0.0] for x in rsu_x]), range_m=70.0, radar_sigma_m=0.3)
    synth = InfraSynth(setup, seed)
    fx = np.arange(-150.0, 151.0, 25.0)
    feats = np.stack([fx, np.full_like(fx, 12.0), 0 * fx, 0 * fx], axis=1) if features else np.empty((0, 4))
    tree = cKDTree(feats[:, :2]) if features else None
    lanes = np.where(np.arange(n_veh) % 2 == 0, -1.6, 1.6)
    direction = np.where(np.arange(n_veh) % 2 == 0, 1.0, -1.0)
    x0 = np.where(direction > 0, start, -start) - direction * spacing * (np.arange(n_veh) // 2)
    speed = 10.0 + rng.uniform(-1, 1, n_veh)
    ids = np.array([f"veh{i}" for i in range(n_veh)], dtype=object)
    frames = []
    for k in range(n_steps):
        t = k * dt
        px = x0 + direction * speed * t
        x_true = np.stack([px, lanes, direction * speed, 0 * px], axis=1)
        heading = np.where(direction > 0, 0.0, np.pi)
        f = synthesize_frame(
            t=t, dt=dt, vehicle_ids=ids, entered=np.full(n_veh, k == 0), x_true=x_true,
            accel_true=np.zeros((n_veh, 2)), heading=heading, gnss_sigma_p=np.full(n_veh, gnss_sigma),
            gnss_sigma_v=np.full(n_veh, 0.1), features_true=feats, feature_tree=tree, params=params, noise=noise,
            zone=np.full(n_veh, "A", dtype=object), area=np.full(n_veh, "1", dtype=object),
        )
        infra, radar_vehicle = synth.step(ids, f.entered, x_true[:, :2])
        frames.append(replace(f, infra=infra, truth=replace(f.truth, radar_vehicle=radar_vehicle)))
    return frames


def scrambled(frame: Frame, rng: np.random.Generator) -> Frame:
    """The frame with every truth field replaced by noise (estimators must not notice)."""
    tr = frame.truth
    return replace(frame, truth=replace(
        tr, x_true=rng.normal(size=tr.x_true.shape), v2f_feature=rng.permutation(tr.v2f_feature),
        features_true=rng.normal(size=tr.features_true.shape), zone=tr.zone[::-1], area=tr.area[::-1],
        heading=None if tr.heading is None else rng.normal(size=tr.heading.shape),
        feature_ids=None if tr.feature_ids is None else tr.feature_ids[::-1],
        feature_class=None if tr.feature_class is None else rng.permutation(tr.feature_class),
        radar_vehicle=None if tr.radar_vehicle is None else rng.permutation(tr.radar_vehicle)))


def select_vehicles(frame: Frame, rows, entered=None) -> Frame:
    """The frame with only the vehicles ``rows`` of ``frame``, in that order (an empty list: no
    vehicles), with their V2F rows, links, radar detections and truth.

    ``entered`` (len(rows),) bool, default ``frame.entered[rows]``: a vehicle marked entered that
    was not entered in ``frame`` gets its GNSS fix as the fast-start prior (and no odometry).
    """
    rows = np.asarray(rows, dtype=np.int64).reshape(-1)
    new_of_old = np.full(frame.n_vehicles, -1, dtype=np.int64)
    new_of_old[rows] = np.arange(rows.size)
    owner = new_of_old[frame.v2f_owner]
    o_idx = np.flatnonzero(owner >= 0)
    o_idx = o_idx[np.argsort(owner[o_idx], kind="stable")]  # rows grouped by vehicle, as the coupler's
    ent = frame.entered[rows].copy() if entered is None else np.asarray(entered, dtype=bool)
    prior_z, prior_r = frame.prior_z[rows].copy(), frame.prior_R[rows].copy()
    fresh = ent & ~frame.entered[rows]
    prior_z[fresh], prior_r[fresh] = frame.gnss_z[rows][fresh], frame.gnss_R[rows][fresh]
    tr = frame.truth
    truth = None
    if tr is not None:
        radar_vehicle = None
        if tr.radar_vehicle is not None:
            radar_vehicle = new_of_old[tr.radar_vehicle]
        truth = replace(
            tr, x_true=tr.x_true[rows], v2f_feature=tr.v2f_feature[o_idx], zone=tr.zone[rows], area=tr.area[rows],
            heading=None if tr.heading is None else tr.heading[rows],
            radar_vehicle=None if radar_vehicle is None else radar_vehicle[radar_vehicle >= 0])
    infra = frame.infra
    if infra is not None:
        keep = new_of_old[tr.radar_vehicle] >= 0  # the radar sees the vehicles that are there
        odom = infra.odom[rows].copy()
        odom[ent] = np.nan
        infra = replace(infra, v2i=infra.v2i[:, rows].tocsr(), radar_z=infra.radar_z[keep],
                        radar_owner=infra.radar_owner[keep], odom=odom)
    imu = None if frame.imu is None else ImuFrame(frame.imu.accel_body[rows], frame.imu.yaw_rate[rows])
    has_fix = None if frame.prior_has_fix is None else np.asarray(frame.prior_has_fix)[rows] & ent
    return replace(
        frame, imu=imu, prior_has_fix=has_fix, vehicle_ids=frame.vehicle_ids[rows], entered=ent, prior_z=prior_z, prior_R=prior_r,
        accel=frame.accel[rows], gnss_z=frame.gnss_z[rows], gnss_R=frame.gnss_R[rows], v2f_z=frame.v2f_z[o_idx],
        v2f_owner=owner[o_idx], v2f_R=frame.v2f_R[o_idx], neighbors=frame.neighbors[rows][:, rows].tocsr(),
        truth=truth, infra=infra)
