"""ICP-DA-PF under clutter: track existence and per-pair P_D, as ICP-DA-LC's steps 3
and 9 (coloc.methods.icp_da_pf, ``existence`` / ``detection`` of icp_da_pf_step)."""

from dataclasses import replace

import numpy as np
import pytest

from coloc.core.detection import DetectionModel
from coloc.inference.params import IcpParams
from coloc.methods.icp_da_pf import IcpDaPf, PfParams
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION
from tests.coloc.test_track_confirmation import CLUTTER_RANGE_M, GNSS_SP, _lc, _rmse, run_under_clutter, with_clutter

PF_SMALL = PfParams(vehicle_particles=300, feature_particles=300, seed=1)


def _without_rows(f):
    """The frame with no V2F row at all."""
    return replace(f, v2f_z=f.v2f_z[:0], v2f_owner=f.v2f_owner[:0], v2f_R=f.v2f_R[:0],
                   truth=replace(f.truth, v2f_feature=f.truth.v2f_feature[:0]))


@pytest.mark.parametrize("seed", [1, 2])
def test_clutter_alone_confirms_no_track_and_vehicles_equal_the_pf_without_rows(seed):
    """No real feature, one false detection per vehicle and scan: with track existence no track is
    ever confirmed, every row is reported discarded, no feature is reported, and the vehicles are
    byte for byte those of the same PF on frames without any V2F row (the particle streams are per
    vehicle and purpose, so rows that move nothing change nothing). Without existence the same
    clutter starts tracks that pull the vehicles away."""
    frames = with_clutter(road_frames(seed=seed, steps=12, n_feat=0, gnss_sp=GNSS_SP), 1.0, seed)
    params = IcpParams(motion=MOTION)
    pf_ex = IcpDaPf(params=params, lc=_lc(1.0), pf=PF_SMALL)
    pf_plain = IcpDaPf(params=params, lc=_lc(1.0, existence=False), pf=PF_SMALL)
    pf_norows = IcpDaPf(params=params, lc=_lc(1.0), pf=PF_SMALL)
    moved = 0.0
    for f in frames:
        blind = f.without_truth()
        e_x, e_p, e_0 = pf_ex.step(blind), pf_plain.step(blind), pf_norows.step(_without_rows(f).without_truth())
        ex = pf_ex.last.existence
        assert ex is not None and not ex.confirmed(ex.ids, pf_ex.lc.confirm_existence).any()
        assert np.all(e_x.v2f_assignment == -1) and e_x.feature_track_ids.size == 0
        np.testing.assert_array_equal(e_x.mean, e_0.mean)
        np.testing.assert_array_equal(e_x.cov, e_0.cov)
        moved = max(moved, float(np.abs(e_p.mean - e_0.mean).max()))
    assert moved > 0.1


def test_real_features_are_confirmed_under_clutter_and_the_pf_beats_gnss():
    """Landmarks 30 m apart plus one false detection per vehicle and scan (the LC test's scene):
    real rows localize the vehicles ten times as often as clutter rows, covariances stay SPD, and
    the PF (J = 300) beats the GNSS Kalman filter."""
    seed = 4
    frames = with_clutter(road_frames(seed=seed, steps=20, n_feat=4, v2v_range=25.0, gnss_sp=GNSS_SP), 1.0, seed)
    pf = IcpDaPf(params=IcpParams(motion=MOTION), lc=_lc(1.0), pf=PF_SMALL)
    out_pf, out_g, used_real, used_clutter = run_under_clutter(pf, frames)
    print(f"real rows used {used_real}, clutter rows used {used_clutter}; "
          f"RMSE PF {_rmse(frames, out_pf):.3f} m, GNSS {_rmse(frames, out_g):.3f} m")
    assert used_real > 10 * max(used_clutter, 1)
    assert _rmse(frames, out_pf) < _rmse(frames, out_g)


def test_a_track_outside_the_field_of_view_is_not_expected():
    """A front sensor (90 deg, 30 m) on vehicles driving east, existence on, no clutter: after the
    vehicles pass the landmarks, tracks behind them are out of view, so their existence stays where
    the detections left it; with a 360 deg sensor of the same range the missed detections of the
    tracks still within 30 m lower it."""
    frames = road_frames(seed=3, steps=12, n_feat=2, v2f_range=CLUTTER_RANGE_M, gnss_sp=1.0)
    lc = replace(_lc(0.0), detection_probability=0.9)
    front = DetectionModel(fov_deg=(90.0,), range_m=(CLUTTER_RANGE_M,), yaw_deg=(0.0,), mount_x_m=(0.0,),
                           pd_near=(0.9,), pd_far=(0.9,))
    around = replace(front, fov_deg=(360.0,))
    r_min = {}
    for name, det in (("front", front), ("around", around)):
        # Rows the sensor could not give: keep only those in its field of view (here every row is
        # in front of the measuring vehicle: features ahead, road_frames senses within 30 m).
        pf = IcpDaPf(params=IcpParams(motion=MOTION), lc=lc, pf=PF_SMALL, detection=det)
        lows = []
        for f in frames:
            ahead = f.v2f_z[:, 0] > 0
            g = replace(f, v2f_z=f.v2f_z[ahead], v2f_owner=f.v2f_owner[ahead], v2f_R=f.v2f_R[ahead],
                        truth=replace(f.truth, v2f_feature=f.truth.v2f_feature[ahead]))
            pf.step(g.without_truth())
            ex = pf.last.existence
            if ex.ids.size:
                lows.append(ex.r.min())
        r_min[name] = min(lows)
    print(r_min)
    assert r_min["front"] > 0.5
    assert r_min["around"] < r_min["front"]
