"""ICP-DA-PF over the lossy V2X channel: the average consensus of (28) as running-sum
ratio consensus and the max consensus of (29) as lossy max consensus on the rounds the channel
delivers, within the step's round budget (coloc.methods.icp_da_pf.pf_bpa_localization)."""

from dataclasses import replace

import numpy as np
import scipy.sparse as sp

from coloc.core.models import MotionParams
from coloc.core.v2x import V2xFrame
from coloc.inference.params import IcpParams
from coloc.inference.row_consensus import ChannelRowConsensus
from coloc.methods.icp_da_pf import IcpDaPf, PfParams
from scenes import road_frames

MOTION = MotionParams(sigma_along=0.08, sigma_cross=0.08)
PF = PfParams(vehicle_particles=300, feature_particles=300, seed=3)


def with_channel(frame, p=1.0, rounds=0, seed=7):
    return replace(frame, v2x=V2xFrame(np.full(frame.neighbors.nnz, float(p)), rounds, seed))


def run(frames, params, channel=None):
    est = IcpDaPf(params=params, pf=PF)
    out = []
    for f in frames:
        g = f if channel is None else with_channel(f, *channel)
        res = est.step_with_association(g.without_truth(), f.truth.v2f_feature)
        out.append((res, est.last))
    return out


def test_perfect_channel_equals_lossless_on_complete_components():
    """Every vehicle hears every other (v2v range 250 m): one round of either consensus is exact, so a
    channel that delivers everything gives the lossless estimates."""
    frames = road_frames(steps=4, n=4)
    params = IcpParams(motion=MOTION, consensus_iterations=3)
    plain = run(frames, params)
    chan = run(frames, params, channel=(1.0, 0))
    for (a, ia), (b, ib) in zip(plain, chan):
        np.testing.assert_allclose(a.mean, b.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(a.cov, b.cov, rtol=0, atol=1e-9)
        assert ia.iterations == ib.iterations
        np.testing.assert_array_equal(ia.comm.bytes, ib.comm.bytes)  # the same rounds counted


def test_the_pf_stops_at_the_round_budget_counted():
    """Budget 3, 2 consensus rounds per exchange: iteration 1 gets 2 average rounds and 1 max round,
    then BPA-L stops; the communication counts those 3 rounds."""
    frames = road_frames(steps=3, n=4)
    params = IcpParams(motion=MOTION, consensus_iterations=2, bpa_max_iterations=10, stop_pos_m=1e-9,
                       stop_vel_mps=1e-9)
    for res, info in run(frames, params, channel=(0.8, 3)):
        assert info.iterations == 1
        assert info.comm.rounds == 3
    unlimited = run(frames, params, channel=(0.8, 0))
    assert max(info.iterations for _, info in unlimited) > 1


def test_heavy_loss_keeps_weights_normalised_and_covariances_spd():
    frames = road_frames(steps=5, n=5, v2v_range=25.0)
    params = IcpParams(motion=MOTION, consensus_iterations=4)
    for res, info in run(frames, params, channel=(0.3, 6)):
        assert np.all(np.isfinite(res.mean))
        np.testing.assert_allclose(res.cov, np.swapaxes(res.cov, -1, -2), atol=1e-9)
        assert np.all(np.linalg.eigvalsh(res.cov) > 0)
        assert info.comm.rounds <= 6


def test_lossy_max_consensus_reaches_the_component_maximum():
    """Rows (vehicle, feature) on a chain of 6 vehicles that all see feature 0: with 40 % loss per link
    and round, enough rounds give every row the largest value; fewer never exceed it."""
    n = 6
    a = sp.diags([np.ones(n - 1), np.ones(n - 1)], [-1, 1], shape=(n, n), format="csr").astype(bool)
    v2x = V2xFrame(np.full(a.nnz, 0.6), 0, 11)
    owner = np.arange(n)
    ch = ChannelRowConsensus(owner, np.zeros(n, np.int64), 1, a, v2x)
    x = np.random.default_rng(2).normal(size=(n, 3))
    few = ch.maximum(x, 2)
    assert np.all(few <= x.max(axis=0)) and np.all(few >= x)
    many = ch.maximum(x, 80)
    np.testing.assert_array_equal(many, np.broadcast_to(x.max(axis=0), x.shape))
    assert ch.rounds_used == 82
