"""[fusion] map_drift: the folded part of a track drifts with the common-mode frame; the live messages and, with
the key off, everything else stay as model (2) predicts them."""

import math

import numpy as np
import pytest

from coloc.inference.feature_store import FeatureStore
from coloc.inference.gaussian import from_information, to_information
from coloc.inference.params import IcpParams
from coloc.kernels import icp_fused
from coloc.methods.coop_fusion import CoopFusion, FusionParams
from coloc.methods.gnss_bias import GnssModelParams
from tests.coloc.test_icp_known_da import MOTION

PARAMS = IcpParams(motion=MOTION, feature_sigma_par=0.001, message_memory_s=1.0)


def _store():
    """Two tracks; track 1 has a folded part (a vehicle that stopped observing it) and a live message."""
    rng = np.random.default_rng(8)
    cov = np.stack([np.diag(rng.uniform(0.5, 2.0, 4)) for _ in range(3)])
    mean = rng.normal(0, 10, (3, 4))
    lam, eta = to_information(mean, cov)
    s = FeatureStore().record(np.array([1, 2]), np.array(["a", "a"], dtype=object), lam[:2], eta[:2], 0.0, PARAMS)
    # at t = 5 s vehicle b observes track 1; a's messages (5 s old, memory 1 s) are folded
    return s.record(np.array([1]), np.array(["b"], dtype=object), lam[2:], eta[2:], 5.0, PARAMS)


@pytest.mark.parametrize("fused", [True, False])
def test_drift_reaches_the_folded_part_only(fused, monkeypatch):
    monkeypatch.setattr(icp_fused, "FUSED", fused)
    store = _store()
    assert np.abs(store.folded_lam).sum() > 0 and store.msg_track.size == 1
    dt, drift = 0.75, 0.3
    plain, drifted = store.predict(dt, PARAMS), store.predict(dt, PARAMS, drift)
    # the live message is predicted by model (2) alone either way
    np.testing.assert_array_equal(plain.msg_cov, drifted.msg_cov)
    np.testing.assert_array_equal(plain.msg_mean, drifted.msg_mean)
    # the folded part: its predicted covariance plus drift on the position diagonal, its mean unchanged
    for k in range(store.ids.size):
        if not np.abs(store.folded_lam[k]).sum():
            continue
        mp, pp = from_information(plain.folded_lam[k:k + 1], plain.folded_eta[k:k + 1])
        md, pd_ = from_information(drifted.folded_lam[k:k + 1], drifted.folded_eta[k:k + 1])
        np.testing.assert_allclose(pd_[0] - pp[0], np.diag([drift, drift, 0, 0]), atol=1e-9)
        np.testing.assert_allclose(md, mp, atol=1e-9)


def test_no_drift_is_the_model_2_prediction_bit_for_bit():
    store = _store()
    a, b = store.predict(0.75, PARAMS), store.predict(0.75, PARAMS, 0.0)
    for name in ("folded_lam", "folded_eta", "msg_mean", "msg_cov"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_fused_equals_reference(monkeypatch):
    store = _store()
    fused = store.predict(0.75, PARAMS, 0.2)
    monkeypatch.setattr(icp_fused, "FUSED", False)
    ref = _store().predict(0.75, PARAMS, 0.2)
    for name in ("folded_lam", "folded_eta", "msg_mean", "msg_cov"):
        np.testing.assert_allclose(getattr(fused, name), getattr(ref, name), rtol=1e-12, atol=1e-12)


def test_the_drift_is_the_common_mode_bias_driving_noise():
    model = GnssModelParams(bias_model="two_state", common_share=0.0, common_sigma_m=1.27, common_tau_s=1800.0)
    on = CoopFusion(FusionParams(common_frame_messages=True, map_drift=True), model)
    dt = 0.75
    assert on.map_drift(dt) == pytest.approx(1.27 ** 2 * (1 - math.exp(-2 * dt / 1800.0)), rel=1e-12)
    # the stationary variance is kept: n steps of the drift sum to the Gauss-Markov's variance of the change
    # over n dt to first order (a random walk), 1.27^2 (1 - exp(-2 n dt / tau)) ~ n * drift for n dt << tau
    assert 400 * on.map_drift(dt) == pytest.approx(1.27 ** 2 * (1 - math.exp(-2 * 400 * dt / 1800.0)), rel=0.2)
    assert CoopFusion(FusionParams(common_frame_messages=True), model).map_drift(dt) == 0.0
    assert CoopFusion(FusionParams(map_drift=True), model).map_drift(dt) == 0.0  # position-marginal messages
    single = GnssModelParams(common_sigma_m=1.27)
    assert CoopFusion(FusionParams(common_frame_messages=True, map_drift=True), single).map_drift(dt) == 0.0
