"""``rsu_bp`` with ``[fusion]`` (the PF rule of coloc.methods.pf_fusion at the RSU): its vehicle covariance against
the centralized joint Kalman filter told the association (coloc.methods.centralized) on small scenes."""

from __future__ import annotations

import numpy as np

from coloc.core.models import MotionParams
from coloc.inference.params import IcpParams
from coloc.methods.centralized import CentralizedKF
from coloc.methods.coop_fusion import CoopFusion, FusionParams
from coloc.methods.infra import InfraMethodParams, RsuBpInfra
from scenes import infra_frames

MOTION = MotionParams(sigma_along=0.3, sigma_cross=0.3)  # isotropic: both filters predict with the same Q


def _gaps(est, frames) -> list[float]:
    """Per step and covered vehicle: smallest eigenvalue of P_est,pos - P_central,pos over the central trace."""
    ref = CentralizedKF(params=IcpParams(motion=MOTION))
    out = []
    for f in frames:
        e = est.step(f.without_truth())
        c = ref.step_with_association(f, f.truth.v2f_feature)
        for i in np.flatnonzero(e.covered):
            pc = c.cov[i, :2, :2]
            out.append(np.linalg.eigvalsh(e.cov[i, :2, :2] - pc)[0] / np.trace(pc))
    return out


def test_fused_rsu_bp_is_never_below_the_centralized_joint_kf():
    """6 scenes (4-6 vehicles through two RSUs, landmarks every 25 m, GNSS 3 m, 100 particles, 24 steps):
    the fused rsu_bp's position covariance is never below the joint KF's, which also has every row of the
    vehicles out of range (measured: the smallest gap +1.6e-3 of the trace); the paper's rsu_bp is below it by
    more than 5 % of the trace on every scene."""
    worst_fused, paper_below = [], 0
    for s in range(6):
        frames = infra_frames(n_steps=24, n_veh=4 + s % 3, seed=20 + s, rsu_x=(-40.0, 60.0))
        fu = CoopFusion.from_config(FusionParams(), None)
        fused = _gaps(RsuBpInfra(InfraMethodParams(motion=MOTION, rsu_bp_particles=100, seed=s), fusion=fu), frames)
        paper = _gaps(RsuBpInfra(InfraMethodParams(motion=MOTION, rsu_bp_particles=100, seed=s)), frames)
        assert len(fused) > 30
        worst_fused.append(min(fused))
        paper_below += min(paper) < -0.05
    assert min(worst_fused) >= -1e-6, worst_fused
    assert paper_below == 6
