"""Particle-pair kernels of ICP-DA-PF (coloc.kernels.pf): fast and brute force against scipy."""

import numpy as np
import pytest

from coloc.kernels.pf import (
    KernelWorkspace,
    RepeatedTransforms,
    fixed_transforms,
    fixed_transforms_summed,
    kept_problem_count,
    transform,
    transform_batch,
    transform_brute,
    transform_fixed,
)
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
    from coloc.kernels.pf import _exp_neg

    y = np.concatenate([np.linspace(0.0, 689.99, 200001), np.random.default_rng(0).uniform(0.0, 40.0, 100000),
                        np.log(2.0) * (np.arange(995) + 0.5)])  # the range reduction's half-way points
    got = np.array([_exp_neg(v) for v in y])
    rel = np.abs(got / np.exp(-y) - 1.0)
    print(f"largest relative error {rel.max():.1e}")
    assert rel.max() < 1e-12
    # beyond exp(-690) exactly 0: terms 1e-300 below the leaf's scale
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


def _four_problems(rng, j, spread, r_diag, src_index, tgt_index):
    """Four transform_batch problems over three random sets (J particles, per-axis ``spread``),
    targets shifted at random: (sets, src_index, src_shift, sets, tgt_index, tgt_shift, r)."""
    spread = np.asarray(spread)
    sets = rng.normal(size=(3, j, 4)) * spread
    shift = rng.normal(size=(4, 4)) * spread * 0.3
    r = np.tile(np.diag(r_diag), (4, 1, 1))
    return sets, np.array(src_index), np.zeros((4, 4)), sets, np.array(tgt_index), shift, r


def _fixed_one(src, tgt, r, max_bytes=1e9, kernel="tree", rel_tol=1e-6):
    return fixed_transforms(src[None], np.zeros(1, int), np.zeros((1, 4)), tgt[None], np.zeros(1, int),
                            np.zeros((1, 4)), r[None], kernel, rel_tol, max_bytes)


def test_kept_kernel_matrices_agree_with_scipy_to_1e6_for_any_weights():
    """The BPA-L path (kernel matrices built once, summed for every iteration's cavity weights): every
    entry within 1e-6 of the full log-sum-exp, tails included (40 random problems x 3 weight vectors,
    the tree test's clouds)."""
    rng = np.random.default_rng(7)
    worst = 0.0
    for trial in range(40):
        src, logw, tgt, r = _problem(rng, [0.05, 0.3, 1.0, 5.0][trial % 4])
        fixed = _fixed_one(src, tgt, r)
        assert fixed.kept.all()
        for spread in (0.0, 5.0, 50.0):  # new weights each "iteration", up to e^+-150 apart
            lw = logw + rng.normal(0.0, spread, logw.size)
            got, pairs = transform_fixed(fixed, lw[None])
            assert pairs.sum() == 0  # no kernel evaluated: the matrix product
            ref = transform_brute(src, lw, tgt, r)
            ok = np.isfinite(ref)
            assert np.array_equal(ok, np.isfinite(got[0]))
            worst = max(worst, float(np.max(np.abs(np.expm1(got[0][ok] - ref[ok])), initial=0.0)))
    print(f"kept matrices: largest relative error {worst:.2e}")
    assert worst < 1e-6


def test_kept_matrices_fall_back_to_the_exact_sum_where_float32_cannot_vouch():
    """Target at the origin; a near source of weight e^-300 and a far one (whitened distance 20) of
    weight 1. The far term e^-200 dominates, but its kept value is 0 (200 > 87 below the nearest);
    the product then holds only the near term, below the floor, and the entry is summed exactly."""
    src = np.zeros((2, 4))
    src[1, 0] = 20.0
    logw = np.array([-300.0, 0.0])
    fixed = _fixed_one(src, np.zeros((1, 4)), np.eye(4))
    assert fixed.values[0, 0, 1] == 0.0
    got, _ = transform_fixed(fixed, logw[None])
    np.testing.assert_allclose(got[0], transform_brute(src, logw, np.zeros((1, 4)), np.eye(4)), rtol=0, atol=1e-12)


