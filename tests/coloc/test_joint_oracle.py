"""``joint_oracle`` (coloc/methods/joint_oracle.py) against batch least squares, and its consistency where its
model is the truth.

* Batch: on small linear problems (GNSS with common and local error states, net-frame V2F rows, features born
  with zero position information) the filter's final joint mean and covariance equal the solution of the
  weighted least-squares problem over the whole trajectory (the same information: priors, process noises,
  every fix and row) to 1e-9.
* NEES: over 100 seeded runs drawn from the oracle's own model, the average NEES of a vehicle's final
  position is inside the 99 % chi-square band.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.stats import chi2

from coloc.core.frame import Frame
from coloc.core.models import MotionParams, driving_noise_cov, input_matrix, transition_matrix
from coloc.inference.feature_store import feature_track_q
from coloc.inference.params import IcpParams
from coloc.methods.joint_oracle import JointOracle, OracleWorld

DT = 0.75
MOTION = MotionParams(sigma_along=0.3, sigma_cross=0.3)  # isotropic: Q does not depend on the estimate
PARAMS = IcpParams(motion=MOTION, feature_sigma_par=0.05, feature_sigma_perp=0.05, feature_velocity_prior_sigma=0.4,
                   feature_drop_after_s=1e9)
# Linear worlds: with infinite correlation lengths the local error's coefficient does not depend on the speed.
WORLDS = {
    "white": OracleWorld(),
    "per_vehicle": OracleWorld(gnss="per_vehicle", tau_s=20.0, fix_noise_share=0.05),
    "field": OracleWorld(gnss="field", tau_s=20.0, common_share=0.4, common_tau_s=200.0, field_share=0.5,
                         field_corr_length_m=math.inf, field_tau_s=60.0, fix_noise_share=0.05),
}


def _factor(q: np.ndarray) -> np.ndarray:
    """L with L L^T = q (q symmetric PSD, possibly singular)."""
    w, v = np.linalg.eigh(q)
    keep = w > 1e-12 * max(w.max(), 1e-300)
    return v[:, keep] * np.sqrt(w[keep])


def _frame(t, n, rng, entered, sig, zg, vel_sig, owner, rows_z, rows_r, prior_z=None, prior_r=None):
    gr = np.zeros((n, 4, 4))
    gr[:, 0, 0] = gr[:, 1, 1] = sig ** 2
    gr[:, 2, 2] = gr[:, 3, 3] = vel_sig ** 2
    return Frame(
        t=t, dt=DT, vehicle_ids=np.array([f"v{i}" for i in range(n)], dtype=object), entered=entered,
        prior_z=prior_z if prior_z is not None else np.full((n, 4), np.nan),
        prior_R=prior_r if prior_r is not None else np.full((n, 4, 4), np.nan),
        accel=rng.normal(0, 0.5, (n, 2)), gnss_z=zg, gnss_R=gr, v2f_z=rows_z, v2f_owner=owner, v2f_R=rows_r,
        neighbors=sp.csr_matrix((n, n), dtype=bool),
    )


def random_priors(rng, n):
    """(prior_z (n, 4), prior_R (n, 4, 4)): random entry priors, SPD covariances."""
    prior_z = rng.normal(0, 5, (n, 4))
    prior_r = np.zeros((n, 4, 4))
    for i in range(n):
        a = rng.normal(size=(4, 4))
        prior_r[i] = a @ a.T + np.diag([4.0, 4.0, 0.5, 0.5])
    return prior_z, prior_r


def _scenario(rng, n=3, k=3, steps=6):
    """Random measurements (any values do for the equality test): a list of (frame, association)."""
    frames = []
    prior_z, prior_r = random_priors(rng, n)
    for step in range(steps):
        sig = rng.uniform(2.0, 9.0, n)  # zone changes: the reported sigma moves
        zg = rng.normal(0, 5, (n, 4))
        owner = np.repeat(np.arange(n), 2)
        # two distinct features per vehicle; every feature is born in the first step (zero position information)
        assoc = np.concatenate([rng.choice(k, 2, replace=False) for _ in range(n)])
        if step == 0:
            assoc = np.concatenate([[i % k, (i + 1) % k] for i in range(n)])
        rows_z = rng.normal(0, 10, (owner.size, 4))
        rows_r = np.zeros((owner.size, 4, 4))
        for j in range(owner.size):
            a = rng.normal(size=(4, 4)) * 0.2
            rows_r[j] = a @ a.T + 0.05 * np.eye(4)
        entered = np.full(n, step == 0)
        f = _frame(step * DT, n, rng, entered, sig, zg, rng.uniform(0.1, 0.4, n), owner, rows_z, rows_r,
                   prior_z if step == 0 else None, prior_r if step == 0 else None)
        frames.append((f, assoc))
    return frames


def _batch(frames, world: OracleWorld, params: IcpParams):
    """Weighted least squares over the whole trajectory, parametrized by the initial state and the unit process
    noises: returns the final joint (mean, covariance) in the oracle's layout."""
    n = frames[0][0].n_vehicles
    k = int(max(a.max() for _, a in frames)) + 1
    vd, cd = world.vehicle_dim, world.common_dim
    d = vd * n + 4 * k + cd
    a4, b4 = transition_matrix(DT), input_matrix(DT)
    # theta = [x_0 (d), e_1, e_2, ...]; x_t = phi_t theta + off_t
    phi = np.eye(d)
    off = np.zeros(d)
    blocks_info = [np.zeros((d, d))]
    eta_parts = [np.zeros(d)]
    f0 = frames[0][0]
    lam0, eta0 = blocks_info[0], eta_parts[0]
    for i in range(n):  # the frames carry no prior_has_fix: every entry prior counts
        li = np.linalg.inv(f0.prior_R[i])
        s = slice(vd * i, vd * i + 4)
        lam0[s, s] += li
        eta0[s] += li @ f0.prior_z[i]
    for i in range(n if world.correlated else 0):
        s = slice(vd * i + 4, vd * i + 6)
        lam0[s, s] += np.eye(2)
    for j in range(k):
        s = slice(vd * n + 4 * j + 2, vd * n + 4 * j + 4)
        lam0[s, s] += np.eye(2) / params.feature_velocity_prior_sigma ** 2
    if cd:
        lam0[-cd:, -cd:] += np.eye(cd)
    rows_h, rows_rinv, rows_z, rows_t = [], [], [], []
    phis, offs = [], []
    for t, (f, assoc) in enumerate(frames):
        if t > 0:
            fm = np.zeros((d, d))
            lq = []
            inp = np.zeros(d)
            for i in range(n):
                s = slice(vd * i, vd * i + 4)
                fm[s, s] = a4
                inp[s] = b4 @ frames[t][0].accel[i]
                lq.append((s, _factor(driving_noise_cov(np.zeros((1, 2)), DT, params.motion)[0])))
                if world.correlated:
                    a_l = float(world.local_coefficient(np.zeros(1), DT)[0])
                    su = slice(vd * i + 4, vd * i + 6)
                    fm[su, su] = a_l * np.eye(2)
                    lq.append((su, math.sqrt(1 - a_l ** 2) * np.eye(2)))
            for j in range(k):
                s = slice(vd * n + 4 * j, vd * n + 4 * j + 4)
                fm[s, s] = a4
                lq.append((s, _factor(feature_track_q(np.zeros((1, 4)), DT, params)[0])))
            if cd:
                a_c = math.exp(-DT / world.common_tau_s)
                fm[-cd:, -cd:] = a_c * np.eye(cd)
                lq.append((slice(d - cd, d), math.sqrt(1 - a_c ** 2) * np.eye(cd)))
            ne = sum(l.shape[1] for _, l in lq)
            g = np.zeros((d, ne))
            c = 0
            for s, l in lq:
                g[s, c:c + l.shape[1]] = l
                c += l.shape[1]
            phi = np.hstack([fm @ phi, g])
            off = fm @ off + inp
        phis.append(phi)
        offs.append(off)
        # measurements of step t: GNSS
        s_share = world.common_share if cd else 0.0
        for i in range(n):
            sig = math.sqrt(f.gnss_R[i, 0, 0])
            h = np.zeros((4, d))
            h[:, vd * i:vd * i + 4] = np.eye(4)
            r = f.gnss_R[i].copy()
            if world.correlated:
                h[0:2, vd * i + 4:vd * i + 6] = sig * math.sqrt(1 - s_share) * np.eye(2)
                if cd:
                    h[0:2, d - cd:] = sig * math.sqrt(s_share) * np.eye(2)
                r[:2, :2] = world.fix_noise_share * sig * sig * np.eye(2)
            rows_h.append(h), rows_rinv.append(np.linalg.inv(r)), rows_z.append(f.gnss_z[i]), rows_t.append(t)
        for o in range(f.v2f_owner.size):
            h = np.zeros((4, d))
            i, j = f.v2f_owner[o], assoc[o]
            h[:, vd * i:vd * i + 4] = -np.eye(4)
            h[:, vd * n + 4 * j:vd * n + 4 * j + 4] = np.eye(4)
            rows_h.append(h), rows_rinv.append(np.linalg.inv(f.v2f_R[o])), rows_z.append(f.v2f_z[o]), rows_t.append(t)
    p_dim = phis[-1].shape[1]
    lam = np.zeros((p_dim, p_dim))
    eta = np.zeros(p_dim)
    lam[:d, :d] += lam0
    eta[:d] += eta0
    lam[d:, d:] += np.eye(p_dim - d)  # unit process noises
    for h, ri, z, t in zip(rows_h, rows_rinv, rows_z, rows_t):
        ph = h @ phis[t]
        ph = np.hstack([ph, np.zeros((4, p_dim - ph.shape[1]))])
        lam += ph.T @ ri @ ph
        eta += ph.T @ ri @ (z - h @ offs[t])
    cov_theta = np.linalg.inv(lam)
    theta = cov_theta @ eta
    mean = phis[-1] @ theta + offs[-1]
    cov = phis[-1] @ cov_theta @ phis[-1].T
    return mean, cov


