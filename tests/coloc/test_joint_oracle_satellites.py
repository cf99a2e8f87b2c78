"""``joint_oracle`` in the satellite world (``OracleWorld(gnss="satellites")``, ``Frame.oracle_gnss``): its update
against batch least squares over a tiny scene (2 vehicles, 5 satellites, a few steps) to 1e-9, and the oracle's
channel ignored by every other estimator (tests/coloc/test_contract.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp

from coloc.core.frame import Frame, OracleGnss
from coloc.core.models import driving_noise_cov, input_matrix, transition_matrix
from coloc.methods.joint_oracle import JointOracle, OracleWorld
from test_joint_oracle import DT, PARAMS, _factor, random_priors

S = 5
WORLD = OracleWorld(gnss="satellites", sv_count=S, sv_tau_s=40.0, multipath_corr_length_m=math.inf,
                    nlos_d_mean_m=6.0, nlos_d_std_m=3.0)


def _scene(rng, n=2, steps=4):
    frames = []
    prior_z, prior_r = random_priors(rng, n)
    for step in range(steps):
        used = rng.random((n, S)) < 0.9
        gain = rng.normal(0, 0.6, (n, 2, S)) * used[:, None, :]
        vgain = rng.normal(0, 0.6, (n, 2, S)) * used[:, None, :]
        ch = OracleGnss(gain=gain, used=used, reflected=used & (rng.random((n, S)) < 0.3),
                        elevation=rng.uniform(0.2, 1.4, S), fix=np.ones(n, bool), velocity_gain=vgain,
                        velocity_used=used, velocity_solved=np.ones(n, bool))
        gr = np.tile(np.diag([9.0, 9.0, 0.04, 0.04]), (n, 1, 1))  # the reported blocks: not used with a channel
        frames.append(Frame(
            t=step * DT, dt=DT, vehicle_ids=np.array([f"v{i}" for i in range(n)], dtype=object),
            entered=np.full(n, step == 0), prior_z=prior_z if step == 0 else np.full((n, 4), np.nan),
            prior_R=prior_r if step == 0 else np.full((n, 4, 4), np.nan), accel=rng.normal(0, 0.5, (n, 2)),
            gnss_z=rng.normal(0, 5, (n, 4)), gnss_R=gr, v2f_z=np.empty((0, 4)), v2f_owner=np.empty(0, np.int64),
            v2f_R=np.empty((0, 4, 4)), neighbors=sp.csr_matrix((n, n), dtype=bool), oracle_gnss=ch))
    return frames


def _batch(frames, w: OracleWorld):
    """Weighted least squares over the trajectory, parametrized by the initial state and the unit process noises
    (as tests/coloc/test_joint_oracle.py): the final joint (mean, covariance), vehicles [p, v, l], satellites."""
    n, vd, sd = frames[0].n_vehicles, w.vehicle_dim, w.satellite_dim
    d = vd * n + sd
    a4, b4 = transition_matrix(DT), input_matrix(DT)
    lam0, eta0 = np.zeros((d, d)), np.zeros(d)
    f0 = frames[0]
    for i in range(n):
        li = np.linalg.inv(f0.prior_R[i])
        lam0[vd * i:vd * i + 4, vd * i:vd * i + 4] += li
        eta0[vd * i:vd * i + 4] += li @ f0.prior_z[i]
        g = f0.oracle_gnss.gain[i]
        mp = (w.multipath_m / np.sin(f0.oracle_gnss.elevation)) ** 2
        lam0[vd * i + 4:vd * i + 6, vd * i + 4:vd * i + 6] += np.linalg.inv(g @ np.diag(mp) @ g.T + 1e-6 * np.eye(2))
    lam0[-sd:, -sd:] += np.eye(sd)
    phi, off = np.eye(d), np.zeros(d)
    rows = []
    for t, f in enumerate(frames):
        if t > 0:
            fm, inp, lq = np.eye(d), np.zeros(d), []
            for i in range(n):
                s = slice(vd * i, vd * i + 4)
                fm[s, s] = a4
                inp[s] = b4 @ f.accel[i]
                lq.append((s, _factor(driving_noise_cov(np.zeros((1, 2)), DT, PARAMS.motion)[0])))
            a_s = math.exp(-DT / w.sv_tau_s)
            fm[-sd:, -sd:] = a_s * np.eye(sd)
            lq.append((slice(d - sd, d), math.sqrt(1 - a_s ** 2) * np.eye(sd)))
            g = np.zeros((d, sum(q.shape[1] for _, q in lq)))
            c = 0
            for s, q in lq:
                g[s, c:c + q.shape[1]] = q
                c += q.shape[1]
            phi, off = np.hstack([fm @ phi, g]), fm @ off + inp
        ch = f.oracle_gnss
        el = ch.elevation
        cols = np.zeros((S, sd))  # clock/orbit, ionosphere (Klobuchar), troposphere (SBAS mapping)
        cols[np.arange(S), np.arange(S)] = w.sv_clock_orbit_m
        cols[np.arange(S), S + np.arange(S)] = w.iono_vertical_m * (1 + 16 * (0.53 - el / np.pi) ** 3)
        cols[:, 2 * S] = w.tropo_zenith_m * 1.001 / np.sqrt(0.002001 + np.sin(el) ** 2)
        for i in range(n):
            k, refl = ch.gain[i], ch.reflected[i]
            h = np.zeros((2, d))
            h[:, vd * i:vd * i + 2] = np.eye(2)
            h[:, vd * i + 4:vd * i + 6] = np.eye(2)
            h[:, -sd:] = k @ cols
            own = w.code_noise_a_m ** 2 + w.code_noise_b_m ** 2 / np.sin(el) + refl * (2 * np.cos(el) * 3.0) ** 2
            z = f.gnss_z[i, :2] - k @ (refl * 2 * np.cos(el) * 6.0)
            rows.append((t, h, k @ np.diag(own) @ k.T, z))
            hv = np.zeros((2, d))
            hv[:, vd * i + 2:vd * i + 4] = np.eye(2)
            kv = ch.velocity_gain[i]
            rows.append((t, hv, kv @ np.diag(w.doppler_noise_mps ** 2 * (1 + 1 / np.sin(el))) @ kv.T, f.gnss_z[i, 2:]))
        rows = [(r if len(r) == 6 else (*r, phi.copy(), off.copy())) for r in rows]
    p = phi.shape[1]
    lam, eta = np.zeros((p, p)), np.zeros(p)
    lam[:d, :d] += lam0
    eta[:d] += eta0
    lam[d:, d:] += np.eye(p - d)
    for _, h, r, z, ph_t, off_t in rows:
        ph = np.hstack([h @ ph_t, np.zeros((2, p - ph_t.shape[1]))])
        ri = np.linalg.inv(r)
        lam += ph.T @ ri @ ph
        eta += ph.T @ ri @ (z - h @ off_t)
    cov_theta = np.linalg.inv(lam)
    return phi @ cov_theta @ eta + off, phi @ cov_theta @ phi.T


@pytest.mark.parametrize("seed", [0, 1])
def test_satellite_update_equals_batch_least_squares(seed):
    frames = _scene(np.random.default_rng(seed))
    est = JointOracle(params=PARAMS, world=WORLD)
    for f in frames:
        est.step_with_association(f, np.empty(0, np.int64))
    mean, cov = _batch(frames, WORLD)
    np.testing.assert_allclose(est.state.mean, mean, rtol=0, atol=1e-9 * max(1.0, float(np.abs(mean).max())))
    np.testing.assert_allclose(est.state.cov, cov, rtol=0, atol=1e-9 * max(1.0, float(np.abs(cov).max())))
    # the comparison can fail: told another extra path's mean, the filter misses the batch solution
    other = JointOracle(params=PARAMS, world=OracleWorld(**{**WORLD.__dict__, "nlos_d_mean_m": 1.0}))
    for f in frames:
        other.step_with_association(f, np.empty(0, np.int64))
    assert np.abs(other.state.mean - mean).max() > 1e-3
