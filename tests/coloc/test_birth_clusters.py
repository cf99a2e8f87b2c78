"""ICP-DA-LC's birth clustering over exactly pruned candidate pairs: the labels of the per-row loop."""

import numpy as np
import pytest

from coloc.methods.icp_da_lc import birth_pairs
from coloc.methods.icp_da_lc import birth_clusters


def reference_birth_clusters(owner, implied_xy, implied_cov, gate_d2):
    """The per-row loop birth_clusters was (every row solved against every seed so far)."""
    b = owner.size
    labels = np.full(b, -1, dtype=np.int64)
    seeds: list[int] = []
    members: list[set] = []
    for i in range(b):
        if seeds:
            sd = np.asarray(seeds)
            d = implied_xy[sd] - implied_xy[i]
            s = implied_cov[sd] + implied_cov[i]
            d2 = np.einsum("ni,ni->n", d, np.linalg.solve(s, d[..., None])[..., 0])
            for c in np.argsort(d2, kind="stable"):
                if d2[c] > gate_d2:
                    break
                if owner[i] not in members[c]:
                    labels[i] = c
                    members[c].add(owner[i])
                    break
        if labels[i] < 0:
            labels[i] = len(seeds)
            seeds.append(i)
            members.append({owner[i]})
    return labels


def _spd(rng, n, scale):
    a = rng.normal(size=(n, 2, 2)) * scale[:, None, None]
    return a @ a.transpose(0, 2, 1) + np.eye(2) * (1e-3 * scale[:, None, None] ** 2)


def _scene(rng, b, n_vehicles, spread):
    """Rows around a few feature positions, duplicated rows (ties), anisotropic covariances of mixed scale."""
    centres = rng.uniform(0, spread, size=(max(1, b // 4), 2))
    jitter = rng.normal(size=(b, 2)) * rng.choice([0.05, 0.5, 3.0], b)[:, None]
    xy = centres[rng.integers(0, centres.shape[0], b)] + jitter
    cov = _spd(rng, b, rng.choice([0.1, 0.7, 2.0], b))
    dup = rng.random(b) < 0.15  # exact copies of an earlier row: equal d2 to several seeds
    for i in np.flatnonzero(dup):
        if i:
            k = rng.integers(0, i)
            xy[i], cov[i] = xy[k], cov[k]
    return rng.integers(0, n_vehicles, b), xy, cov


@pytest.mark.parametrize("seed", range(12))
def test_labels_equal_the_per_row_loop(seed):
    rng = np.random.default_rng(seed)
    for b in (0, 1, 2, 7, 60, 250):
        for n_vehicles in (1, 3, 40):
            owner, xy, cov = _scene(rng, b, n_vehicles, spread=rng.choice([5.0, 60.0, 2000.0]))
            for gate in (0.5, 5.99, 9.21, 60.0):
                want = reference_birth_clusters(owner, xy, cov, gate)
                got = birth_clusters(owner, xy, cov, gate)
                assert got.dtype == np.int64
                np.testing.assert_array_equal(got, want, err_msg=f"b={b} vehicles={n_vehicles} gate={gate}")


def test_ties_go_to_the_earlier_seed_and_same_vehicle_is_skipped():
    xy = np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]])
    owner = np.array([0, 0, 1, 1, 2])
    cov = np.repeat(np.eye(2)[None], 5, 0)
    # rows 0 and 1 (vehicle 0) are two seeds at one place; row 2 ties between them: the first;
    # row 3 (vehicle 1 again) goes to the second; row 4 (vehicle 2) to the first again.
    assert birth_clusters(owner, xy, cov, 9.21).tolist() == [0, 1, 0, 1, 0]
    assert reference_birth_clusters(owner, xy, cov, 9.21).tolist() == [0, 1, 0, 1, 0]


def test_non_finite_rows_as_the_loop():
    rng = np.random.default_rng(5)
    owner, xy, cov = _scene(rng, 30, 4, 20.0)
    xy[[3, 17]] = np.nan
    with np.errstate(invalid="ignore"):
        want = reference_birth_clusters(owner, xy, cov, 9.21)
        got = birth_clusters(owner, xy, cov, 9.21)
    np.testing.assert_array_equal(got, want)


def test_pruning_keeps_every_pair_within_the_gate():
    rng = np.random.default_rng(11)
    owner, xy, cov = _scene(rng, 300, 5, 100.0)
    gate = 9.21
    indptr, cand_j, cand_d2 = birth_pairs(xy, cov, gate)
    kept = {(i, int(j)) for i in range(300) for j in cand_j[indptr[i]:indptr[i + 1]]}
    i, j = np.tril_indices(300, -1)
    d = xy[j] - xy[i]
    d2 = np.einsum("ni,ni->n", d, np.linalg.solve(cov[j] + cov[i], d[..., None])[..., 0])
    within = {(int(a), int(c)) for a, c in zip(i[d2 <= gate], j[d2 <= gate])}
    assert within <= kept
    assert len(kept) < i.size // 4  # and it does prune


def test_batched_solve_is_bit_identical_to_smaller_batches():
    """The claim the pruning rests on: numpy's batched solve (LAPACK per matrix) and the einsum give each
    pair's d2 bit for bit as a call over any other batch holding it."""
    rng = np.random.default_rng(2)
    n = 4000
    d = rng.normal(size=(n, 2)) * rng.choice([1e-3, 1.0, 1e3], n)[:, None]
    s = _spd(rng, n, rng.choice([0.01, 1.0, 100.0], n))
    whole = np.einsum("ni,ni->n", d, np.linalg.solve(s, d[..., None])[..., 0])
    cuts = np.sort(rng.choice(np.arange(1, n), 60, replace=False))
    parts = [np.einsum("ni,ni->n", dd, np.linalg.solve(ss, dd[..., None])[..., 0])
             for dd, ss in zip(np.split(d, cuts), np.split(s, cuts))]
    assert np.concatenate(parts).tobytes() == whole.tobytes()
    one = np.array([np.einsum("ni,ni->n", d[k:k + 1], np.linalg.solve(s[k:k + 1], d[k:k + 1, :, None])[..., 0])[0]
                    for k in range(0, n, 7)])
    assert one.tobytes() == whole[::7].tobytes()