@pytest.mark.parametrize("world_name", sorted(WORLDS))
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_equals_batch_least_squares(world_name, seed):
    world = WORLDS[world_name]
    frames = _scenario(np.random.default_rng(seed))
    est = JointOracle(params=PARAMS, world=world)
    for f, assoc in frames:
        est.step_with_association(f, assoc)
    mean, cov = _batch(frames, world, PARAMS)
    scale = max(1.0, float(np.abs(cov).max()))
    np.testing.assert_allclose(est.state.mean, mean, rtol=0, atol=1e-9 * max(1.0, float(np.abs(mean).max())))
    np.testing.assert_allclose(est.state.cov, cov, rtol=0, atol=1e-9 * scale)


def test_batch_differs_when_the_model_does():
    """The comparison can fail: a filter told another world's coefficients misses the batch solution."""
    frames = _scenario(np.random.default_rng(5))
    est = JointOracle(params=PARAMS, world=WORLDS["field"])
    for f, assoc in frames:
        est.step_with_association(f, assoc)
    other = OracleWorld(**{**WORLDS["field"].__dict__, "common_tau_s": 20.0})
    mean, _ = _batch(frames, other, PARAMS)
    assert np.abs(est.state.mean - mean).max() > 1e-3


def _scene_start(rng, n: int, k: int):
    """The start of a drawn run: model (1)'s and model (2)'s matrices and driving-noise factors, the vehicles' true
    states (20 m apart), their priors N(x, diag(4, 4, 0.25, 0.25)) and the features' true states. Returns (a4, b4,
    lv, lf, prior_r, x, prior_z, feat)."""
    a4, b4 = transition_matrix(DT), input_matrix(DT)
    lv = _factor(driving_noise_cov(np.zeros((1, 2)), DT, MOTION)[0])
    lf = _factor(feature_track_q(np.zeros((1, 4)), DT, PARAMS)[0])
    prior_r = np.tile(np.diag([4.0, 4.0, 0.25, 0.25]), (n, 1, 1))
    x = np.zeros((n, 4))
    x[:, 2:] = rng.normal(0, 3, (n, 2))
    x[:, :2] = np.array([[20.0 * i, 0.0] for i in range(n)])
    prior_z = x + np.einsum("nij,nj->ni", np.linalg.cholesky(prior_r), rng.standard_normal((n, 4)))
    feat = np.zeros((k, 4))
    feat[:, :2] = rng.uniform(-30, 60, (k, 2))
    feat[:, 2:] = rng.normal(0, PARAMS.feature_velocity_prior_sigma, (k, 2))
    return a4, b4, lv, lf, prior_r, x, prior_z, feat


