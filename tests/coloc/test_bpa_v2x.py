"""Gaussian BPA-L over the lossy V2X channel and the communication counts.

The consensus of (20) runs as running-sum ratio consensus on the V2V links each round delivered
(coloc.inference.row_consensus.ChannelRowConsensus), rounds counted over the step within
``rounds_per_step``; without ``frame.v2x`` nothing changes (the shipped configs' hashes, in the
branch notes)."""

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

import coloc.inference.row_consensus as row_consensus_module
from coloc.core.models import MotionParams
from coloc.core.v2x import V2xFrame, directed_links
from coloc.inference.bpa import bpa_localization
from coloc.inference.comm import GAUSSIAN_CONSENSUS_WORDS, LC_BIRTH_WORDS, WORD_BYTES
from coloc.inference.lossy_consensus import running_sum_consensus
from coloc.inference.params import IcpParams
from coloc.inference.row_consensus import ChannelRowConsensus, consensus_graph, row_links
from coloc.kernels.lossy import running_sum_kernel
from coloc.methods.centralized import one_step_joint
from coloc.methods.icp_da_lc import IcpDaLc
from coloc.methods.icp_known_da import IcpKnownDA, IcpState, vehicle_prior_beliefs
from scenes import road_frames

MOTION = MotionParams(sigma_along=0.08, sigma_cross=0.08)


def exact_params(consensus_iterations=200, **kw):
    """BPA-L run to convergence (stopping thresholds far below the Sec. V-A rule)."""
    base = dict(motion=MOTION, consensus_iterations=consensus_iterations, bpa_max_iterations=1000,
                stop_pos_m=1e-10, stop_vel_mps=1e-10)
    base.update(kw)
    return IcpParams(**base)


def with_channel(frame, p=1.0, rounds=0, seed=7):
    nnz = frame.neighbors.nnz
    return replace(frame, v2x=V2xFrame(np.full(nnz, float(p)), rounds, seed))


def bpa_inputs(frame, params):
    """b^(0), the feature priors of a first step and the rows, for a direct bpa_localization call."""
    state = IcpState()
    assoc = frame.truth.v2f_feature
    used = assoc >= 0
    b0_mean, b0_cov = vehicle_prior_beliefs(state.ids, state.mean, state.cov, frame, params)
    pred = state.features.predict(frame.dt, params)
    fl, fe = pred.prior_information(np.unique(assoc[used]), assoc[used], frame.vehicle_ids[frame.v2f_owner[used]],
                                    params)
    return b0_mean, b0_cov, assoc, fl, fe


def run_bpa(frame, params, v2x="frame"):
    b0_mean, b0_cov, assoc, fl, fe = bpa_inputs(frame, params)
    return bpa_localization(b0_mean, b0_cov, b0_mean, b0_cov, frame.v2f_owner, assoc, frame.v2f_z, frame.v2f_R,
                            frame.neighbors, fl, fe, params, v2x=frame.v2x if v2x == "frame" else v2x)


def assert_spd(cov):
    assert np.all(np.isfinite(cov))
    np.testing.assert_allclose(cov, np.swapaxes(cov, -1, -2), atol=1e-9)
    assert np.all(np.linalg.eigvalsh(cov) > 0)


# ----------------------------------------------------------------------------- building blocks


def test_row_links_are_the_row_graph_with_the_v2v_link_each_rides_on():
    f = road_frames(steps=1, v2v_range=25.0)[0]
    assoc = f.truth.v2f_feature
    used = assoc >= 0
    owner, feat = f.v2f_owner[used], assoc[used]
    _, gidx = np.unique(feat, return_inverse=True)
    src, dst, link = row_links(owner, gidx, int(gidx.max()) + 1, f.neighbors)
    graph = consensus_graph(owner, feat, f.neighbors).tocoo()
    assert sorted(zip(dst.tolist(), src.tolist())) == sorted(zip(graph.row.tolist(), graph.col.tolist()))
    v_src, v_dst = directed_links(f.neighbors)
    np.testing.assert_array_equal(v_src[link], owner[src])  # row src's vehicle sends on link j -> i
    np.testing.assert_array_equal(v_dst[link], owner[dst])
    np.testing.assert_array_equal(gidx[src], gidx[dst])


