"""Measurement synthesis: detection range, shuffling, V2V graph and noise statistics."""

import numpy as np
import pytest
from scipy import stats
from scipy.spatial import cKDTree

from couplers.sensing.sensors import SensorNoise, SensorParams, features_in_range, neighbor_graph, synthesize_frame


def scene(seed=0, n=60, k=40, extent=600.0):
    rng = np.random.default_rng(seed)
    x = np.hstack([rng.uniform(0, extent, (n, 2)), rng.normal(0, 8, (n, 2))])
    feats = np.hstack([rng.uniform(0, extent, (k, 2)), np.zeros((k, 2))])
    return x, feats


def frame_for(x, feats, seed=1, params=SensorParams(), sp=5.0, sv=0.2, entered=None):
    n = x.shape[0]
    return synthesize_frame(
        t=1.0, dt=0.75, vehicle_ids=np.array([f"v{i}" for i in range(n)], dtype=object),
        entered=np.ones(n, bool) if entered is None else entered,
        x_true=x, accel_true=np.zeros((n, 2)), heading=np.arctan2(x[:, 3], x[:, 2]),
        gnss_sigma_p=np.full(n, sp), gnss_sigma_v=np.full(n, sv), features_true=feats,
        feature_tree=cKDTree(feats[:, :2]), params=params, noise=SensorNoise(seed),
        zone=np.array(["A"] * n), area=np.array(["1"] * n),
    )


def test_v2f_detections_are_exactly_the_features_in_range():
    x, feats = scene()
    params = SensorParams(v2f_range_m=50.0)
    fr = frame_for(x, feats, params=params)
    d = np.linalg.norm(x[:, None, :2] - feats[None, :, :2], axis=2)
    expected = {(i, j) for i, j in zip(*np.nonzero(d <= 50.0))}
    got = set(zip(fr.v2f_owner.tolist(), fr.truth.v2f_feature.tolist()))
    assert got == expected
    assert len(got) == fr.v2f_owner.size  # no duplicates
    # Rows are grouped by owner (owners non-decreasing).
    assert np.all(np.diff(fr.v2f_owner) >= 0)


def test_v2f_rows_are_shuffled_within_each_vehicle():
    x, feats = scene(n=30, k=200, extent=300)
    orders, pair_sets = [], []
    for seed in range(5):
        fr = frame_for(x, feats, seed=seed)
        orders.append(fr.truth.v2f_feature.copy())
        pair_sets.append(sorted(zip(fr.v2f_owner.tolist(), fr.truth.v2f_feature.tolist())))
    # Same detections whatever the seed; only their order changes.
    assert all(p == pair_sets[0] for p in pair_sets)
    # Within a vehicle the true feature indices are not sorted (the association is hidden).
    fr = frame_for(x, feats, seed=0)
    sorted_groups = 0
    groups = 0
    for v in np.unique(fr.v2f_owner):
        f = fr.truth.v2f_feature[fr.v2f_owner == v]
        if f.size >= 5:
            groups += 1
            sorted_groups += bool(np.all(np.diff(f) > 0))
    assert groups >= 10 and sorted_groups == 0
    assert not all(np.array_equal(orders[0], o) for o in orders[1:])


def test_v2f_measurement_is_relative_feature_state():
    x, feats = scene(n=10, k=30, extent=100)
    params = SensorParams(v2f_sigma_p=1e-9, v2f_sigma_v=1e-9)
    fr = frame_for(x, feats, params=params)
    np.testing.assert_allclose(fr.v2f_z, feats[fr.truth.v2f_feature] - x[fr.v2f_owner], atol=1e-6)


def test_neighbor_graph_matches_all_pairs():
    rng = np.random.default_rng(4)
    xy = rng.uniform(0, 1000, (150, 2))
    adj = neighbor_graph(xy, 250.0).toarray()
    d = np.linalg.norm(xy[:, None] - xy[None], axis=2)
    expected = (d <= 250.0) & ~np.eye(150, dtype=bool)
    np.testing.assert_array_equal(adj, expected)
    assert neighbor_graph(xy[:1], 250.0).shape == (1, 1)
    assert neighbor_graph(xy[:0], 250.0).shape == (0, 0)


@pytest.mark.parametrize("field", ["gnss", "v2f", "prior"])
def test_noise_is_gaussian_with_the_stated_covariance(field):
    """Chi-square test: sum of squared normalised residuals ~ chi2(dof); two-sided 0.1 % level."""
    x, feats = scene(n=400, k=300, extent=800)
    fr = frame_for(x, feats, seed=2024, sp=7.0, sv=0.3)
    if field == "gnss":
        resid, cov = fr.gnss_z - x, fr.gnss_R
    elif field == "v2f":
        resid, cov = fr.v2f_z - (feats[fr.truth.v2f_feature] - x[fr.v2f_owner]), fr.v2f_R
    else:
        resid, cov = fr.prior_z - x, fr.prior_R
    q = np.einsum("ni,nij,nj->n", resid, np.linalg.inv(cov), resid)
    dof = 4 * q.size
    assert q.size > 300
    lo, hi = stats.chi2.ppf([0.0005, 0.9995], dof)
    assert lo < q.sum() < hi
    # Per-component variances too (each about 1 after normalisation, 5-sigma band).
    z = resid / np.sqrt(np.diagonal(cov, axis1=1, axis2=2))
    np.testing.assert_allclose(z.var(axis=0), 1.0, atol=5 * np.sqrt(2 / q.size))


