"""Frames with road-side units for the infrastructure-method tests, without SUMO.

Vehicles drive along the x axis (two lanes, both directions) through the range of one or two
RSUs; static features stand along the road. Measurements come from the coupler's own
synthesis (couplers.sensors.synthesize_frame, couplers.infra.InfraSynth).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial import cKDTree

from couplers.infra import InfraSetup, InfraSynth
from couplers.sensors import SensorNoise, SensorParams, synthesize_frame


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


def scrambled(frame, rng):
    """The frame with every truth field replaced by noise (estimators must not notice)."""
    tr = frame.truth
    return replace(frame, truth=replace(
        tr, x_true=rng.normal(size=tr.x_true.shape), v2f_feature=rng.permutation(tr.v2f_feature),
        features_true=rng.normal(size=tr.features_true.shape),
        radar_vehicle=rng.permutation(tr.radar_vehicle)))