def _drawn_rows(rng, x, feat, first: bool):
    """One step's V2F rows of a drawn run: each (vehicle, feature) pair seen with probability 0.5 (vehicle 0 sees
    every feature at the first step), noise std 0.3 m / 0.2 m/s. Returns (owner, assoc, rows, rows' covariance)."""
    n, k = len(x), len(feat)
    owner = np.repeat(np.arange(n), k)
    assoc = np.tile(np.arange(k), n)
    keep = rng.random(owner.size) < 0.5
    if first:
        keep[:k] = True
    owner, assoc = owner[keep], assoc[keep]
    rr = np.tile(np.diag([0.3, 0.3, 0.2, 0.2]) ** 2, (owner.size, 1, 1))
    rows = feat[assoc] - x[owner] + rng.standard_normal((owner.size, 4)) * np.array([0.3, 0.3, 0.2, 0.2])
    return owner, assoc, rows, rr


def _simulate(rng, world: OracleWorld, n=3, k=4, steps=25):
    """One run drawn from the oracle's own model (linear world, features static on average): frames,
    associations and the final true vehicle states."""
    vd = world.vehicle_dim
    a4, b4, lv, lf, prior_r, x, prior_z, feat = _scene_start(rng, n, k)
    u = rng.standard_normal((n, 2))
    c = rng.standard_normal(2)
    s = world.common_share if world.common_dim else 0.0
    a_l = float(world.local_coefficient(np.zeros(1), DT)[0]) if world.correlated else 0.0
    a_c = math.exp(-DT / world.common_tau_s)
    out = []
    for step in range(steps):
        accel = rng.normal(0, 0.5, (n, 2))  # the input over (t - Ts, t], carried by the frame at t
        if step:
            x = x @ a4.T + accel @ b4.T + rng.standard_normal((n, lv.shape[1])) @ lv.T
            feat = feat @ a4.T + rng.standard_normal((k, lf.shape[1])) @ lf.T
            u = a_l * u + math.sqrt(1 - a_l ** 2) * rng.standard_normal((n, 2))
            c = a_c * c + math.sqrt(1 - a_c ** 2) * rng.standard_normal(2)
        sig = rng.uniform(2.0, 6.0, n)
        vel_sig = np.full(n, 0.3)
        zg = x.copy()
        if world.correlated:
            white = math.sqrt(world.fix_noise_share) * sig[:, None] * rng.standard_normal((n, 2))
            zg[:, :2] += sig[:, None] * (math.sqrt(s) * c[None, :] + math.sqrt(1 - s) * u) + white
        else:
            zg[:, :2] += sig[:, None] * rng.standard_normal((n, 2))
        zg[:, 2:] += vel_sig[:, None] * rng.standard_normal((n, 2))
        owner, assoc, rows, rr = _drawn_rows(rng, x, feat, first=step == 0)
        f = _frame(step * DT, n, rng, np.full(n, step == 0), sig, zg, vel_sig, owner, rows, rr,
                   prior_z if step == 0 else None, prior_r if step == 0 else None)
        f = Frame(**{**f.__dict__, "accel": accel})
        out.append((f, assoc))
    return out, x