def test_kept_matrices_within_the_memory_budget_and_in_the_workspace():
    """Problems beyond the budget are summed by the tree; results do not depend on the split, on the
    storage or on a tolerance float32 cannot meet (nothing kept then)."""
    rng = np.random.default_rng(5)
    args = _four_problems(rng, 600, [1.0, 1.0, 0.2, 0.2], [0.04, 0.04, 0.01, 0.01], [0, 1, 2, 0], [1, 2, 0, 2])
    sets = args[0]
    logw = rng.normal(size=(4, 600))
    ref, _ = transform_batch(sets, logw, *args[1:], kernel="brute")
    bytes_per_problem = 4 * 600 * 600
    for budget, n_kept in ((0, 0), (2.5 * bytes_per_problem, 2), (1e9, 4)):
        assert kept_problem_count(4, 600, 600, "tree", 1e-6, budget) == n_kept
        fixed = fixed_transforms(*args, "tree", 1e-6, budget)
        assert fixed.kept.tolist() == [p < n_kept for p in range(4)]
        got, pairs = transform_fixed(fixed, logw)
        assert np.all(pairs[:n_kept] == 0) and np.all(pairs[n_kept:] > 0)
        assert np.max(np.abs(np.expm1(got - ref))) < 1e-6
    workspace = KernelWorkspace()
    a, b = workspace.arrays(4 * 600 * 600, 4 * 600 * 600)
    assert not np.shares_memory(a, b)
    in_workspace, _ = transform_fixed(fixed_transforms(*args, "tree", 1e-6, 1e9, a), logw)
    np.testing.assert_array_equal(in_workspace, got)
    assert kept_problem_count(4, 600, 600, "tree", 1e-8, 1e9) == 0  # below float32's 2^-24
    assert kept_problem_count(4, 600, 600, "brute", 1e-6, 1e9) == 0  # the reference stays brute force


def test_building_with_the_first_sum_equals_building_then_summing():
    """BPA-L's first iteration sums each kept row while building it (fixed_transforms_summed): the same
    values, the same kept matrices and the same later sums as fixed_transforms then transform_fixed,
    whatever share of the problems the budget keeps; all-(-inf) weights give -inf."""
    rng = np.random.default_rng(11)
    args = _four_problems(rng, 500, [2.0, 2.0, 0.3, 0.3], [0.09, 0.09, 0.02, 0.02], [0, 1, 2, 1], [1, 2, 0, 0])
    sets = args[0]
    first, later = rng.normal(0.0, 3.0, (4, 500)), rng.normal(0.0, 3.0, (4, 500))
    first[3] = -np.inf
    for budget in (0, 2.5 * 4 * 500 * 500, 1e9):
        plain = fixed_transforms(*args, "tree", 1e-6, budget)
        ref, ref_pairs = transform_fixed(plain, first)
        summed, got, pairs = fixed_transforms_summed(sets, first, *args[1:], "tree", 1e-6, budget)
        np.testing.assert_array_equal(summed.kept, plain.kept)
        np.testing.assert_array_equal(summed.values, plain.values)
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
        assert np.all(got[3] == -np.inf)
        np.testing.assert_array_equal(pairs, ref_pairs)
        np.testing.assert_array_equal(transform_fixed(summed, later)[0], transform_fixed(plain, later)[0])
        brute, _ = transform_batch(sets, first, *args[1:], kernel="brute")
        assert np.max(np.abs(np.expm1(got[:3] - brute[:3]))) < 1e-6
        # BPA-L's view: the first sum builds (its evaluations include the build's), later ones are products.
        repeated = RepeatedTransforms(*args, "tree", 1e-6, budget)
        once, once_pairs = repeated.sum(first)
        np.testing.assert_array_equal(once, got)
        np.testing.assert_array_equal(once_pairs, pairs + summed.build_pairs)
        again, again_pairs = repeated.sum(later)
        np.testing.assert_array_equal(again, transform_fixed(plain, later)[0])
        assert np.all(again_pairs[summed.kept] == 0)