@pytest.mark.parametrize("seed", [1, 2])
def test_running_sum_kernel_equals_the_numpy_reference(seed):
    rng = np.random.default_rng(seed)
    n = 25
    adj = rng.random((n, n)) < 0.2
    adj = (adj | adj.T) & ~np.eye(n, dtype=bool)
    src, dst = np.nonzero(adj)
    x = rng.normal(size=(n, 14))
    got = rng.random((40, src.size)) > 0.3
    share = 1.0 / (1.0 + np.bincount(src, minlength=n))
    np.testing.assert_allclose(running_sum_kernel(x, share, src.astype(np.int64), dst.astype(np.int64), got),
                               running_sum_consensus(x, src, dst, got), rtol=0, atol=1e-12)


def test_channel_must_be_aligned_with_neighbors():
    f = road_frames(steps=1)[0]
    bad = V2xFrame(np.ones(f.neighbors.nnz + 1), 0, 1)
    with pytest.raises(ValueError, match="aligned"):
        ChannelRowConsensus(np.zeros(1, np.int64), np.zeros(1, np.int64), 1, f.neighbors, bad)


# ----------------------------------------------------------------------------- BPA-L on the channel


def test_perfect_channel_equals_lossless_bpa_on_complete_components():
    """Rc = 250 m: every feature's observers are all V2V neighbours, so both consensus forms are exact
    after one round and BPA-L takes the same path: equal to rounding."""
    frames = road_frames(steps=1)
    f = frames[0]
    params = IcpParams(motion=MOTION)
    lossless = run_bpa(f, params, v2x=None)
    lossy = run_bpa(with_channel(f, 1.0, 0), params)
    assert lossless.iterations == lossy.iterations
    np.testing.assert_allclose(lossy.mean, lossless.mean, rtol=0, atol=1e-9)
    np.testing.assert_allclose(lossy.cov, lossless.cov, rtol=0, atol=1e-9)


def test_perfect_channel_and_lossless_both_reach_the_exact_joint_on_sparse_links():
    """Rc = 25 m: chains of observers, where ratio consensus and Metropolis have different finite-round
    iterates; with 300 rounds per iteration and BPA-L to convergence both give the exact one-step
    joint (centralized product) means, and agree with each other."""
    f = road_frames(steps=1, v2v_range=25.0)[0]
    params = exact_params(300)
    b0_mean, b0_cov, assoc, fl, fe = bpa_inputs(f, params)
    jm, _, _, _, _ = one_step_joint(b0_mean, b0_cov, fl, fe, f.v2f_owner, assoc, f.v2f_z, f.v2f_R)
    lossless = run_bpa(f, params, v2x=None)
    lossy = run_bpa(with_channel(f, 1.0, 0), params)
    gap_lossless = np.abs(lossless.mean - jm).max()
    gap_lossy = np.abs(lossy.mean - jm).max()
    print(f"gap to the joint: lossless {gap_lossless:.1e}, perfect channel {gap_lossy:.1e}, "
          f"between them {np.abs(lossy.mean - lossless.mean).max():.1e}")
    assert gap_lossless < 1e-6 and gap_lossy < 1e-6
    np.testing.assert_allclose(lossy.mean, lossless.mean, rtol=0, atol=1e-6)
    assert_spd(lossy.cov)


