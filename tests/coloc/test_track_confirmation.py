"""ICP-DA-LC under clutter (issue 21, estimator side): the clutter intensity in the normaliser of
eta (13), births weighed against clutter, and M-of-N track confirmation (module docstring of
coloc.methods.icp_da_lc, step 9)."""

from dataclasses import replace

import numpy as np
import pytest

from coloc.inference.params import IcpParams
from coloc.methods.gnss import GnssTracker
from coloc.methods.icp_da_lc import (
    IcpDaLc,
    LcParams,
    TrackStatus,
    clutter_log_density,
    new_feature_log_density,
)
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION

CLUTTER_RANGE_M = 30.0


def with_clutter(frames, per_scan: float, seed: int, keep_features: bool = True):
    """Add Poisson(per_scan) false detections per vehicle and frame, uniform over a disc of
    CLUTTER_RANGE_M around the vehicle, looking like static objects (z_v = -v_true + noise), truth
    index -1; with ``keep_features`` False the frame's real rows are removed first."""
    rng = np.random.default_rng(seed)
    out = []
    for f in frames:
        n = f.n_vehicles
        k = rng.poisson(per_scan, n)
        owner = np.repeat(np.arange(n), k)
        r = CLUTTER_RANGE_M * np.sqrt(rng.random(owner.size))
        phi = rng.uniform(0, 2 * np.pi, owner.size)
        z = np.zeros((owner.size, 4))
        z[:, 0], z[:, 1] = r * np.cos(phi), r * np.sin(phi)
        z[:, 2:] = -f.truth.x_true[owner, 2:] + rng.normal(0, 0.1, (owner.size, 2))
        z[:, :2] += rng.normal(0, 0.2, (owner.size, 2))
        cov = np.diag([0.04, 0.04, 0.01, 0.01])
        old = slice(None) if keep_features else slice(0, 0)
        all_owner = np.concatenate([f.v2f_owner[old], owner])
        order = np.argsort(all_owner, kind="stable")
        out.append(replace(
            f,
            v2f_z=np.concatenate([f.v2f_z[old], z])[order],
            v2f_owner=all_owner[order],
            v2f_R=np.concatenate([f.v2f_R[old], np.repeat(cov[None], owner.size, 0)])[order],
            truth=replace(f.truth, v2f_feature=np.concatenate([f.truth.v2f_feature[old],
                                                               np.full(owner.size, -1)])[order]),
        ))
    return out


def _lc(per_scan, confirm=(3, 4)):
    return LcParams(sensing_range_m=CLUTTER_RANGE_M, eta_threshold=0.5,
                    clutter_intensity=per_scan / (np.pi * CLUTTER_RANGE_M**2),
                    confirm_hits=confirm[0], confirm_window_steps=confirm[1])


def test_clutter_density_joins_the_new_feature_density():
    """lambda_c f_c is the static-object velocity Gaussian times lambda_c, added to mu_new f_new."""
    rng = np.random.default_rng(1)
    v_mean, z = rng.normal(size=(4, 4)), rng.normal(size=(4, 4))
    v_cov = np.repeat(np.eye(4)[None] * 0.5, 4, 0)
    r = np.repeat(np.eye(4)[None] * 0.1, 4, 0)
    lc = LcParams(clutter_intensity=2e-3)
    d = z[:, 2:] + v_mean[:, 2:]
    ref = np.log(2e-3) - np.log(2 * np.pi * 0.6) - 0.5 * np.einsum("ni,ni->n", d, d) / 0.6
    np.testing.assert_allclose(clutter_log_density(v_mean, v_cov, z, r, lc), ref, rtol=1e-12)
    base = new_feature_log_density(v_mean, v_cov, z, r, LcParams())
    np.testing.assert_allclose(new_feature_log_density(v_mean, v_cov, z, r, lc), np.logaddexp(base, ref), rtol=1e-12)


@pytest.mark.parametrize("bad", [dict(clutter_intensity=-1.0), dict(confirm_hits=0),
                                 dict(confirm_hits=4, confirm_window_steps=3)])
def test_bad_confirmation_parameters(bad):
    with pytest.raises(ValueError):
        LcParams(**bad)


