"""The receiver bias of ``[gnss_model]`` (:mod:`coloc.methods.gnss_bias`) as factors of the
``fg_topology_new`` fixed-lag smoother (:class:`coloc.methods.fg_topology.FgTopologyInfra`).

Per vehicle and step a bias variable b_t (Point2) beside the position p_t; with s = ``bias_share``,
a = exp(-Ts / tau) and R_t the position block of the covariance the receiver reports at t:

* fix: ``z_t = p_t + b_t + n``, ``n ~ N(0, (1 - s) R_t)``: a factor on (p_t, b_t), residual p + b - z;
* Gauss-Markov chain: ``b_t = a b_{t-1} + w``, ``w ~ N(0, (1 - a^2) s R_t)``: a between factor on
  (b_{t-1}, b_t), residual b_t - a b_{t-1} (gtsam's BetweenFactorPoint2 is the case a = 1; the
  transition here decays, so the factor is written out);
* start: the tracker's joint belief of (p, b) at the vehicle's first state (Cov(p, b) included):
  a factor on (p_t, b_t), residual [p - m_p, b - m_b] with that 4x4 covariance.

All three are linear; their Jacobians are constant blocks. gtsam is imported inside the functions.
"""

from __future__ import annotations

import numpy as np


def _linear_factor(gtsam, keys, blocks, offset, cov):
    """gtsam CustomFactor with residual sum_j blocks[j] x_j - offset and Gaussian noise ``cov``."""
    blocks = [np.asarray(b, dtype=float) for b in blocks]
    offset = np.asarray(offset, dtype=float)

    def error(this, values, jacobians):
        res = -offset.copy()
        for j, k in enumerate(this.keys()):
            res += blocks[j] @ values.atPoint2(k)
            if jacobians is not None:
                jacobians[j] = blocks[j]
        return res

    noise = gtsam.noiseModel.Gaussian.Covariance(np.asarray(cov, dtype=float))
    return gtsam.CustomFactor(noise, list(keys), error)


def fix_factor(gtsam, p_key: int, b_key: int, z: np.ndarray, r_pos: np.ndarray, share: float):
    """z = p + b + n, Var(n) = (1 - s) R_pos."""
    eye = np.eye(2)
    return _linear_factor(gtsam, (p_key, b_key), (eye, eye), z, (1.0 - share) * np.asarray(r_pos, float))


def chain_factor(gtsam, b_prev: int, b_key: int, decay: float, r_pos: np.ndarray, share: float):
    """b_t = a b_{t-1} + w, Var(w) = (1 - a^2) s R_pos."""
    eye = np.eye(2)
    return _linear_factor(gtsam, (b_prev, b_key), (-decay * eye, eye), np.zeros(2),
                          (1.0 - decay * decay) * share * np.asarray(r_pos, float))


def start_factor(gtsam, p_key: int, b_key: int, mean6: np.ndarray, cov6: np.ndarray):
    """The joint Gaussian prior of (p, b) from a 6-D [p, v, b] belief (its velocity marginalised out)."""
    sel = np.array([0, 1, 4, 5])
    z4, e4 = np.zeros((4, 2)), np.zeros((4, 2))
    z4[:2], e4[2:] = np.eye(2), np.eye(2)
    return _linear_factor(gtsam, (p_key, b_key), (z4, e4), np.asarray(mean6, float)[sel],
                          np.asarray(cov6, float)[np.ix_(sel, sel)])