@pytest.mark.parametrize("v2v_range", [250.0, 25.0])
def test_thirty_percent_asymmetric_loss_converges_to_the_lossless_result(v2v_range):
    """Every directed link loses 30 % of its packets, independently per direction and round; with 300
    rounds per BPA-L iteration the vehicles reach the lossless BPA-L to 1e-6 m (m/s)."""
    f = road_frames(steps=1, v2v_range=v2v_range)[0]
    params = exact_params(300)
    lossless = run_bpa(f, params, v2x=None)
    lossy = run_bpa(with_channel(f, 0.7, 0, seed=11), params)
    gap = np.abs(lossy.mean - lossless.mean).max()
    print(f"Rc {v2v_range:g} m, 30 % loss: mean gap {gap:.1e}, cov gap {np.abs(lossy.cov - lossless.cov).max():.1e}")
    assert gap < 1e-6
    np.testing.assert_allclose(lossy.cov, lossless.cov, rtol=0, atol=1e-6)
    assert_spd(lossy.cov)
    # ... and the losses did happen: few rounds leave a visible gap.
    few = run_bpa(with_channel(f, 0.7, 0, seed=11), exact_params(1))
    print(f"one round per iteration: mean gap {np.abs(few.mean - lossless.mean).max():.1e}")
    assert np.abs(few.mean - lossless.mean).max() > 1e-4


def test_heavy_loss_every_step_keeps_covariances_spd():
    frames = road_frames(steps=10, v2v_range=25.0)
    est = IcpKnownDA(IcpParams(motion=MOTION))
    for f in frames:
        out = est.step_with_association(with_channel(f, 0.3, 3, seed=int(f.t) + 1), f.truth.v2f_feature)
        assert_spd(out.cov)
        assert np.all(np.isfinite(out.mean))


def test_a_method_stops_at_the_round_budget_counted(monkeypatch):
    """10 consensus rounds per BPA-L iteration, 25 rounds per step: iterations of 10, 10 and 5 rounds,
    then BPA-L stops (not converged); the channel is asked for rounds 0..24 only, each once."""
    asked = []
    real = row_consensus_module.round_deliveries

    def counting(v2x, r):
        asked.append(r)
        return real(v2x, r)

    monkeypatch.setattr(row_consensus_module, "round_deliveries", counting)
    f = road_frames(steps=1, v2v_range=25.0)[0]
    params = exact_params(10)
    res = run_bpa(with_channel(f, 0.8, 25), params)
    assert asked == list(range(25))
    assert res.iterations == 3 and not res.converged
    assert res.comm.rounds == 25
    # A budget smaller than one iteration's rounds: one iteration with what fits.
    asked.clear()
    res = run_bpa(with_channel(f, 0.8, 3), params)
    assert asked == [0, 1, 2] and res.iterations == 1 and res.comm.rounds == 3
    # Through the method: every active vehicle broadcast exactly rounds_per_step messages.
    asked.clear()
    est = IcpKnownDA(params)
    est.step_with_association(with_channel(f, 0.8, 7), f.truth.v2f_feature)
    assert asked == list(range(7)) and est.last_iterations == 1 and not est.last_converged
    assert est.last_comm.rounds == 7
    assert set(est.last_comm.messages.tolist()) <= {0, 7} and est.last_comm.messages.max() == 7
    # Unlimited: as many rounds as the iterations want.
    res = run_bpa(with_channel(f, 0.8, 0), IcpParams(motion=MOTION, consensus_iterations=10))
    assert res.comm.rounds == 10 * res.iterations


def test_without_a_channel_nothing_is_drawn(monkeypatch):
    def fail(*_):
        raise AssertionError("no channel: no round realised")

    monkeypatch.setattr(row_consensus_module, "round_deliveries", fail)
    f = road_frames(steps=1, v2v_range=25.0)[0]
    res = run_bpa(f, IcpParams(motion=MOTION), v2x=None)
    assert res.comm.rounds == res.iterations * 20


# ----------------------------------------------------------------------------- communication counts