def _final_nees(est, frames, x_true) -> float:
    """Vehicle 0's 2-D position NEES after ``est`` is stepped through a drawn run, told its association."""
    for f, assoc in frames:
        res = est.step_with_association(f, assoc)
    e = res.mean[0, :2] - x_true[0, :2]
    return float(e @ np.linalg.solve(res.cov[0, :2, :2], e))


@pytest.mark.slow  # 100 runs per world: about a minute on the 2-core machine
@pytest.mark.parametrize("world_name", ["white", "field"])
def test_nees_inside_the_99_band_where_the_model_is_the_truth(world_name):
    world = WORLDS[world_name]
    runs = 100
    nees = []
    for seed in range(runs):
        frames, x_true = _simulate(np.random.default_rng(1000 + seed), world)
        nees.append(_final_nees(JointOracle(params=PARAMS, world=world), frames, x_true))
    lo, hi = chi2.ppf([0.005, 0.995], 2 * runs) / runs
    assert lo <= np.mean(nees) <= hi, (np.mean(nees), lo, hi)


def test_gate_leaves_out_a_fix_far_from_the_prediction():
    """NLOS gate: a fix 200 m off is left out (its velocity kept); the estimate stays near the others."""
    world = OracleWorld(gnss="per_vehicle", tau_s=20.0, nlos=True)
    frames, _ = _simulate(np.random.default_rng(7), world, steps=10)
    est = JointOracle(params=PARAMS, world=world)
    for f, assoc in frames[:-1]:
        est.step_with_association(f, assoc)
    before = est.state.mean[:2].copy()
    f, assoc = frames[-1]
    z = f.gnss_z.copy()
    z[0, :2] += 200.0
    res = est.step_with_association(Frame(**{**f.__dict__, "gnss_z": z}), assoc)
    assert est.last_excluded[0] and not est.last_excluded[1:].any()
    assert np.hypot(*(res.mean[0, :2] - before)) < 20.0


