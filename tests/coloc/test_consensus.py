"""Tests of coloc.inference.consensus (Brambilla et al. Sec. IV-B, eqs. (28)-(29): average + max consensus)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import shortest_path

from coloc.inference.consensus import (
    average_consensus,
    connected_components,
    max_consensus,
    metropolis_weights,
)


def random_geometric_graph(rng: np.random.Generator, n: int, radius: float) -> sp.csr_matrix:
    pts = rng.random((n, 2))
    d = np.linalg.norm(pts[:, None, :] - pts[None, :, :], axis=-1)
    A = (d < radius) & ~np.eye(n, dtype=bool)
    return sp.csr_matrix(A)


def component_reduce(values: np.ndarray, labels: np.ndarray, how: str) -> np.ndarray:
    out = np.empty_like(values, dtype=float)
    for c in np.unique(labels):
        sel = labels == c
        out[sel] = getattr(values[sel], how)(axis=0)
    return out


@st.composite
def graphs(draw, max_n=25):
    n = draw(st.integers(1, max_n))
    seed = draw(st.integers(0, 2**32 - 1))
    radius = draw(st.floats(0.05, 0.8))
    return random_geometric_graph(np.random.default_rng(seed), n, radius), seed


# ---------------------------------------------------------------- weights


@settings(max_examples=100, deadline=None)
@given(graphs(max_n=40))
def test_metropolis_weights_doubly_stochastic_symmetric(g):
    A, _ = g
    W = metropolis_weights(A).toarray()
    n = A.shape[0]
    np.testing.assert_allclose(W.sum(axis=0), 1.0, atol=1e-14)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_array_equal(W, W.T)
    assert np.all(np.diag(W) > 0) and np.all(W >= 0)
    # support = edges + diagonal; weights 1/(1+max(d_i, d_j))
    Ad = A.toarray()
    np.testing.assert_array_equal((W > 0) & ~np.eye(n, dtype=bool), Ad)
    deg = Ad.sum(axis=1)
    i, j = np.nonzero(Ad)
    np.testing.assert_allclose(W[i, j], 1.0 / (1.0 + np.maximum(deg[i], deg[j])))


def test_adjacency_validation():
    with pytest.raises(ValueError):
        metropolis_weights(sp.csr_matrix(np.array([[0, 1], [0, 0]], dtype=bool)))  # not symmetric
    with pytest.raises(ValueError):
        metropolis_weights(sp.csr_matrix(np.eye(3, dtype=bool)))  # diagonal
    with pytest.raises(ValueError):
        metropolis_weights(sp.csr_matrix(np.zeros((2, 3), dtype=bool)))
    A = sp.csr_matrix(np.array([[0, 1], [1, 0]], dtype=bool))
    with pytest.raises(ValueError):
        average_consensus(np.zeros(3), A, 5)
    with pytest.raises(ValueError):
        average_consensus(np.zeros(2), A, 5, participants=np.array([1, 0]))  # not bool


# ---------------------------------------------------------------- average consensus


def test_average_converges_to_component_means():
    """2000 rounds on random geometric graphs (several components): error < 1e-9."""
    rng = np.random.default_rng(0)
    for trial in range(5):
        # two random geometric graphs side by side plus an isolated vehicle: >= 3 components
        A = sp.block_diag(
            [random_geometric_graph(rng, 35, 0.4), random_geometric_graph(rng, 24, 0.45), sp.csr_matrix((1, 1))],
            format="csr",
        ).astype(bool)
        n = A.shape[0]
        x = rng.normal(size=n) * 10.0
        ncomp, labels = connected_components(A)
        assert ncomp >= 3
        out = average_consensus(x, A, 2000)
        np.testing.assert_allclose(out, component_reduce(x, labels, "mean"), atol=1e-9, rtol=0)
        assert out[-1] == x[-1]


def test_average_error_within_spectral_bound():
    """Sparse graphs mix slowly: per component, ||x_t - mean|| <= slem(W)^t ||x_0 - mean||."""
    rng = np.random.default_rng(12)
    for _ in range(5):
        A = random_geometric_graph(rng, 50, 0.2)
        ncomp, labels = connected_components(A)
        W = metropolis_weights(A).toarray()
        x = rng.normal(size=50)
        mean = component_reduce(x, labels, "mean")
        for t in (10, 100, 1000):
            out = average_consensus(x, A, t)
            for c in range(ncomp):
                sel = labels == c
                if sel.sum() == 1:
                    assert out[sel][0] == x[sel][0]
                    continue
                ev = np.sort(np.abs(np.linalg.eigvalsh(W[np.ix_(sel, sel)])))
                bound = ev[-2] ** t * np.linalg.norm(x[sel] - mean[sel]) + 1e-12
                assert np.linalg.norm(out[sel] - mean[sel]) <= bound


def test_average_preserves_component_sum_each_iteration():
    rng = np.random.default_rng(1)
    A = random_geometric_graph(rng, 50, 0.25)
    _, labels = connected_components(A)
    x = rng.normal(size=(50, 3)) * 100.0
    target = component_reduce(x, labels, "sum")
    scale = component_reduce(np.abs(x), labels, "sum")
    cur = x
    for _ in range(200):
        cur = average_consensus(cur, A, 1)
        np.testing.assert_array_less(np.abs(component_reduce(cur, labels, "sum") - target), 1e-12 * scale)
    # the same after many rounds in one call
    out = average_consensus(x, A, 1000)
    np.testing.assert_array_less(np.abs(component_reduce(out, labels, "sum") - target), 1e-12 * scale)


def test_isolated_vehicle_keeps_value_and_two_components():
    # path 0-1-2, edge 3-4, isolated 5
    edges = [(0, 1), (1, 2), (3, 4)]
    A = sp.lil_matrix((6, 6), dtype=bool)
    for i, j in edges:
        A[i, j] = A[j, i] = True
    A = A.tocsr()
    x = np.array([3.0, 6.0, 9.0, -1.0, 5.0, 42.0])
    out = average_consensus(x, A, 500)
    np.testing.assert_allclose(out, [6, 6, 6, 2, 2, 42], atol=1e-12)
    assert out[5] == 42.0
    n, labels = connected_components(A)
    assert n == 3 and len(set(labels[:3])) == 1 and labels[3] == labels[4] != labels[0]


def test_participants_mask():
    """Non-participants neither send nor receive; a non-participant can split a component."""
    # path 0-1-2-3-4; vehicle 2 does not participate -> components {0,1}, {3,4}
    n = 5
    A = sp.diags([np.ones(n - 1), np.ones(n - 1)], [-1, 1], format="csr").astype(bool)
    x = np.array([1.0, 3.0, 100.0, 10.0, 20.0])
    part = np.array([True, True, False, True, True])
    out = average_consensus(x, A, 500, participants=part)
    np.testing.assert_allclose(out, [2, 2, 100, 15, 15], atol=1e-12)
    assert out[2] == 100.0
    mx = max_consensus(x, A, 10, participants=part)
    np.testing.assert_array_equal(mx, [3, 3, 100, 20, 20])
    ncomp, labels = connected_components(A, participants=part)
    assert ncomp == 2 and labels[2] == -1 and labels[0] == labels[1] != labels[3] == labels[4]
    # all-False mask: nothing moves
    none = np.zeros(n, dtype=bool)
    np.testing.assert_array_equal(average_consensus(x, A, 50, participants=none), x)
    assert connected_components(A, participants=none)[0] == 0


def test_random_participants_match_induced_subgraph():
    rng = np.random.default_rng(3)
    A = random_geometric_graph(rng, 40, 0.3)
    part = rng.random(40) < 0.7
    x = rng.normal(size=(40, 2))
    out = average_consensus(x, A, 3000, participants=part)
    ncomp, labels = connected_components(A, participants=part)
    np.testing.assert_array_equal(out[~part], x[~part])
    np.testing.assert_allclose(out[part], component_reduce(x[part], labels[part], "mean"), atol=1e-9)
    sub = A[part][:, part]
    np.testing.assert_allclose(out[part], average_consensus(x[part], sub, 3000), atol=1e-13)


def test_trailing_dimensions():
    rng = np.random.default_rng(4)
    A = random_geometric_graph(rng, 30, 0.35)
    _, labels = connected_components(A)
    for shape in [(30, 4), (30, 4, 4)]:
        x = rng.normal(size=shape)
        out = average_consensus(x, A, 2000)
        assert out.shape == shape
        np.testing.assert_allclose(out, component_reduce(x, labels, "mean"), atol=1e-9)
        # equals the per-column scalar consensus
        flat = x.reshape(30, -1)
        cols = np.stack([average_consensus(flat[:, c], A, 37) for c in range(flat.shape[1])], axis=1)
        np.testing.assert_allclose(average_consensus(x, A, 37).reshape(30, -1), cols, atol=1e-14)
        mx = max_consensus(x, A, 30)
        assert mx.shape == shape
        np.testing.assert_array_equal(mx, component_reduce(x, labels, "max"))


def test_zero_iterations_and_empty():
    A = sp.csr_matrix((0, 0), dtype=bool)
    assert average_consensus(np.zeros((0, 3)), A, 10).shape == (0, 3)
    assert max_consensus(np.zeros(0), A, 10).shape == (0,)
    assert connected_components(A)[0] == 0
    A = sp.csr_matrix(np.array([[0, 1], [1, 0]], dtype=bool))
    x = np.array([1.0, 2.0])
    np.testing.assert_array_equal(average_consensus(x, A, 0), x)
    np.testing.assert_array_equal(max_consensus(x, A, 0), x)
    np.testing.assert_allclose(average_consensus(x, A, 1), [1.5, 1.5])  # W = [[.5,.5],[.5,.5]]


def test_input_not_modified():
    rng = np.random.default_rng(6)
    A = random_geometric_graph(rng, 10, 0.5)
    x = rng.normal(size=10)
    x0 = x.copy()
    average_consensus(x, A, 10)
    max_consensus(x, A, 10)
    np.testing.assert_array_equal(x, x0)


# ---------------------------------------------------------------- max consensus


@settings(max_examples=100, deadline=None)
@given(graphs(max_n=30))
def test_max_consensus_after_diameter(g):
    """Component max everywhere after diameter rounds; with diameter - 1 rounds not everywhere."""
    A, seed = g
    n = A.shape[0]
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n)
    ncomp, labels = connected_components(A)
    dist = shortest_path(A, unweighted=True, directed=False)
    diam = int(np.max(np.where(np.isfinite(dist), dist, 0)))
    target = component_reduce(x, labels, "max")
    np.testing.assert_array_equal(max_consensus(x, A, diam), target)
    np.testing.assert_array_equal(max_consensus(x, A, diam + 5), target)
    if diam >= 1:
        # put the max at one end of a longest shortest path: the other end cannot know it earlier
        i, j = np.unravel_index(np.argmax(np.where(np.isfinite(dist), dist, -1)), dist.shape)
        y = x.copy()
        y[i] = x.max() + 1.0
        out = max_consensus(y, A, diam - 1)
        assert out[j] < y[i]
        assert not np.array_equal(out, component_reduce(y, labels, "max"))


def test_average_then_max_gives_identical_values():
    """Eqs. (28)-(29) pipeline: average consensus on log-weights, then max consensus -> identical."""
    rng = np.random.default_rng(8)
    A = random_geometric_graph(rng, 30, 0.4)
    ncomp, labels = connected_components(A)
    logw = rng.normal(size=(30, 100))  # J_f = 100 particles
    avg = average_consensus(logw, A, 20)  # few rounds: not yet agreed
    assert not np.allclose(avg, component_reduce(avg, labels, "mean"), atol=1e-12)
    dist = shortest_path(A, unweighted=True, directed=False)
    diam = int(np.max(np.where(np.isfinite(dist), dist, 0)))
    out = max_consensus(avg, A, diam)
    for c in range(ncomp):
        sel = out[labels == c]
        assert np.all(sel == sel[0])