def tiny_scene():
    """Three vehicles, all V2V neighbours; v0 and v1 observe features 5 and 9, v2 observes 9 and 3
    (nobody else sees 3). Rows: v0:5, v0:9, v1:5, v1:9, v2:9, v2:3."""
    f = road_frames(steps=1, n=3, v2v_range=250.0)[0]
    owner = np.array([0, 0, 1, 1, 2, 2])
    feature = np.array([5, 9, 5, 9, 9, 3])
    z = np.zeros((6, 4))
    z[:, 0] = 5.0
    r = np.broadcast_to(np.diag([0.04, 0.04, 0.01, 0.01]), (6, 4, 4)).copy()
    return f, owner, feature, z, r


def test_gaussian_consensus_count_by_hand():
    f, owner, feature, z, r = tiny_scene()
    params = IcpParams(motion=MOTION, consensus_iterations=4, bpa_max_iterations=3, stop_pos_m=0.0, stop_vel_mps=0.0)
    b0_mean, b0_cov = vehicle_prior_beliefs(np.empty(0, object), np.empty((0, 4)), np.empty((0, 4, 4)), f, params)
    k = np.unique(feature).size
    for v2x in (None, V2xFrame(np.full(f.neighbors.nnz, 0.9), 0, 3)):
        res = bpa_localization(b0_mean, b0_cov, b0_mean, b0_cov, owner, feature, z, r, f.neighbors,
                               np.zeros((k, 4, 4)), np.zeros((k, 4)), params, v2x=v2x)
        assert res.iterations == 3
        rounds = 3 * 4
        # v0: rows 5 and 9 shared; v1: 5 and 9; v2: 9 shared, 3 alone (not sent).
        np.testing.assert_array_equal(res.comm.messages, [rounds, rounds, rounds])
        word = GAUSSIAN_CONSENSUS_WORDS * WORD_BYTES
        assert word == 128  # id + 10 + 4 + (degree or running z), 8 bytes each
        np.testing.assert_array_equal(res.comm.bytes, [rounds * 2 * word, rounds * 2 * word, rounds * 1 * word])
        assert res.comm.rounds == rounds


def test_lc_counts_new_tracks_once():
    """First step of LC: every row starts a track (announced once: 6 words per row), then BPA-L."""
    f = road_frames(steps=1, n=3, v2v_range=250.0)[0]
    est = IcpDaLc(IcpParams(motion=MOTION))
    est.step(f)
    comm = est.last.comm
    rows = np.bincount(f.v2f_owner, minlength=f.n_vehicles)
    assert est.last.born > 0
    births = np.bincount(f.v2f_owner[est.last.row_track >= 0], minlength=f.n_vehicles)  # step 0: every track is new
    birth_bytes = births * LC_BIRTH_WORDS * WORD_BYTES
    consensus_bytes = comm.bytes - birth_bytes
    assert comm.rounds > 0
    np.testing.assert_array_equal(consensus_bytes % (GAUSSIAN_CONSENSUS_WORDS * WORD_BYTES * comm.rounds), 0)
    np.testing.assert_array_equal(comm.messages, (births > 0) + comm.rounds * (consensus_bytes > 0))
    assert rows.sum() == f.v2f_owner.size


def test_pf_count_by_hand():
    """Particle ICP: per BPA-L iteration C rounds of average consensus (id, degree, Jf log-weights) and
    max(C, 1) rounds of max consensus (id, Jf values); one announcement of the rows starting tracks."""
    from coloc.methods.icp_da_pf import PfParams, pf_step_comm

    f, *_ = tiny_scene()
    entry_vehicle = np.array([0, 0, 1, 1, 2, 2])
    entry_track = np.array([0, 1, 0, 1, 1, 2])  # track 2: v2 alone
    params = IcpParams(motion=MOTION, consensus_iterations=4)
    pf = PfParams(vehicle_particles=50, feature_particles=200)
    comm = pf_step_comm(entry_vehicle, entry_track, f.neighbors, np.array([2]), 3, 3, params, pf)
    per_entry = 3 * 4 * (2 + 200) + 3 * 4 * (1 + 200)
    np.testing.assert_array_equal(comm.messages, [24, 24, 25])
    np.testing.assert_array_equal(comm.bytes, np.array([2 * per_entry, 2 * per_entry, per_entry + 15]) * 8)
    assert comm.rounds == 24
    none = pf_step_comm(entry_vehicle, entry_track, f.neighbors, np.array([], np.int64), 3, 3,
                        IcpParams(motion=MOTION, consensus_iterations=0), pf)
    np.testing.assert_array_equal(none.messages, [3, 3, 3])  # max consensus still runs one round


