"""Particle-pair kernels of ICP-DA-PF (coloc.pf_kernels): fast and brute force against scipy."""

import numpy as np
import pytest

from coloc.pf_kernels import transform, transform_batch, transform_brute
from scriptload import load_script


def _problem(rng, scale):
    js, jt = rng.integers(1, 300, 2)
    src = rng.normal(0.0, scale, (js, 4))
    tgt = rng.normal(rng.normal(0.0, scale, 4), scale, (jt, 4))
    logw = rng.normal(0.0, 3.0, js)
    a = rng.normal(size=(4, 4)) * 0.05
    r = np.diag(rng.uniform(0.005, 0.05, 4)) + a @ a.T  # correlated noise: whitening is tested too
    return src, logw, tgt, r


@pytest.mark.parametrize("kernel", ["tree", "brute"])
def test_kernels_agree_with_scipy_to_1e6_relative_per_entry(kernel):
    """Every entry, tails included, within 1e-6 relative of the full log-sum-exp (40 random problems,
    clouds from 0.05 to 20 times the kernel width)."""
    rng = np.random.default_rng(7)
    worst = 0.0
    for trial in range(40):
        src, logw, tgt, r = _problem(rng, [0.05, 0.3, 1.0, 5.0][trial % 4])
        fast = transform(src, logw, tgt, r, kernel=kernel)
        ref = transform_brute(src, logw, tgt, r)
        ok = np.isfinite(ref)
        assert np.array_equal(ok, np.isfinite(fast))
        worst = max(worst, float(np.max(np.abs(np.expm1(fast[ok] - ref[ok])), initial=0.0)))
    print(f"{kernel}: largest relative error {worst:.2e}")
    assert worst < 1e-6


def test_batch_equals_single_problems_and_counts_fewer_pairs_on_narrow_kernels():
    rng = np.random.default_rng(3)
    spread = np.array([2.0, 2.0, 0.1, 0.1])  # metres, m/s: clouds wide in position, narrow in velocity
    vehicles = rng.normal(size=(2, 400, 4)) * spread
    tracks = rng.normal(size=(3, 3000, 4)) * spread  # sources: several k-d tree leaves
    src_index, tgt_index = np.array([0, 1, 2, 0]), np.array([1, 0, 1, 0])
    shift = rng.normal(size=(4, 4)) * spread * 0.3
    logw = rng.normal(size=(4, 3000))
    r = np.tile(np.diag([0.01, 0.01, 0.01, 0.01]), (4, 1, 1))
    out, pairs = transform_batch(tracks, logw, src_index, np.zeros((4, 4)), vehicles, tgt_index, shift, r)
    for p in range(4):
        single = transform(tracks[src_index[p]], logw[p], vehicles[tgt_index[p]] + shift[p], r[p])
        np.testing.assert_allclose(out[p], single, rtol=0, atol=1e-12)
    _, brute_pairs = transform_batch(tracks, logw, src_index, np.zeros((4, 4)), vehicles, tgt_index, shift, r,
                                     kernel="brute")
    assert np.all(brute_pairs == 400 * 3000)
    print(f"tree kernel evaluated {pairs.sum() / brute_pairs.sum():.2f} of the pairs")
    assert pairs.sum() < 0.5 * brute_pairs.sum()  # 2 m clouds, 0.1 m kernel: the tree prunes


def test_zero_weights_and_empty_batches():
    out = transform(np.zeros((3, 4)), np.full(3, -np.inf), np.ones((2, 4)), np.eye(4))
    assert np.all(out == -np.inf)
    out, pairs = transform_batch(np.zeros((1, 3, 4)), np.zeros((0, 3)), np.zeros(0, int), np.zeros((0, 4)),
                                 np.zeros((1, 5, 4)), np.zeros(0, int), np.zeros((0, 4)), np.zeros((0, 4, 4)))
    assert out.shape == (0, 5) and pairs.shape == (0,)


def test_polynomial_exp_of_the_leaf_loop():
    from coloc.pf_kernels import _exp_neg

    y = np.linspace(0.0, 689.99, 200001)
    got = np.array([_exp_neg(v) for v in y])
    rel = np.abs(got / np.exp(-y) - 1.0)
    print(f"largest relative error {rel.max():.1e}")
    assert rel.max() < 2e-10
    # beyond exp(-690) exactly 0: the squarings would pass through subnormal numbers (10x slower)
    assert _exp_neg(690.0) == 0.0 and _exp_neg(746.0) == 0.0 and _exp_neg(1e6) == 0.0


def test_least_exact_share_counts_the_terms_a_1e6_sum_needs():
    """bench/pf_kernels.py's lower bound on the pairs any 1e-6-exact sum evaluates.

    One target at the origin, identity kernel: sources at whitened distances 0, 1, 3, 6, 8
    give terms 1, e^-0.5, e^-4.5, e^-18, e^-32. The last two together are 9e-9 of the sum,
    below 1e-6, but e^-4.5 (6.9e-3 of it) is not: three terms are needed, a share of 3 / 5.
    """
    bench = load_script("bench/pf_kernels.py")
    src = np.zeros((5, 4))
    src[:, 0] = [0.0, 1.0, 3.0, 6.0, 8.0]
    assert bench.least_exact_share(src, np.zeros((1, 4)), np.eye(4)) == pytest.approx(3 / 5)
    # A tolerance above e^-4.5 / sum: two terms suffice.
    assert bench.least_exact_share(src, np.zeros((1, 4)), np.eye(4), rel_tol=1e-2) == pytest.approx(2 / 5)
    # The tree kernel never evaluates fewer pairs than this bound (it is exact to 1e-6).
    s, t, r = bench.case_problem(400, 8.0, 0.1, 0.2, 0.1, True)
    pairs, _ = bench.run_case(s, t, r, "tree")
    assert pairs / 400 ** 2 >= bench.least_exact_share(s, t, r)