def test_track_status_m_of_n():
    lc = LcParams(confirm_hits=2, confirm_window_steps=3)
    st = TrackStatus().advance(np.empty(0, np.int64), np.array([5]), lc)  # born, hit 1
    assert st.ids.tolist() == [5] and st.hits.tolist() == [1] and not st.confirmed.any()
    st = st.advance(np.array([5]), np.empty(0, np.int64), lc)  # missed
    assert st.age.tolist() == [2] and st.expired(lc).size == 0
    st2 = st.advance(np.array([5]), np.array([5]), lc)  # hit 2 in step 3: confirmed
    assert st2.confirmed.tolist() == [True] and st2.expired(lc).size == 0
    st3 = st.advance(np.array([5]), np.empty(0, np.int64), lc)  # missed again: expired at age 3
    assert st3.expired(lc).tolist() == [5]
    merged = st2.advance(np.array([5]), np.array([9]), lc).merged(np.array([9]), np.array([5]))
    assert merged.ids.tolist() == [5] and merged.confirmed.tolist() == [True]
    assert st2.is_confirmed(np.array([-1, 5, 7])).tolist() == [False, True, False]


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_clutter_alone_confirms_no_track_and_vehicles_equal_gnss(seed):
    """No real feature, one false detection per vehicle and scan (five vehicles 10 m apart, each
    with clutter over a 30 m disc) and 3-of-4 confirmation: no track is ever confirmed, every row
    is reported discarded, and the vehicles are exactly the GNSS tracker's. Without confirmation
    (M = 1) the same clutter starts tracks that pull the vehicles off GNSS.

    Measured limit (not asserted): at three per vehicle and scan, 8 seeds x 15 steps, a clutter
    track is confirmed in 25 of 120 steps with 3-of-4 and 15 of 120 with 4-of-5 (GNSS 8 m); the
    five overlapping discs put about one false detection per step into a track's gate."""
    frames = with_clutter(road_frames(seed=seed, steps=15, n_feat=0), 1.0, seed)
    params = IcpParams(motion=MOTION)
    confirmed = IcpDaLc(params, _lc(1.0))
    unconfirmed = IcpDaLc(params, _lc(1.0, confirm=(1, 1)))
    gnss = GnssTracker(MOTION)
    moved = 0.0
    for f in frames:
        blind = f.without_truth()
        e_c, e_u, e_g = confirmed.step(blind), unconfirmed.step(blind), gnss.step(blind)
        assert not confirmed.last.status.confirmed.any()
        assert np.all(e_c.v2f_assignment == -1) and e_c.feature_track_ids.size == 0
        np.testing.assert_array_equal(e_c.mean, e_g.mean)
        np.testing.assert_array_equal(e_c.cov, e_g.cov)
        moved = max(moved, float(np.abs(e_u.mean - e_g.mean).max()))
    assert moved > 0.1


def _rmse(frames, ests):
    e = np.concatenate([np.sum((r.mean[:, :2] - f.truth.x_true[:, :2]) ** 2, 1) for f, r in zip(frames, ests)])
    return float(np.sqrt(e.mean()))


def test_real_features_are_confirmed_under_clutter_and_help_the_vehicles():
    """Landmarks 30 m apart plus one false detection per vehicle and scan: the landmarks' tracks
    are confirmed within the window, clutter's are not, and the vehicles beat GNSS."""
    seed = 4
    frames = with_clutter(road_frames(seed=seed, steps=20, n_feat=4, v2v_range=25.0), 1.0, seed)
    params = IcpParams(motion=MOTION)
    lc_est, gnss = IcpDaLc(params, _lc(1.0)), GnssTracker(MOTION)
    out_lc, out_g = [], []
    used_clutter = used_real = 0
    for f in frames:
        blind = f.without_truth()
        out_lc.append(lc_est.step(blind))
        out_g.append(gnss.step(blind))
        a = out_lc[-1].v2f_assignment
        used_clutter += int(((a >= 0) & (f.truth.v2f_feature < 0)).sum())
        used_real += int(((a >= 0) & (f.truth.v2f_feature >= 0)).sum())
        for c in out_lc[-1].cov:
            assert np.linalg.eigvalsh(c).min() > 0
    assert used_real > 10 * max(used_clutter, 1)
    assert _rmse(frames, out_lc) < _rmse(frames, out_g)