def test_numpy_reference_loop_takes_the_same_channel_path(monkeypatch):
    """BPA_KERNELS = False (the batched numpy BPA-L) over the same lossy channel and budget: same
    iterations and rounds, results equal up to rounding."""
    import coloc.inference.bpa as bpa_module

    f = with_channel(road_frames(steps=1, v2v_range=25.0)[0], 0.7, 17, seed=5)
    params = IcpParams(motion=MOTION, consensus_iterations=6)
    kern = run_bpa(f, params)
    monkeypatch.setattr(bpa_module, "BPA_KERNELS", False)
    ref = run_bpa(f, params)
    assert (kern.iterations, kern.comm.rounds) == (ref.iterations, ref.comm.rounds) == (3, 17)
    np.testing.assert_allclose(kern.mean, ref.mean, rtol=0, atol=1e-8)
    np.testing.assert_allclose(kern.cov, ref.cov, rtol=0, atol=1e-8)


def test_even_budget_split_gives_every_iteration_rounds():
    """budget_split = "even", 10 rounds wanted per iteration, bpa_max_iterations 4, budget 10: the
    iterations get 10 // 4 = 2, 8 // 3 = 2, 6 // 2 = 3 and 3 rounds (BPA-L never converges here), so
    all four run; "greedy" spends the budget in the first iteration. Unlimited budget: no change."""
    f = road_frames(steps=1, v2v_range=25.0)[0]
    even = exact_params(10, bpa_max_iterations=4, budget_split="even")
    greedy = exact_params(10, bpa_max_iterations=4)
    res = run_bpa(with_channel(f, 0.8, 10), even)
    assert res.iterations == 4 and res.comm.rounds == 10
    assert run_bpa(with_channel(f, 0.8, 10), greedy).iterations == 1
    a = run_bpa(with_channel(f, 0.8, 0), even)
    b = run_bpa(with_channel(f, 0.8, 0), greedy)
    np.testing.assert_array_equal(a.mean, b.mean)
    # the split rule itself
    p = IcpParams(bpa_max_iterations=10, budget_split="even")
    assert [p.exchanges_left(i) for i in (1, 5, 10, 11)] == [10, 6, 1, 1]
    assert p.exchanges_left(1, per_iteration=2, done=1) == 19
    assert IcpParams().exchanges_left(1) == 1


def test_even_split_reaches_the_bound_under_a_tight_budget():
    """On complete components one consensus round per iteration is exact: with a budget of 4 rounds the
    even split runs 4 BPA-L iterations of one round and lands nearer the unlimited result than greedy's
    single iteration of 4 rounds."""
    f = road_frames(steps=1)[0]  # v2v range 250 m: one complete component
    ref = run_bpa(with_channel(f, 1.0, 0), exact_params(20, bpa_max_iterations=4))
    even = run_bpa(with_channel(f, 1.0, 4), exact_params(20, bpa_max_iterations=4, budget_split="even"))
    greedy = run_bpa(with_channel(f, 1.0, 4), exact_params(20, bpa_max_iterations=4))
    err_even = np.abs(even.mean - ref.mean).max()
    err_greedy = np.abs(greedy.mean - ref.mean).max()
    assert even.iterations == 4 and greedy.iterations == 1
    assert err_even < 1e-9 < err_greedy
