"""``sme`` with ``[gnss_model]`` (6-D blocks with the receiver bias) and ``[fusion]`` (covariance intersection for
a vehicle that re-enters an RSU's joint state): against a centralized joint EKF over every vehicle and every
step on random small scenes where vehicles leave and re-enter the RSU's set."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from coloc.core.models import MotionParams, driving_noise_cov, predict
from coloc.inference.topology import sum_sq_pairwise, sum_sq_pairwise_grad, topology_bias, topology_variance
from coloc.methods.coop_fusion import CoopFusion, FusionParams
from coloc.methods.gnss import GnssTracker
from coloc.methods.gnss_bias import GnssModelParams
from coloc.methods.infra import InfraMethodParams, SmeInfra
from scenes import infra_frames

# Isotropic driving noise: its covariance does not depend on the velocity estimate, so the filters compared
# predict with the same Q.
MOTION = MotionParams(sigma_along=0.3, sigma_cross=0.3)


def flicker_frames(seed: int, n_veh: int, n_steps: int, p_in: float, gnss_sigma: float) -> list:
    """One RSU; each step each vehicle is in its set (V2I link and radar detection) with probability ``p_in``:
    vehicles leave and re-enter the joint state often."""
    frames = infra_frames(n_steps=n_steps, n_veh=n_veh, seed=seed, features=False, gnss_sigma=gnss_sigma,
                          spacing=15.0, start=-40.0)
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5AE]))
    out = []
    for f in frames:
        inside = rng.random(n_veh) < p_in
        keep = inside[f.truth.radar_vehicle]
        v2i = sp.csr_matrix(inside[None, :])
        infra = replace(f.infra, v2i=v2i, radar_z=f.infra.radar_z[keep], radar_owner=np.zeros(int(keep.sum()), np.int64))
        out.append(replace(f, infra=infra, truth=replace(f.truth, radar_vehicle=f.truth.radar_vehicle[keep])))
    return out


class CentralizedEkf:
    """Every vehicle's [p, v] (with ``model``: [p, v, b], the receiver's Gauss-Markov bias) in one state, every
    fix, the RSU's topology measurement (10) on the vehicles in its set, linearized at this filter's own
    prediction: the joint information the RSU could have had."""

    def __init__(self, model: GnssModelParams | None = None):
        self.model = model
        self.d = 4 if model is None else 6
        self.mean = self.cov = None

    def step(self, f):
        n, d = f.n_vehicles, self.d
        s = 0.0 if self.model is None else self.model.bias_share
        r_pos = np.asarray(f.gnss_R, float)[:, :2, :2]
        if self.mean is None:
            self.mean, self.cov = np.zeros(d * n), np.zeros((d * n, d * n))
            for i in range(n):
                self.mean[d * i:d * i + 4] = f.prior_z[i]
                self.cov[d * i:d * i + 4, d * i:d * i + 4] = f.prior_R[i]
                if d == 6:
                    self.cov[6 * i + 4:6 * i + 6, 6 * i + 4:6 * i + 6] = s * r_pos[i]
        else:
            x = self.mean.reshape(n, d)
            q = driving_noise_cov(x[:, 2:4], f.dt, MOTION)
            a = np.eye(d)
            a[0, 2] = a[1, 3] = f.dt
            decay = 1.0 if d == 4 else np.exp(-f.dt / self.model.bias_tau_s)
            if d == 6:
                a[4, 4] = a[5, 5] = decay
            big_a, big_q = np.kron(np.eye(n), a), np.zeros((d * n, d * n))
            for i in range(n):
                big_q[d * i:d * i + 4, d * i:d * i + 4] = q[i]
                if d == 6:
                    big_q[6 * i + 4:6 * i + 6, 6 * i + 4:6 * i + 6] = (1 - decay**2) * s * r_pos[i]
            xm, _ = predict(x[:, :4], np.zeros((n, 4, 4)), f.accel, f.dt, q)
            x = x.copy()
            x[:, :4] = xm
            if d == 6:
                x[:, 4:] *= decay
            self.mean, self.cov = x.reshape(-1), big_a @ self.cov @ big_a.T + big_q
        h, r = np.zeros((4 * n, d * n)), np.zeros((4 * n, 4 * n))
        for i in range(n):
            h[4 * i:4 * i + 4, d * i:d * i + 4] = np.eye(4)
            if d == 6:
                h[4 * i:4 * i + 2, 6 * i + 4:6 * i + 6] = np.eye(2)
            r[4 * i:4 * i + 4, 4 * i:4 * i + 4] = f.gnss_R[i]
            r[4 * i:4 * i + 2, 4 * i:4 * i + 2] *= 1 - s
        self._update(h, f.gnss_z.reshape(-1), r)
        inside = np.flatnonzero(f.infra.v2i.toarray()[0])
        if inside.size >= 2 and f.infra.radar_z.shape[0] == inside.size:
            pos = self.mean.reshape(n, d)[inside, :2]
            y = float(sum_sq_pairwise(f.infra.radar_z)) - topology_bias(inside.size, f.infra.radar_var)
            h0 = float(sum_sq_pairwise(pos))
            jac = np.zeros((1, d * n))
            g = sum_sq_pairwise_grad(pos)
            jac[0, d * inside], jac[0, d * inside + 1] = g[:, 0], g[:, 1]
            rt = np.array([[topology_variance(h0, inside.size, f.infra.radar_var)]])
            self._update(jac, np.array([y - h0]) + jac @ self.mean, rt)

    def _update(self, h, z, r):
        s = h @ self.cov @ h.T + r
        k = np.linalg.solve(s, h @ self.cov).T
        self.mean = self.mean + k @ (z - h @ self.mean)
        ikh = np.eye(self.cov.shape[0]) - k @ h
        self.cov = ikh @ self.cov @ ikh.T + k @ r @ k.T
        self.cov = 0.5 * (self.cov + self.cov.T)


def _min_gap(est, frames, model=None) -> tuple[float, int]:
    """Smallest eigenvalue over steps and covered vehicles of P_est,pos - P_central,pos, relative to the
    central one's trace, and the number of comparisons."""
    ref = CentralizedEkf(model)
    d = ref.d
    worst, count = np.inf, 0
    for f in frames:
        out = est.step(f.without_truth())
        ref.step(f)
        for i in np.flatnonzero(out.covered):
            pc = ref.cov[d * i:d * i + 2, d * i:d * i + 2]
            gap = np.linalg.eigvalsh(out.cov[i, :2, :2] - pc)[0] / np.trace(pc)
            worst, count = min(worst, gap), count + 1
    return worst, count


