"""Consensus over lossy, asymmetric links (coloc.inference.lossy_consensus) against the exact average and max."""

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from coloc.inference.lossy_consensus import (lossy_max_consensus, lossy_metropolis_consensus,
                                             running_sum_consensus)


def _graph(seed: int, n: int = 30, radius: float = 350.0):
    """A connected random geometric graph (vehicles in a 1 km square, V2V range ``radius``)."""
    rng = np.random.default_rng(seed)
    while True:
        xy = rng.uniform(0.0, 1000.0, (n, 2))
        adj = (np.hypot(*(xy[:, None] - xy[None]).transpose(2, 0, 1)) < radius) & ~np.eye(n, dtype=bool)
        if connected_components(sp.csr_matrix(adj))[0] == 1:
            src, dst = np.nonzero(adj)
            return src, dst, rng


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_running_sums_reach_the_exact_average_with_asymmetric_losses(seed):
    """30 % of packets lost, independently per direction and round: i may hear j while j does not hear i."""
    src, dst, rng = _graph(seed)
    values = rng.normal(size=(30, 4, 4))
    delivered = rng.random((600, src.size)) > 0.3
    out = running_sum_consensus(values, src, dst, delivered)
    assert np.abs(out - values.mean(axis=0)).max() < 1e-9


def test_plain_metropolis_fails_that_test_and_passes_without_losses():
    src, dst, rng = _graph(1)
    values = rng.normal(size=(30, 3))
    lossy = rng.random((600, src.size)) > 0.3
    agreed = lossy_metropolis_consensus(values, src, dst, lossy)
    assert np.ptp(agreed, axis=0).max() < 1e-6  # the nodes agree ...
    assert np.abs(agreed - values.mean(axis=0)).max() > 1e-3  # ... on a value that is not the average
    perfect = np.ones((600, src.size), dtype=bool)
    assert np.abs(lossy_metropolis_consensus(values, src, dst, perfect) - values.mean(axis=0)).max() < 1e-9
    assert np.abs(running_sum_consensus(values, src, dst, perfect) - values.mean(axis=0)).max() < 1e-9


def test_weights_give_the_weighted_average():
    src, dst, rng = _graph(4)
    x = rng.normal(size=(30, 2))
    w = rng.uniform(0.5, 2.0, 30)
    out = running_sum_consensus(w[:, None] * x, src, dst, rng.random((600, src.size)) > 0.2, weights=w)
    assert np.abs(out - (w[:, None] * x).sum(axis=0) / w.sum()).max() < 1e-9


def test_the_round_budget_is_what_was_given():
    """R rows of deliveries are R rounds: a budget of 3 rounds leaves the nodes apart, 10 bring them closer."""
    src, dst, rng = _graph(5)
    x = rng.normal(size=(30, 1))
    three = running_sum_consensus(x, src, dst, np.ones((3, src.size), dtype=bool))
    assert np.ptp(three) > 1e-3
    ten = running_sum_consensus(x, src, dst, np.ones((10, src.size), dtype=bool))
    assert np.ptp(ten) < np.ptp(three)


def test_max_consensus_with_losses_reaches_the_maximum_and_never_exceeds_it():
    src, dst, rng = _graph(6)
    x = rng.normal(size=(30, 5))
    few = lossy_max_consensus(x, src, dst, rng.random((1, src.size)) > 0.5)
    assert (few <= x.max(axis=0)).all() and (few >= x).all()
    out = lossy_max_consensus(x, src, dst, rng.random((200, src.size)) > 0.5)
    assert np.array_equal(out, np.broadcast_to(x.max(axis=0), x.shape))