def test_shared_heading_term_equals_the_dense_joint_covariance():
    """Sensor-frame rows of one vehicle share its heading error: the rank-one term per vehicle gives the same
    information as inverting the dense joint covariance of all rows (D + var_i G_i G_i^T), and differs from
    the rows taken as independent."""
    from coloc.core.detections import SensorDetections, to_net_frame
    from coloc.methods.joint_oracle import _information, _scatter, _shared_heading_information

    rng = np.random.default_rng(3)
    m, nv = 7, 3
    own = np.array([0, 1, 0, 0, 1, 2, 0])
    fpos = np.array([0, 1, 1, 2, 2, 0, 3])
    det = SensorDetections(range=rng.uniform(5, 60, m), bearing=rng.uniform(-1, 1, m), range_rate=rng.normal(0, 5, m),
                           mount_x=rng.uniform(0, 3, m), yaw=rng.uniform(-1, 1, m), sigma_range=np.full(m, 0.1),
                           sigma_bearing=np.full(m, 0.005), sigma_range_rate=np.full(m, 0.03))
    psi, var = rng.uniform(-3, 3, nv), np.array([0.002, 0.01, 0.05])
    z, r = to_net_frame(det, psi[own], var[own])
    d = 4 * nv + 16
    ind = np.concatenate([own[:, None] * 4 + np.arange(4), 4 * nv + 4 * fpos[:, None] + np.arange(4)], axis=1)
    lam, eta = np.zeros((d, d)), np.zeros(d)
    _shared_heading_information(lam, eta, ind, det, psi[own], var, own, z, r)
    h = np.zeros((4 * m, d))
    for j in range(m):
        h[4 * j:4 * j + 4, ind[j, :4]] = -np.eye(4)
        h[4 * j:4 * j + 4, ind[j, 4:]] = np.eye(4)
    phi = psi[own] + det.yaw + det.bearing
    nrm = np.stack([-np.sin(phi), np.cos(phi)], 1)
    g = det.mount_x[:, None] * np.stack([-np.sin(psi[own]), np.cos(psi[own])], 1) + det.range[:, None] * nrm
    gz = np.concatenate([g, det.range_rate[:, None] * nrm], 1)
    big = np.zeros((4 * m, 4 * m))
    for j in range(m):
        big[4 * j:4 * j + 4, 4 * j:4 * j + 4] = r[j] - var[own[j]] * np.outer(gz[j], gz[j])
    for i in range(nv):
        col = np.zeros(4 * m)
        for j in np.flatnonzero(own == i):
            col[4 * j:4 * j + 4] = gz[j]
        big += var[i] * np.outer(col, col)
    inv = np.linalg.inv(big)
    assert np.allclose(lam, h.T @ inv @ h, rtol=1e-9, atol=1e-9 * np.abs(lam).max())
    assert np.allclose(eta, h.T @ inv @ z.ravel(), rtol=1e-9, atol=1e-9 * np.abs(eta).max())
    # the rows taken as independent (each with its own full heading variance) are not the same information
    lam_ind, eta_ind = np.zeros((d, d)), np.zeros(d)
    hh = np.zeros((m, 4, 8))
    hh[:, :, :4], hh[:, :, 4:] = -np.eye(4), np.eye(4)
    hth, htz = _information(hh, np.linalg.inv(r), z)
    _scatter(lam_ind, eta_ind, ind, hth, htz)
    assert not np.allclose(lam_ind, lam, rtol=1e-3)


def test_heading_from_state_rows_linearize_the_conversion():
    """With the heading the direction of the velocity state, a row's H on the velocity is - dz/dpsi dpsi/dv:
    the converted row moves with a small change of the velocity as H predicts (finite differences)."""
    from coloc.core.detections import SensorDetections, to_net_frame
    from coloc.methods.joint_oracle import _heading_state_information

    rng = np.random.default_rng(5)
    m = 4
    det = SensorDetections(range=rng.uniform(5, 60, m), bearing=rng.uniform(-1, 1, m), range_rate=rng.normal(0, 5, m),
                           mount_x=rng.uniform(0, 3, m), yaw=rng.uniform(-1, 1, m), sigma_range=np.full(m, 0.1),
                           sigma_bearing=np.full(m, 0.005), sigma_range_rate=np.full(m, 0.03))
    v = rng.normal(0, 8, (m, 2))
    psi = np.arctan2(v[:, 1], v[:, 0])
    z, r0 = to_net_frame(det, psi, np.zeros(m))
    # one row at a time, one vehicle (cols 0-3) and one feature (cols 4-7): recover H from the information
    for j in range(m):
        sub = SensorDetections(**{k: np.asarray(getattr(det, k))[j:j + 1] for k in (f.name for f in dataclasses.fields(det))})
        lam, eta = np.zeros((8, 8)), np.zeros(8)
        ind = np.arange(8)[None, :]
        _heading_state_information(lam, eta, ind, sub, psi[j:j + 1], v[j:j + 1], z[j:j + 1], r0[j:j + 1])
        # H^T R^-1 H = lam with R = r0: H's velocity columns from lam's vehicle-velocity / feature block
        dv = 1e-6 * rng.normal(size=2)
        psi2 = np.arctan2(v[j, 1] + dv[1], v[j, 0] + dv[0])
        z2, _ = to_net_frame(sub, np.array([psi2]), np.zeros(1))
        # the world's row for a velocity v + dv is the same body-frame measurement seen with the truer heading:
        # z(psi_hat) - z(psi_true) = -(H_v) (v_true - v_hat) to first order, i.e. z(psi2) - z(psi) = -H_v dv
        hvel = -(z2[0] - z[j])
        # H_v as built: -gz g_v^T; read it back from the information: lam[4:, 2:4] = R^-1 H_v (feature's H = I)
        h_built = np.linalg.solve(np.linalg.inv(r0[j]), lam[4:, 2:4])
        h_built[2:4] += np.eye(2)  # model (4)'s -I on the relative velocity; the rest is the heading's part
        assert np.allclose(h_built @ dv, hvel, rtol=1e-4, atol=1e-9)


