"""coloc.core.vehicles.match_ids (through a dict) against the sort-and-search it replaced."""

import numpy as np

from coloc.core.vehicles import match_ids


def _sorted_search(previous_ids, current_ids):
    """The reference: a stable argsort of the previous ids and a binary search (first row of a duplicate)."""
    current, previous = np.asarray(current_ids), np.asarray(previous_ids)
    if previous.size == 0 or current.size == 0:
        return np.full(current.shape[0], -1, dtype=np.int64)
    order = np.argsort(previous, kind="stable")
    sorted_prev = previous[order]
    pos = np.minimum(np.searchsorted(sorted_prev, current), sorted_prev.size - 1)
    return np.where(sorted_prev[pos] == current, order[pos], -1).astype(np.int64)


def test_match_ids_equals_the_sorted_search():
    rng = np.random.default_rng(3)
    pool = np.array([f"veh{i}" for i in range(60)] + ["flow.1", "flow.10", "", "ped 2"], dtype=object)
    for _ in range(300):
        prev = rng.choice(pool, rng.integers(0, 40), replace=bool(rng.random() < 0.3))  # some with duplicates
        cur = rng.choice(pool, rng.integers(0, 40), replace=False)
        for p, c in ((prev, cur), (prev.astype(str), cur.astype(str)), (prev, cur.astype(str))):
            got = match_ids(p, c)
            np.testing.assert_array_equal(got, _sorted_search(p, c))
            assert got.dtype == np.int64 and got.shape == (len(c),)
