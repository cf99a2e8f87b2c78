"""The gate bound of ``association_terms_kernel`` (coloc/kernels/icp_fused.py): pairs that
d2 >= |nu_b|^2 / tr S_bb (b the position or the velocity block) puts beyond the chi-square gate are not solved, and nothing else changes: the
solved pairs' terms are those of the kernel without a gate, and ICP-DA-LC's weights equal the numpy
reference's, byte for byte, on clutter-heavy scenes (most rows far from every track)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from coloc.inference.gaussian import chi2_ppf
from coloc.kernels import icp_fused
from coloc.kernels.icp_fused import association_terms_kernel
from coloc.methods.icp_da_lc import LcParams, association_weights


def _spd(rng, k, pos, vel):
    a = rng.normal(size=(k, 4, 4)) * 0.3
    return a @ np.swapaxes(a, 1, 2) + np.diag([pos, pos, vel, vel])


def _clutter_scene(seed: int, n_v: int = 25, n_t: int = 120, rows_per_v: int = 10, nan_rows: int = 0):
    """Vehicles and tracks over 400 m x 400 m; a fifth of the rows from a track near the vehicle, the
    rest clutter uniform within 60 m (as the realistic sensing draws it)."""
    rng = np.random.default_rng(seed)
    v_mean = np.c_[rng.uniform(0, 400, (n_v, 2)), rng.normal(0, 5, (n_v, 2))]
    t_mean = np.c_[rng.uniform(0, 400, (n_t, 2)), rng.normal(0, 0.1, (n_t, 2))]
    owner = rng.integers(0, n_v, n_v * rows_per_v)
    z = np.c_[rng.uniform(-60, 60, (owner.size, 2)), -v_mean[owner, 2:] + rng.normal(0, 0.1, (owner.size, 2))]
    real = rng.random(owner.size) < 0.2
    near = np.argmin(np.hypot(*(t_mean[None, :, :2] - v_mean[owner][:, None, :2]).transpose(2, 0, 1)), axis=1)
    z[real] = t_mean[near[real]] - v_mean[owner[real]] + rng.normal(0, 0.5, (real.sum(), 4))
    z[:nan_rows] = np.nan
    return (v_mean, _spd(rng, n_v, 4.0, 0.5), t_mean, _spd(rng, n_t, 1.0, 0.01), owner, z,
            _spd(rng, owner.size, 0.5, 0.01))


def _kernel(scene, rs: float, gate: float):
    v_mean, v_cov, t_mean, t_cov, owner, z, r = scene
    return association_terms_kernel(v_mean, v_cov, t_mean, t_cov, owner.astype(np.int64), z, r, rs, gate)


@pytest.mark.parametrize("seed", range(8))
def test_pruned_pairs_are_beyond_the_gate_and_the_rest_is_solved_as_without_a_gate(seed):
    scene = _clutter_scene(seed, nan_rows=3 if seed % 2 else 0)
    gate = chi2_ppf(0.99, 4)
    pv, pt, pr, log_lik, d2 = _kernel(scene, 75.0, gate)
    pv0, pt0, pr0, log0, d20 = _kernel(scene, 75.0, math.inf)  # every pair solved
    for x, y in [(pv, pv0), (pt, pt0), (pr, pr0)]:
        assert x.tobytes() == y.tobytes()
    pruned = np.isinf(d2)
    assert 0.5 * pr.size < pruned.sum() < pr.size  # most pairs of a clutter scene are cut, not all
    assert (d20[pruned] > gate).all()  # the bound never cuts a pair inside the gate
    solved = ~pruned
    assert d2[solved].tobytes() == d20[solved].tobytes()
    inside = solved & (d20 <= gate)
    assert inside.any() and log_lik[inside].tobytes() == log0[inside].tobytes()
    if seed % 2:  # NaN rows: never cut, NaN as before
        assert np.isnan(d2[np.isin(pr, np.arange(3))]).all()


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("lc", [
    LcParams(sensing_range_m=75.0),  # the log-weights kernel (no clutter, no field of view)
    LcParams(sensing_range_m=75.0, clutter_intensity=3.35e-4),  # the terms kernel + numpy densities
    LcParams(sensing_range_m=75.0, clutter_intensity=3.35e-4, pairing="paper"),  # no gate: nothing cut
])
def test_weights_on_clutter_scenes_equal_the_numpy_reference(seed, lc, monkeypatch):
    scene = _clutter_scene(100 + seed)
    out = {}
    for fused in (False, True):
        monkeypatch.setattr(icp_fused, "FUSED", fused)
        out[fused] = association_weights(*scene, lc)
    for x, y in zip(out[False], out[True]):
        assert x.shape == y.shape and x.tobytes() == y.tobytes()
    assert (out[True][3] > 0).any()


@pytest.mark.parametrize("seed", range(4))
def test_candidates_with_non_finite_positions_and_a_wide_net_equal_the_numpy_reference(seed, monkeypatch):
    """The x window of the candidate search: tracks and vehicles without a finite position, a track
    with an infinite spread (the window then spans every track), vehicles far apart."""
    v_mean, v_cov, t_mean, t_cov, owner, z, r = _clutter_scene(200 + seed, n_v=40, n_t=200)
    v_mean[:, 0] *= 10.0  # 4 km along x
    t_mean[:, 0] *= 10.0
    t_mean[3, 0], t_mean[5, 1], v_mean[2, 0] = np.nan, np.inf, np.nan
    if seed % 2:
        t_cov[7, 0, 0] = np.inf
    scene = (v_mean, v_cov, t_mean, t_cov, owner, z, r)
    lc = LcParams(sensing_range_m=75.0, clutter_intensity=3.35e-4)
    out = {}
    for fused in (False, True):
        monkeypatch.setattr(icp_fused, "FUSED", fused)
        with np.errstate(invalid="ignore"):
            out[fused] = association_weights(*scene, lc)
    for x, y in zip(out[False][:3], out[True][:3]):
        assert x.tobytes() == y.tobytes()
    assert np.array_equal(out[False][3], out[True][3], equal_nan=True)
    assert out[True][0].size > 0