def test_front_slip_moves_a_turning_vehicle_across_its_heading():
    """The world reports the front bumper and the body axis (SUMO): turning at yaw rate w, the bumper moves
    sideways by about l w Ts a step. The term is across the mid-step heading, proportional to w, zero when
    driving straight, and its residual covariance is rank one across, capped; without the IMU the rate is the
    one the net-frame input turns the velocity at."""
    from types import SimpleNamespace

    from coloc.methods.joint_oracle import _front_slip

    w = OracleWorld(front_lever_m=2.25, front_slip_sigma_per_rad=2.5, front_slip_sigma_max_m=0.25)
    om = np.array([0.0, 0.2, -0.2, 1.0])
    psi_end = np.array([0.3, 1.0, -2.0, 0.5])  # heading at t (the IMU input's heading: at t-1 plus w Ts)
    frame = SimpleNamespace(imu=SimpleNamespace(yaw_rate=om))
    surv = np.arange(4)
    mean, cov = _front_slip(w, frame, surv, np.zeros((4, 2)), psi_end, np.zeros((4, 2)), DT, 1.0)
    mid = psi_end - 0.5 * om * DT
    nrm = np.stack([-np.sin(mid), np.cos(mid)], axis=1)
    assert np.allclose(mean, (2.25 * om * DT)[:, None] * nrm)
    assert np.allclose(mean[0], 0.0) and np.allclose(cov[0], 0.0)
    along = np.stack([np.cos(mid), np.sin(mid)], axis=1)
    assert np.allclose(np.einsum("ni,nij,nj->n", along, cov, along), 0.0)
    sd = np.sqrt(np.einsum("ni,nij,nj->n", nrm, cov, nrm))
    assert np.allclose(sd, np.minimum(2.5 * np.abs(om) * DT, 0.25))
    # without the IMU: w = (v x a) / |v|^2 of the velocity at t-1 and the net-frame input
    v0 = np.array([[10.0, 0.0], [0.5, 0.0]])
    acc = np.array([[0.0, 2.0], [0.0, 2.0]])
    mean, _ = _front_slip(w, SimpleNamespace(imu=None), np.arange(2), v0, None, acc, DT, 1.0)
    mid0 = 0.5 * 0.2 * DT  # heading of v0 (0) plus half the step's turn
    assert np.allclose(mean[0], 2.25 * 0.2 * DT * np.array([-math.sin(mid0), math.cos(mid0)]))
    assert np.allclose(mean[1], 0.0)  # below the minimum speed the rate is not known: no term


def test_course_constraint_linearizes_the_velocity_along_the_heading():
    """heading_state: 0 = u_perp(psi)^T v. The row's H is the gradient of h(psi, v) = -sin psi vx + cos psi vy at the
    linearization point (finite differences), and H x_hat - z = h(x_hat)."""
    from coloc.methods.joint_oracle import _course_information

    rng = np.random.default_rng(11)
    n, vd, ho = 3, 6, 4
    mean = rng.normal(0, 5, n * vd)
    lam, eta = np.zeros((n * vd, n * vd)), np.zeros(n * vd)
    _course_information(lam, eta, mean, n, vd, ho, 1.0)
    blk = mean.reshape(n, vd)

    def h(psi, v):
        return -math.sin(psi) * v[0] + math.cos(psi) * v[1]

    for i in range(n):
        cols = vd * i + np.array([2, 3, ho])
        sub = lam[np.ix_(cols, cols)]  # = H^T H (unit noise): rank one
        psi, v = blk[i, ho], blk[i, 2:4]
        eps = 1e-6
        grad = np.array([(h(psi, v + [eps, 0]) - h(psi, v - [eps, 0])) / (2 * eps),
                         (h(psi, v + [0, eps]) - h(psi, v - [0, eps])) / (2 * eps),
                         (h(psi + eps, v) - h(psi - eps, v)) / (2 * eps)])
        assert np.allclose(sub, np.outer(grad, grad), atol=1e-8)
        z = (eta[cols] @ grad) / (grad @ grad)  # eta = H^T z
        assert abs(grad @ mean[cols] - z - h(psi, v)) < 1e-6  # grad: finite differences


