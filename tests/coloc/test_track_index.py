"""The candidate index (coloc/kernels/track_index.py) and the P_D kernel (coloc/kernels/detection.py)
against their numpy references: the same (vehicle, track) pairs in the same order as the full test,
and the same P_D byte for byte, on random city-like scenes with a few wide tracks, NaN and inf
positions and spreads, standing vehicles and tracks on a sensor's boundary."""

from __future__ import annotations

import numpy as np
import pytest

from coloc.core.detection import DetectionModel, expected_detection_probability
from coloc.kernels import icp_fused
from coloc.kernels.detection import detection_probability_pairs
from coloc.kernels.track_index import N_SPREAD_CLASSES, candidate_pairs_kernel, candidate_tracks
from coloc.methods.icp_da_lc import DENSE_PAIRS_MAX, LcParams, association_weights, candidate_pairs


def _spd(rng, k, scale):
    a = rng.normal(size=(k, 4, 4)) * 0.3
    return a @ np.swapaxes(a, 1, 2) + np.diag([1.0, 1.0, 0.1, 0.1]) * scale[:, None, None]


def _city(seed: int, n_v: int = 60, n_t: int = 900, odd: bool = True):
    """Vehicles and tracks over 3 km x 2 km; track spreads over 10 orders of magnitude (most narrow, a
    few km wide); with ``odd`` NaN/inf positions and spreads on some of each."""
    rng = np.random.default_rng(seed)
    v_mean = np.c_[rng.uniform(0, 3000, n_v), rng.uniform(0, 2000, n_v), rng.normal(0, 8, (n_v, 2))]
    v_mean[:5, 2:] = rng.normal(0, 0.3, (5, 2))  # standing: heading unknown
    t_mean = np.c_[rng.uniform(0, 3000, n_t), rng.uniform(0, 2000, n_t), rng.normal(0, 0.1, (n_t, 2))]
    near = rng.integers(0, n_v, n_t // 3)  # a third of the tracks near a vehicle
    t_mean[: near.size, :2] = v_mean[near, :2] + rng.normal(0, 40, (near.size, 2))
    t_cov = _spd(rng, n_t, 10.0 ** rng.uniform(-2, 1, n_t))
    t_cov[rng.choice(n_t, 6, replace=False)] *= 10.0 ** rng.uniform(3, 8, 6)[:, None, None]  # a few wide ones
    v_cov = _spd(rng, n_v, 10.0 ** rng.uniform(-1, 1.5, n_v))
    if odd:
        t_mean[3, 0], t_mean[5, 1], t_mean[8, 0], t_mean[9] = np.nan, np.inf, -np.inf, np.nan
        t_cov[11, 0, 0], t_cov[12, 1, 1], t_cov[13, 0, 0] = np.inf, np.nan, -50.0
        v_mean[7, 0], v_mean[8, 1], v_mean[9, 2] = np.nan, np.inf, np.nan
        v_cov[10, 0, 0], v_cov[11, 1, 1] = np.inf, np.nan
    return v_mean, v_cov, t_mean, t_cov


def _reference_pairs(v_mean, v_cov, t_mean, t_cov, rs, monkeypatch):
    monkeypatch.setattr(icp_fused, "FUSED", False)
    assert v_mean.shape[0] * t_mean.shape[0] <= DENSE_PAIRS_MAX  # the dense full test
    with np.errstate(invalid="ignore", over="ignore"):
        return candidate_pairs(v_mean, v_cov, t_mean, t_cov, LcParams(sensing_range_m=rs))


@pytest.mark.parametrize("seed", range(10))
def test_candidate_pairs_equal_the_full_test(seed, monkeypatch):
    scene = _city(seed, odd=seed % 2 == 1)
    rs = (30.0, 75.0, 200.0)[seed % 3]
    vi0, ti0 = _reference_pairs(*scene, rs, monkeypatch)
    with np.errstate(invalid="ignore"):
        vi, ti = candidate_pairs_kernel(*scene, rs)
    assert vi.tobytes() == vi0.tobytes() and ti.tobytes() == ti0.tobytes()
    assert 0 < vi.size < scene[0].shape[0] * scene[2].shape[0] // 4  # a city: most pairs are out of range
    monkeypatch.setattr(icp_fused, "FUSED", True)  # the dispatch in icp_da_lc
    vi1, ti1 = candidate_pairs(*scene, LcParams(sensing_range_m=rs))
    assert vi1.tobytes() == vi0.tobytes() and ti1.tobytes() == ti0.tobytes()


def test_every_spread_class_and_an_overflowing_reach(monkeypatch):
    """Tracks in every spread class (the last one past 4^15 m^2), one spread near the float maximum
    (its class's reach overflows to inf: the whole class is scanned) and vehicles over it."""
    v_mean, v_cov, t_mean, t_cov = _city(7, n_v=40, n_t=400, odd=False)
    tr = 4.0 ** np.arange(-1, N_SPREAD_CLASSES + 2)
    for j, x in enumerate(tr):
        t_cov[20 + j] = np.diag([x / 2, x / 2, 0.01, 0.01])
    t_cov[60] = np.diag([5e307, 5e307, 0.01, 0.01])  # with vehicle 0's spread the sum overflows
    t_cov[61] = np.diag([1e300, 1e300, 0.01, 0.01])
    v_cov[0] = np.diag([5e307, 5e307, 1.0, 1.0])
    scene = (v_mean, v_cov, t_mean, t_cov)
    vi0, ti0 = _reference_pairs(*scene, 75.0, monkeypatch)
    with np.errstate(invalid="ignore", over="ignore"):
        start, track = candidate_tracks(*scene, 75.0)
    assert start[-1] == track.size == ti0.size and track.tobytes() == ti0.tobytes()
    assert np.array_equal(np.diff(start), np.bincount(vi0, minlength=v_mean.shape[0]))
    assert (ti0 == 60).sum() == v_mean.shape[0]  # the widest track is every vehicle's candidate


def test_no_tracks_no_vehicles():
    e4, e44 = np.empty((0, 4)), np.empty((0, 4, 4))
    one, one_cov = np.zeros((1, 4)), np.eye(4)[None]
    for args in [(e4, e44, one, one_cov), (one, one_cov, e4, e44), (e4, e44, e4, e44)]:
        vi, ti = candidate_pairs_kernel(*args, 75.0)
        assert vi.size == ti.size == 0


def _model(kind: int) -> DetectionModel:
    if kind == 0:  # the realistic preset's front radar and surround
        return DetectionModel((90.0, 360.0), (70.0, 30.0), (0.0, 0.0), (0.0, 0.0), (0.95, 0.95), (0.7, 0.7),
                              visibility=0.6)
    return DetectionModel((90.0, 120.0, 45.0), (70.0, 40.0, 25.0), (0.0, 180.0, -30.0), (2.0, -1.5, 0.5),
                          (0.95, 0.9, 0.8), (0.7, 0.5, 0.8), heading_min_speed=0.5, visibility=1.0)


@pytest.mark.parametrize("seed", range(6))
def test_detection_probability_of_pairs_equals_the_reference(seed):
    model = _model(seed % 2)
    v_mean, v_cov, t_mean, t_cov = _city(300 + seed, n_v=80, n_t=600, odd=seed >= 2)
    with np.errstate(invalid="ignore"):
        vi, ti = candidate_pairs_kernel(v_mean, v_cov, t_mean, t_cov, 80.0)
    rng = np.random.default_rng(seed)
    # tracks on the vehicle, on a range boundary and on the field-of-view edge of the front sensor
    extra_v = rng.integers(10, 80, 6)
    t_mean[:6, :2] = v_mean[extra_v, :2]
    t_mean[6, :2] = v_mean[extra_v[0], :2] + [model.range_m[0], 0.0]
    vi = np.r_[vi, extra_v, extra_v[0], rng.integers(0, 80, 500)]
    ti = np.r_[ti, np.arange(6), 6, rng.integers(0, 600, 500)]
    with np.errstate(invalid="ignore", divide="ignore"):
        ref = expected_detection_probability(v_mean[vi], t_mean[ti, :2], model)
        got = detection_probability_pairs(v_mean, t_mean, vi, ti, model)
    assert got.tobytes() == ref.tobytes()
    assert 0.05 < (ref > 0).mean() < 0.95  # pairs in and out of view


@pytest.mark.parametrize("seed", range(4))
def test_weights_with_a_detection_model_equal_the_numpy_reference(seed, monkeypatch):
    """association_weights' P_D of the gated pairs (the pairs kernel) and the candidate index together."""
    rng = np.random.default_rng(400 + seed)
    v_mean, v_cov, t_mean, t_cov = _city(400 + seed, n_v=50, n_t=500, odd=False)
    owner = rng.integers(0, 50, 500)
    z = np.c_[rng.uniform(-60, 60, (500, 2)), -v_mean[owner, 2:] + rng.normal(0, 0.1, (500, 2))]
    d = np.hypot(*(t_mean[None, :, :2] - v_mean[owner][:, None, :2]).transpose(2, 0, 1))
    real = rng.random(500) < 0.3
    z[real] = t_mean[np.argmin(d, axis=1)[real]] - v_mean[owner[real]] + rng.normal(0, 0.3, (real.sum(), 4))
    r = _spd(rng, 500, np.full(500, 0.3))
    lc = LcParams(sensing_range_m=75.0, clutter_intensity=3.35e-4)
    out = {}
    for fused in (False, True):
        monkeypatch.setattr(icp_fused, "FUSED", fused)
        out[fused] = association_weights(v_mean, v_cov, t_mean, t_cov, owner, z, r, lc, _model(seed % 2))
    for x, y in zip(out[False], out[True]):
        assert x.shape == y.shape and x.tobytes() == y.tobytes()
    assert (out[True][3] > 0).sum() > 20
