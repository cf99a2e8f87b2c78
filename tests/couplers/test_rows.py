"""couplers.rows.id_rows against its reference, coloc.core.vehicles.match_ids."""

import numpy as np

from coloc.core.vehicles import match_ids
from couplers.rows import id_rows


def test_id_rows_equals_match_ids():
    rng = np.random.default_rng(3)
    pool = np.array([f"veh{i}" for i in range(60)] + ["flow.1", "flow.10", "", "ped 2"], dtype=object)
    for _ in range(300):
        prev = rng.choice(pool, rng.integers(0, 40), replace=bool(rng.random() < 0.3))  # some with duplicates
        cur = rng.choice(pool, rng.integers(0, 40), replace=False)
        for p, c in ((prev, cur), (prev.astype(str), cur.astype(str)), (prev, cur.astype(str))):
            got = id_rows(p, c)
            np.testing.assert_array_equal(got, match_ids(p, c))
            assert got.dtype == np.int64 and got.shape == (len(c),)