def _turning_run(rng, world: OracleWorld, steps: int):
    """One vehicle driving curves at 8-14 m/s, kinematics of the world (velocity along the heading, psi_mid =
    psi_{t-1} + r Ts / 2, couplers/sensing/inertial.py), a gyroscope with a turn-on bias and white noise, white GNSS
    fixes of std 3 m (velocity 0.1 m/s). Returns the frames and the true heading and gyroscope bias at the end."""
    from coloc.core.inertial import ImuFrame

    psi, speed = rng.uniform(-math.pi, math.pi), 10.0
    v = speed * np.array([math.cos(psi), math.sin(psi)])
    p = np.zeros(2)
    bias = math.radians(world.gyro_turn_on_sigma) * rng.standard_normal()
    frames = []
    for step in range(steps):
        r = 0.15 * math.sin(0.05 * step) if step else 0.0
        if step:
            psi_prev, v_prev = psi, v
            psi = psi_prev + r * DT
            speed = float(np.clip(speed + rng.normal(0, 0.2), 8.0, 14.0))
            v = speed * np.array([math.cos(psi), math.sin(psi)])
            a_net = (v - v_prev) / DT
            p = p + 0.5 * DT * (v + v_prev)
            mid = psi_prev + 0.5 * r * DT
            c, s = math.cos(mid), math.sin(mid)
            a_body = np.array([c * a_net[0] + s * a_net[1], -s * a_net[0] + c * a_net[1]])
        else:
            a_body = np.zeros(2)
        gyro = r + bias + rng.normal(0, math.radians(world.gyro_noise_density) / math.sqrt(DT))
        zg = np.concatenate([p + rng.normal(0, 3.0, 2), v + rng.normal(0, 0.1, 2)])[None, :]
        prior_r = np.diag([9.0, 9.0, 0.01, 0.01])[None] if step == 0 else None
        f = _frame(step * DT, 1, rng, np.array([step == 0]), np.array([3.0]), zg, np.array([0.1]),
                   np.empty(0, dtype=np.int64), np.empty((0, 4)), np.empty((0, 4, 4)),
                   zg.copy() if step == 0 else None, prior_r)
        frames.append(Frame(**{**f.__dict__, "accel": np.zeros((1, 2)),
                               "imu": ImuFrame(accel_body=a_body[None, :], yaw_rate=np.array([gyro]))}))
    return frames, psi, bias


@pytest.mark.slow  # 20 runs of 200 steps: about a minute on the 2-core machine
def test_heading_state_tracks_the_heading_and_the_gyroscope_bias():
    """heading_state: over 20 runs of 200 steps with a biased gyroscope (turn-on 0.5 deg/s, the world's default), the
    heading and the bias are recovered from the fixes' course and the yaw rate, their normalized squared errors
    average near 1 (1 dof each; band of 20 runs at 99 % with a factor 2 margin), and the state's heading is better
    than the fixes' course."""
    world = OracleWorld(accel_turn_on_sigma=0.0, accel_bias_sigma=1e-3, gyro_turn_on_sigma=0.5, gyro_bias_sigma=0.0497,
                       gyro_noise_density=0.01944, heading_state=True)
    assert world.vehicle_dim == 8 and world.heading_offset == 6
    ho = world.heading_offset
    e_psi, e_b, n_psi, n_b = [], [], [], []
    for seed in range(20):
        frames, psi, bias = _turning_run(np.random.default_rng(300 + seed), world, 200)
        est = JointOracle(params=PARAMS, world=world)
        for f in frames:
            est.step_with_association(f, np.empty(0, dtype=np.int64))
        m, c = est.state.mean, est.state.cov
        d = (m[ho] - psi + math.pi) % (2 * math.pi) - math.pi
        e_psi.append(d)
        e_b.append(m[ho + 1] - bias)
        n_psi.append(d * d / c[ho, ho])
        n_b.append((m[ho + 1] - bias) ** 2 / c[ho + 1, ho + 1])
    hi = chi2.ppf(0.995, 20) / 20
    assert np.mean(n_psi) <= 2 * hi and np.mean(n_b) <= 2 * hi, (np.mean(n_psi), np.mean(n_b))
    assert np.sqrt(np.mean(np.square(e_b))) < math.radians(0.1)  # against the 0.5 deg/s turn-on bias
    assert np.sqrt(np.mean(np.square(e_psi))) < 0.1 / 10.0  # the fixes' course: 0.1 m/s / 10 m/s


