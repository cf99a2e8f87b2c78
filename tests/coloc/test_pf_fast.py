"""The approximate pair sums of ICP-DA-PF (coloc.kernels.pf_fast, ``[pf] kernel = "fast"``): every entry
within the stated 1e-3 of brute force, on random problems; the PF with them end to end."""

import numba as nb
import numpy as np
import pytest

from coloc.inference.params import IcpParams
from coloc.kernels.pf import KernelWorkspace, transform_batch, transform_brute
from coloc.kernels.pf_fast import (
    CODE_REL_ERROR,
    EXP_REL_ERROR,
    FAST_REL_TOL,
    FastRepeatedTransforms,
    _code,
    _decode,
    _exp32,
    fast_kept_problem_count,
    fast_transform,
    fast_transform_batch,
)
from coloc.methods.icp_da_pf import IcpDaPf, PfParams
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION
from tests.coloc.test_pf_kernels import _four_problems, _problem


@nb.njit(cache=False)
def _exp_and_code(ys):
    e, c = np.empty(ys.size), np.empty(ys.size)
    for i in range(ys.size):
        e[i] = _exp32(ys[i])
        c[i] = _decode(_code(ys[i]))
    return e, c


def test_float32_exponential_and_16_bit_values_within_their_stated_errors():
    ys = np.linspace(0.0, 43.5, 400001).astype(np.float32)
    e, c = _exp_and_code(ys)
    ref = np.exp(-ys.astype(float))
    exp_err, code_err = np.max(np.abs(e / ref - 1)), np.max(np.abs(c / ref - 1))
    print(f"float32 exp: largest relative error {exp_err:.2e}; 16-bit values {code_err:.2e}")
    assert exp_err < EXP_REL_ERROR
    assert code_err < CODE_REL_ERROR + EXP_REL_ERROR


def _far_problem(rng):
    """Targets 5-60 whitened units from a source cloud, sources with outliers beyond 32 units: the
    float64 guards of the float32 path."""
    src = rng.normal(0.0, 1.0, (200, 4))
    src[:3] *= 40.0
    tgt = rng.normal(0.0, 1.0, (150, 4)) + rng.uniform(5.0, 60.0) * rng.normal(size=4) / 2.0
    return src, rng.normal(0.0, 3.0, 200), tgt, np.eye(4) * rng.uniform(0.5, 2.0)


def test_fast_sums_within_1e3_of_scipy_per_entry():
    """One-off sums (eta, the output set): every entry, tails included, within FAST_REL_TOL relative of
    the full log-sum-exp; 40 problems of the exact kernels' test (clouds 0.05 to 20 kernel widths) and
    10 with far targets and outlying sources."""
    rng = np.random.default_rng(7)
    worst = 0.0
    for trial in range(50):
        src, logw, tgt, r = _problem(rng, [0.05, 0.3, 1.0, 5.0][trial % 4]) if trial < 40 else _far_problem(rng)
        got = fast_transform(src, logw, tgt, r)
        ref = transform_brute(src, logw, tgt, r)
        ok = np.isfinite(ref)
        assert np.array_equal(ok, np.isfinite(got))
        worst = max(worst, float(np.max(np.abs(np.expm1(got[ok] - ref[ok])), initial=0.0)))
    print(f"fast one-off sums: largest relative error {worst:.2e}")
    assert worst < FAST_REL_TOL


def test_kept_16_bit_matrices_within_1e3_for_any_weights():
    """BPA-L's path: 16-bit matrices built with the first weights, summed for new ones up to e^+-150
    apart; every entry within FAST_REL_TOL of scipy, and the first sum equal to a later one with the
    same weights."""
    rng = np.random.default_rng(8)
    worst = 0.0
    for trial in range(50):
        src, logw, tgt, r = _problem(rng, [0.05, 0.3, 1.0, 5.0][trial % 4]) if trial < 40 else _far_problem(rng)
        rt = FastRepeatedTransforms(src[None], [0], np.zeros((1, 4)), tgt[None], [0], np.zeros((1, 4)), r[None], 1e9)
        assert rt.kept.all()
        first, pairs = rt.sum(logw[None])
        assert pairs.sum() == src.shape[0] * tgt.shape[0]
        again, pairs = rt.sum(logw[None])
        assert pairs.sum() == 0
        np.testing.assert_array_equal(first, again)
        for spread in (0.0, 5.0, 50.0):
            lw = logw + rng.normal(0.0, spread, logw.size)
            got, _ = rt.sum(lw[None])
            ref = transform_brute(src, lw, tgt, r)
            ok = np.isfinite(ref)
            assert np.array_equal(ok, np.isfinite(got[0]))
            worst = max(worst, float(np.max(np.abs(np.expm1(got[0][ok] - ref[ok])), initial=0.0)))
    print(f"kept 16-bit matrices: largest relative error {worst:.2e}")
    assert worst < FAST_REL_TOL


