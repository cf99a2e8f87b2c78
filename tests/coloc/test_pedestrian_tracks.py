"""Feature tracks with a class (SUMO pedestrians, Frame.v2f_class): model (2) with the class's noise,
uniform velocity at birth for pedestrians, class-gated association in ICP-DA-LC."""

from dataclasses import replace

import numpy as np

from coloc.core.models import feature_noise_cov
from coloc.inference.feature_store import FeatureStore, feature_track_q
from coloc.inference.gaussian import to_information
from coloc.inference.params import CLASS_PEDESTRIAN, CLASS_STATIC, IcpParams
from coloc.methods.icp_da_lc import IcpDaLc, LcParams
from coloc.methods.icp_known_da import IcpKnownDA
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION

PARAMS = IcpParams(motion=MOTION, feature_sigma_par=0.001, pedestrian_sigma_par=0.05)


def _closed_form_q(s_par, s_perp, vx, vy, dt):
    """Q_F = G R(theta) diag(s_par^2, s_perp^2) R(theta)^T G^T, G = [dt I; I] (model (2))."""
    th = np.arctan2(vy, vx)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    c = rot @ np.diag([s_par**2, s_perp**2]) @ rot.T
    g = np.vstack([dt * np.eye(2), np.eye(2)])
    return g @ c @ g.T


def test_q_follows_the_track_class():
    mean = np.array([[0, 0, 1.3, 0.0], [5, 5, 0.0, -1.2], [1, 1, 0, 0]])
    dt = 0.75
    q = feature_track_q(mean, dt, PARAMS, np.array([CLASS_STATIC, CLASS_PEDESTRIAN, CLASS_PEDESTRIAN], np.int8))
    np.testing.assert_allclose(q[0], _closed_form_q(0.001, 0.0005, 1.3, 0.0, dt), atol=1e-15)
    np.testing.assert_allclose(q[1], _closed_form_q(0.05, 0.025, 0.0, -1.2, dt), atol=1e-15)
    np.testing.assert_allclose(q[2], _closed_form_q(0.05, 0.05, 1, 0, dt), atol=1e-15)  # still: isotropic
    # without classes: every track static, exactly as before
    np.testing.assert_array_equal(feature_track_q(mean, dt, PARAMS),
                                  feature_noise_cov(np.where(np.hypot(*mean[:, 2:].T)[:, None] < 0.5, 0, mean[:, 2:]),
                                                    dt, 0.001, 0.0005))


def test_predict_of_a_pedestrian_track_adds_the_pedestrian_noise():
    cov = np.diag([0.04, 0.04, 0.01, 0.01])
    mean = np.array([[10.0, 2.0, 0.0, 1.4], [20.0, 2.0, 0.0, 1.4]])
    lam, eta = to_information(mean, np.stack([cov, cov]))
    store = FeatureStore().record(np.array([1, 2]), np.array(["v0", "v0"], dtype=object), lam, eta, 0.0, PARAMS,
                                  row_class=np.array([CLASS_STATIC, CLASS_PEDESTRIAN], np.int8))
    np.testing.assert_array_equal(store.klass, [CLASS_STATIC, CLASS_PEDESTRIAN])
    dt = 0.5
    pred = store.predict(dt, PARAMS)
    f = np.block([[np.eye(2), dt * np.eye(2)], [np.zeros((2, 2)), np.eye(2)]])
    m, p = store.moments(PARAMS)
    m2, p2 = pred.moments(PARAMS)
    static_q = _closed_form_q(0.001, 0.0005, 0.0, 1.4, dt)
    ped_q = _closed_form_q(0.05, 0.025, 0.0, 1.4, dt)
    # the landmark keeps its velocity prior N(0, s^2) only if given; here none: moments are the message's
    np.testing.assert_allclose(p2[0], f @ p[0] @ f.T + static_q, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(p2[1], f @ p[1] @ f.T + ped_q, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m2[1], f @ m[1], atol=1e-9)
    # merges and drops keep the classes aligned with the ids
    assert list(pred.drop(np.array([1])).klass) == [CLASS_PEDESTRIAN]


def test_pedestrian_tracks_are_born_without_the_landmark_velocity_prior():
    params = replace(PARAMS, feature_velocity_prior_sigma=0.1)
    lam, eta = FeatureStore().prior_information(np.array([3, 4]), np.array([3, 4]), np.array(["a", "b"], object),
                                                params, row_class=np.array([CLASS_STATIC, CLASS_PEDESTRIAN], np.int8))
    np.testing.assert_allclose([lam[0, 2, 2], lam[0, 3, 3]], 100.0)
    assert not lam[1].any()


def _classed(frames, klass_of_feature):
    """The frames with v2f_class = the class of each row's true feature."""
    return [replace(f, v2f_class=klass_of_feature[f.truth.v2f_feature].astype(np.int8)) for f in frames]


def test_a_row_only_pairs_with_tracks_of_its_class():
    """By construction: the first steps label every feature static (tracks are born static); from
    step 8 on the same features, at the same places, are labelled pedestrians. No pedestrian row may
    take a static track: they start pedestrian tracks, and every pairing matches the classes."""
    frames = road_frames(seed=1, steps=16, v2v_range=25.0)
    n_feat = 4
    static = _classed(frames[:8], np.zeros(n_feat, np.int8))
    peds = _classed(frames[8:], np.ones(n_feat, np.int8))
    est = IcpDaLc(PARAMS, LcParams(sensing_range_m=30.0))
    static_tracks: set = set()
    for k, f in enumerate(static + peds):
        r = est.step(f.without_truth())
        store = est.state.features
        assert store.klass is not None
        cls_of = dict(zip(store.ids.tolist(), store.klass.tolist()))
        paired = r.v2f_assignment >= 0
        assert paired[3:].all() if k >= 3 else True
        for trk, c in zip(r.v2f_assignment[paired].tolist(), f.v2f_class[paired].tolist()):
            assert cls_of[trk] == c
            if k < 8:
                static_tracks.add(trk)
            else:
                assert trk not in static_tracks


def test_mixed_classes_every_pairing_matches_and_known_da_records_classes():
    frames = _classed(road_frames(seed=2, steps=12, v2v_range=25.0), np.array([0, 1, 0, 1], np.int8))
    lc = IcpDaLc(PARAMS, LcParams(sensing_range_m=30.0))
    kd = IcpKnownDA(PARAMS)
    for f in frames:
        r = lc.step(f.without_truth())
        store = lc.state.features
        cls_of = dict(zip(store.ids.tolist(), store.klass.tolist()))
        paired = r.v2f_assignment >= 0
        assert all(cls_of[t] == c for t, c in zip(r.v2f_assignment[paired].tolist(), f.v2f_class[paired].tolist()))
        kd.step_with_association(f.without_truth(), f.truth.v2f_feature)
        ks = kd.state.features
        np.testing.assert_array_equal(ks.klass, np.array([0, 1, 0, 1], np.int8)[ks.ids])


def test_no_classes_no_class_state():
    frames = road_frames(seed=1, steps=5)
    est = IcpDaLc(PARAMS, LcParams(sensing_range_m=30.0))
    for f in frames:
        est.step(f.without_truth())
    assert est.state.features.klass is None