def test_prior_only_for_entering_vehicles_and_noise_streams_independent():
    x, feats = scene(n=20)
    entered = np.zeros(20, bool)
    entered[[2, 5]] = True
    fr = frame_for(x, feats, entered=entered)
    assert np.isfinite(fr.prior_z[entered]).all() and np.isnan(fr.prior_z[~entered]).all()
    # Changing which vehicles enter does not shift the GNSS noise draws.
    fr2 = frame_for(x, feats, entered=np.ones(20, bool))
    np.testing.assert_array_equal(fr.gnss_z, fr2.gnss_z)


def _lattice_scene(rng, n=120, k=80, radius=50.0):
    """Points on an integer lattice with 3-4-5 offsets (distances exactly ``radius``), duplicates
    (distance 0) and random points."""
    base = rng.integers(0, 40, (n, 2)).astype(float) * 10.0
    feats = np.vstack([base[: k // 2] + np.array([30.0, 40.0]) * rng.choice([-1, 1], (k // 2, 2)),
                       base[k // 2: k - k // 4], rng.uniform(0, 400, (k // 4, 2))])
    veh = np.vstack([base, rng.uniform(0, 400, (n // 4, 2)), base[:5]])  # base[:5] twice: coincident vehicles
    return veh, feats


def test_neighbor_graph_matches_dense_reference_at_the_radius():
    """Sorted CSR rows, exactly as a dense distance test; pairs at exactly the radius and coincident points."""
    rng = np.random.default_rng(5)
    for radius in (50.0, 250.0):
        xy, _ = _lattice_scene(rng, radius=radius)
        adj = neighbor_graph(xy, radius)
        d2 = ((xy[:, None] - xy[None]) ** 2).sum(axis=2)
        expected = (d2 <= radius * radius) & ~np.eye(len(xy), dtype=bool)
        np.testing.assert_array_equal(adj.toarray(), expected)
        assert adj.has_sorted_indices and adj.dtype == bool
        for i in range(len(xy)):  # rows strictly increasing (sorted, no duplicates)
            assert np.all(np.diff(adj.indices[adj.indptr[i]:adj.indptr[i + 1]]) > 0)
        assert np.any(np.isclose(d2[expected], radius * radius))  # the boundary is exercised


def test_features_in_range_equals_the_kd_tree_pairs():
    """The numba pair search against cKDTree.sparse_distance_matrix (the previous implementation)."""
    rng = np.random.default_rng(6)
    for radius in (50.0, 80.0, 0.5):
        veh, feats = _lattice_scene(rng, radius=radius)
        tree = cKDTree(feats)
        pairs = cKDTree(veh).sparse_distance_matrix(tree, radius, output_type="ndarray")
        order = np.lexsort((pairs["j"], pairs["i"]))
        owner, feat = features_in_range(veh, tree, radius)
        np.testing.assert_array_equal(owner, pairs["i"][order].astype(np.int64))
        np.testing.assert_array_equal(feat, pairs["j"][order].astype(np.int64))
    assert [a.size for a in features_in_range(veh[:0], tree, 50.0)] == [0, 0]
    assert [a.size for a in features_in_range(veh, None, 50.0)] == [0, 0]


def test_neighbor_graph_is_the_matrix_scipys_constructor_builds():
    from couplers.sensing.sensors import _CSR_MAXPRINT, _csr_checked, _radius_graph_csr

    assert _CSR_MAXPRINT is not None  # the fast path is on with this scipy
    rng = np.random.default_rng(3)
    for n in (2, 3, 40, 200):
        xy = rng.uniform(0, 800, (n, 2))
        got = neighbor_graph(xy, 250.0)
        indptr, indices = _radius_graph_csr(xy, 250.0)
        want = _csr_checked(np.ones(indices.size, dtype=bool), indices, indptr, (n, n))
        assert type(got) is type(want) and set(vars(got)) == set(vars(want))
        for key, val in vars(want).items():
            if isinstance(val, np.ndarray):
                assert getattr(got, key).dtype == val.dtype
                np.testing.assert_array_equal(getattr(got, key), val)
            else:
                assert getattr(got, key) == val, key
        assert got.has_sorted_indices and got.has_canonical_format
        np.testing.assert_array_equal(got.toarray(), want.toarray())
        got.check_format(full_check=True)