def test_tail_mass_is_summed_exactly_where_the_codes_cannot_vouch():
    """A near source of weight e^-300 and a far one (whitened distance 20) of weight 1: the far term
    e^-200 is below the smallest code relative to the near one; the entry is summed exactly."""
    src = np.zeros((2, 4))
    src[1, 0] = 20.0
    logw = np.array([-300.0, 0.0])
    ref = transform_brute(src, logw, np.zeros((1, 4)), np.eye(4))
    rt = FastRepeatedTransforms(src[None], [0], np.zeros((1, 4)), np.zeros((1, 1, 4)), [0], np.zeros((1, 4)),
                                np.eye(4)[None], 1e9)
    rt.sum(np.zeros((1, 2)))
    np.testing.assert_allclose(rt.sum(logw[None])[0][0], ref, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast_transform(src, logw, np.zeros((1, 4)), np.eye(4)), ref, rtol=0, atol=1e-12)


def test_budget_storage_and_thread_count_leave_the_bytes_unchanged():
    """Problems beyond the memory budget are summed directly: within the bound of the kept ones; the
    workspace storage and the numba thread count give the same bytes."""
    rng = np.random.default_rng(5)
    args = _four_problems(rng, 600, [1.0, 1.0, 0.2, 0.2], [0.04, 0.04, 0.01, 0.01], [0, 1, 2, 0], [1, 2, 0, 2])
    logw, later = rng.normal(size=(4, 600)), rng.normal(size=(4, 600))
    ref, _ = transform_batch(args[0], logw, *args[1:], kernel="brute")
    per_problem = 2 * 600 * 600
    results = []
    for budget, n_kept in ((0, 0), (2.5 * per_problem, 2), (1e9, 4)):
        assert fast_kept_problem_count(4, 600, 600, budget) == n_kept
        rt = FastRepeatedTransforms(*args, budget)
        got, pairs = rt.sum(logw)
        assert np.max(np.abs(np.expm1(got - ref))) < FAST_REL_TOL
        _, pairs = rt.sum(later)
        assert np.all(pairs[:n_kept] == 0) and np.all(pairs[n_kept:] == 600 * 600)
        results.append(rt.sum(later)[0])
    direct, _ = fast_transform_batch(args[0], later, *args[1:])
    np.testing.assert_array_equal(results[0], direct)  # nothing kept: the direct sums
    storage = KernelWorkspace().arrays(4 * 600 * 600 // 2)[0].view(np.uint16)
    rt = FastRepeatedTransforms(*args, 1e9, storage)
    rt.sum(logw)
    np.testing.assert_array_equal(rt.sum(later)[0], results[2])
    threads = nb.get_num_threads()
    try:
        nb.set_num_threads(1)
        one = FastRepeatedTransforms(*args, 1e9)
        one.sum(logw)
        np.testing.assert_array_equal(one.sum(later)[0], results[2])
        np.testing.assert_array_equal(fast_transform_batch(args[0], later, *args[1:])[0], direct)
    finally:
        nb.set_num_threads(threads)


def test_pf_with_the_fast_kernel_steps_like_the_exact_one_and_repeats_its_bytes():
    """The separated-features scene with kernel = "fast": the first step (before resampling carries any
    difference on) within a millimetre of the exact tree, the same associations, and the same bytes
    when run again. Later steps differ by Monte Carlo noise: a weight off by 1e-3 moves a systematic
    resampling draw now and then (printed, not asserted; tools/pf_equivalence.py judges that)."""
    frames = road_frames(steps=8, spacing=10.0)
    runs = {}
    for kernel in ("tree", "fast", "fast"):
        est = IcpDaPf(params=IcpParams(motion=MOTION),
                      pf=PfParams(vehicle_particles=300, feature_particles=300, seed=3, kernel=kernel))
        out = [est.step(f.without_truth()) for f in frames]
        runs.setdefault(kernel, []).append(out)
    tree, (fast, fast_again) = runs["tree"][0], runs["fast"]
    for a, b in zip(fast, fast_again):
        assert a.mean.tobytes() == b.mean.tobytes()
    for a, b in zip(tree, fast):
        np.testing.assert_array_equal(a.v2f_assignment >= 0, b.v2f_assignment >= 0)
    first = [i for i, f in enumerate(frames) if f.v2f_owner.size][0]
    assert np.max(np.abs(tree[first].mean - fast[first].mean)) < 1e-3
    gap = max(float(np.max(np.abs(a.mean[:, :2] - b.mean[:, :2]))) for a, b in zip(tree, fast))
    print(f"first step with V2F: {np.max(np.abs(tree[first].mean - fast[first].mean)):.1e}; "
          f"largest position difference over the run {gap:.3f} m")


def test_fast_is_a_kernel_of_pf_params():
    assert PfParams(kernel="fast").kernel == "fast"
    with pytest.raises(ValueError):
        PfParams(kernel="fgt")
