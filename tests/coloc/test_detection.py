"""The detection model an estimator expects (coloc.core.detection) against the coupler's perception
geometry (couplers.sensing.perception): same field of view, range and detection profile."""

import numpy as np
import pytest

from coloc.core.detection import expected_detection_probability
from couplers.sensing.perception import (
    DEFAULT_SENSORS,
    PerceptionParams,
    SensorSpec,
    detection_model,
    detection_probability,
    fov_candidates,
    sensor_origins,
)


def test_expected_pd_equals_the_perception_geometry_for_a_known_heading():
    """Random vehicles (speed >= 1 m/s, heading = velocity direction) and targets: P_D = 1 -
    prod_s (1 - P_D,s(d) [in the field of view of s]) with the coupler's own functions."""
    rng = np.random.default_rng(7)
    sensors = DEFAULT_SENSORS + (SensorSpec(name="rear", fov_deg=60.0, range_m=40.0, yaw_deg=180.0,
                                            mount_x_m=-4.0, pd_near=0.9, pd_far=0.5),)
    params = PerceptionParams(sensors=sensors)
    n = 4000
    xy = rng.uniform(-50, 50, (n, 2))
    heading = rng.uniform(-np.pi, np.pi, n)
    speed = rng.uniform(1.0, 15.0, n)
    v_mean = np.column_stack([xy, speed * np.cos(heading), speed * np.sin(heading)])
    target = xy + rng.uniform(-90, 90, (n, 2))
    miss = np.ones(n)
    for spec in sensors:
        rows, dist = fov_candidates(sensor_origins(xy, heading, spec), heading, np.arange(n), target, spec)
        p = np.zeros(n)
        p[rows] = detection_probability(dist, spec)
        miss *= 1.0 - p
    got = expected_detection_probability(v_mean, target, detection_model(params, 1.0))
    np.testing.assert_allclose(got, 1.0 - miss, rtol=1e-9, atol=1e-12)
    assert (got == 0).any() and (got > 0.9).any()


def test_unknown_heading_weighs_each_sensor_by_its_opening():
    """Below heading_min_speed the heading is unknown: a 120 deg sensor detects with a third of its
    profile, a 360 deg one with all of it."""
    params = PerceptionParams(sensors=(SensorSpec(name="front", fov_deg=120.0, range_m=80.0, pd_near=0.9, pd_far=0.9),
                                       SensorSpec(name="round", fov_deg=360.0, range_m=30.0, pd_near=0.6, pd_far=0.6)))
    model = detection_model(params, 1.0)
    v_mean = np.array([[0.0, 0.0, 0.2, 0.0], [0.0, 0.0, 0.0, 0.0]])
    target = np.array([[50.0, 0.0], [10.0, 5.0]])
    got = expected_detection_probability(v_mean, target, model)
    np.testing.assert_allclose(got, [0.9 / 3.0, 1.0 - (1.0 - 0.3) * (1.0 - 0.6)])


def test_visibility_scales_the_expected_detection_probability():
    """[lc] visibility v: P_D = v x (1 - prod_s (1 - P_D,s)); v = 1 is the model without it, bit for bit."""
    params = PerceptionParams(sensors=(SensorSpec(name="front", fov_deg=120.0, range_m=80.0, pd_near=0.9, pd_far=0.7),
                                       SensorSpec(name="round", fov_deg=360.0, range_m=30.0, pd_near=0.6, pd_far=0.6)))
    rng = np.random.default_rng(4)
    v_mean = np.c_[rng.uniform(-50, 50, (200, 2)), rng.normal(0, 5, (200, 2))]
    target = v_mean[:, :2] + rng.uniform(-60, 60, (200, 2))
    full = expected_detection_probability(v_mean, target, detection_model(params, 1.0))
    same = expected_detection_probability(v_mean, target, detection_model(params, 1.0, visibility=1.0))
    assert np.array_equal(full, same)
    np.testing.assert_allclose(expected_detection_probability(v_mean, target, detection_model(params, 1.0, 0.6)),
                               0.6 * full, rtol=1e-15, atol=0)
    with pytest.raises(ValueError):
        detection_model(params, 1.0, visibility=0.0)