SCENES = [(s, 3 + s % 3, 0.55 + 0.1 * (s % 3), (3.0, 6.0, 10.0)[s % 3]) for s in range(12)]


def _sme(fusion: bool, gnss_model=None):
    fu = CoopFusion.from_config(FusionParams(), gnss_model) if fusion else None
    return SmeInfra(InfraMethodParams(motion=MOTION), gnss_model=gnss_model, fusion=fu)


def test_reentry_ci_is_never_below_the_centralized_joint_ekf():
    """12 random scenes (3-5 vehicles, GNSS 3-10 m, each in the RSU's set with probability 0.55-0.75 a step, 25
    steps): the fused sme's position covariance is never below the centralized EKF's in Loewner order (up to
    5e-3 of its trace: the two linearize the topology measurement at their own estimates; measured worst
    -1.6e-3); the paper's sme, which re-admits a vehicle with its tracker's belief and no cross-covariance
    although its earlier fixes are in the others' states, is below it by more than 1e-2 of the trace on most
    scenes (measured on 11 of 12, down to -9.7e-2)."""
    below = 0
    for seed, n_veh, p_in, sigma in SCENES:
        frames = flicker_frames(seed, n_veh, 25, p_in, sigma)
        fused, count = _min_gap(_sme(True), frames)
        paper, _ = _min_gap(_sme(False), frames)
        assert count > 20
        assert fused >= -5e-3, (seed, fused)
        below += paper < -1e-2
    assert below >= 9


def test_single_vehicle_with_the_bias_model_is_the_bias_tracker():
    """One vehicle: no topology; the 6-D joint update is the gnss benchmark's bias-state tracker's."""
    from coloc.methods.gnss_bias import GnssBiasTracker

    model = GnssModelParams(innovation_gate=0.0)
    frames = infra_frames(n_steps=30, n_veh=1)
    sme = _sme(True, model)
    trk = GnssBiasTracker(motion=MOTION, model=model)
    covered = 0
    for f in frames:
        a, b = sme.step(f.without_truth()), trk.step(f.without_truth())
        covered += int(a.covered.sum())
        np.testing.assert_allclose(a.mean, b.mean, atol=1e-9, rtol=0)
        np.testing.assert_allclose(a.cov, b.cov, atol=1e-9, rtol=0)
    assert covered > 10


def test_bias_model_and_fusion_off_is_the_paper_sme():
    """Without the tables the code path is the paper's: equal bytes to an sme built without the arguments."""
    frames = flicker_frames(3, 4, 15, 0.65, 6.0)
    a = SmeInfra(InfraMethodParams(motion=MOTION))
    b = SmeInfra(InfraMethodParams(motion=MOTION), gnss_model=None, fusion=None)
    for f in frames:
        x, y = a.step(f.without_truth()), b.step(f.without_truth())
        assert x.mean.tobytes() == y.mean.tobytes() and x.cov.tobytes() == y.cov.tobytes()


def test_reentry_ci_with_the_bias_model_is_never_below_the_centralized_joint_ekf():
    """As above with [gnss_model] (s = 0.8, tau = 60 s, no gate) in both the sme and the centralized EKF, on 6
    of the scenes (measured: fused worst -7e-5 of the trace; paper below by more than 1e-2 on 5 of 6, down
    to -0.156)."""
    model = GnssModelParams(innovation_gate=0.0)
    below = 0
    for seed, n_veh, p_in, sigma in SCENES[:6]:
        frames = flicker_frames(seed, n_veh, 25, p_in, sigma)
        fused, count = _min_gap(_sme(True, model), frames, model)
        paper, _ = _min_gap(_sme(False, model), frames, model)
        assert count > 20
        assert fused >= -5e-3, (seed, fused)
        below += paper < -1e-2
    assert below >= 4