def test_heading_linearization_point_and_row_gate():
    """heading_row_max_std_deg: a survivor with a narrow predicted heading keeps its mean as the linearization point
    and its rows; one with a wide heading but a well-known velocity is linearized at the velocity's direction (and
    keeps its rows); one with both wide (standing) loses its rows; a fresh vehicle's point is its fix's course, its
    rows kept only when that course is narrow (fast fix) and the gate is a std in degrees."""
    from coloc.methods.joint_oracle_rows import _heading_linearization

    world = OracleWorld(accel_turn_on_sigma=0.0, gyro_turn_on_sigma=0.5, heading_state=True,
                        heading_row_max_std_deg=2.0)
    vd, ho = world.vehicle_dim, world.heading_offset
    ns = 3
    p = np.eye(vd * ns) * 1e-4
    xv = np.zeros((ns, vd))
    xv[:, 2:4] = [[10.0, 0.0], [0.0, 10.0], [0.05, 0.0]]
    p[ho, ho] = math.radians(1.0) ** 2  # vehicle 0: narrow heading
    p[vd + ho, vd + ho] = 1.0  # vehicle 1: wide heading, velocity known to 1 cm/s at 10 m/s
    p[2 * vd + ho, 2 * vd + ho] = 1.0  # vehicle 2: wide heading, standing
    p[2 * vd + 2:2 * vd + 4, 2 * vd + 2:2 * vd + 4] = np.eye(2) * 0.01
    fresh = np.array([False, False, False, True, True])
    zg = np.zeros((5, 4))
    zg[3, 2:] = [10.0, 0.0]  # fresh and fast: course to 0.1 / 10 rad
    zg[4, 2:] = [0.3, 0.0]  # fresh and slow
    rg = np.tile(np.diag([9.0, 9.0, 0.01, 0.01]), (5, 1, 1))
    psi_lin, out = _heading_linearization(world, p, xv, np.arange(3), fresh, zg, rg)
    assert np.isnan(psi_lin[[0, 2, 3, 4]]).all() and psi_lin[1] == pytest.approx(math.pi / 2)
    assert out.tolist() == [False, False, True, False, True]
    wide = OracleWorld(**{**world.__dict__, "heading_row_max_std_deg": 60.0})
    assert not _heading_linearization(wide, p, xv, np.arange(3), fresh, zg, rg)[1][:4].any()


def test_field_read_share_is_the_field_increment_over_the_position_error():
    """field_read_noise: the fix's extra variance share is (1 - s) f 2 (1 - exp(-r / L)), r the predicted position's
    RMS error (survivors) or sqrt(2) sigma (entering vehicles); it grows with r and is 0 for an exact position. The
    increment variance of the world's field (random Fourier features of the exponential kernel) over a distance
    r is that of the kernel, 2 (1 - exp(-r / L)), within the 64 frequencies' spread (a factor 1.5)."""
    from coloc.methods.joint_oracle_rows import _field_read_share
    from couplers.sensing.gnss_error import exponential_kernel_frequencies

    world = OracleWorld(gnss="field", common_share=0.5, field_share=0.5, field_corr_length_m=50.0,
                        local_corr_length_m=20.0, field_read_noise=True)
    vd = world.vehicle_dim
    p = np.zeros((2 * vd, 2 * vd))
    p[0, 0] = p[1, 1] = 2.0  # survivor 0: r = 2 m
    sig = np.array([3.0, 3.0, 4.0])
    out = _field_read_share(world, p, np.array([0, 1]), sig, 0.5)
    assert out[0] == pytest.approx(0.25 * 2.0 * (1.0 - math.exp(-2.0 / 50.0)))
    assert out[1] == 0.0  # survivor 1: exact position
    assert out[2] == pytest.approx(0.25 * 2.0 * (1.0 - math.exp(-math.sqrt(2.0) * 4.0 / 50.0)))
    rng = np.random.default_rng(5)
    om = exponential_kernel_frequencies(rng, 64, 50.0)
    for r in (2.0, 5.0):
        ang = rng.uniform(0, 2 * math.pi, 4000)
        inc = np.mean(2.0 * (1.0 - np.cos(r * np.stack([np.cos(ang), np.sin(ang)], 1) @ om.T)))
        assert 1 / 1.5 < inc / (2.0 * (1.0 - math.exp(-r / 50.0))) < 1.5, (r, inc)
