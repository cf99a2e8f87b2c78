"""The numba passes of the realistic frames against their numpy references, bit for bit on seeded scenes:
the noise-free relative states of the sensor-frame rows and the merge of the perception's rows with the other
road users' (couplers.sensing.sensor_frame, couplers.sensing.road_users)."""

import numpy as np
import pytest

from couplers.sensing.perception import Detections
from couplers.sensing.road_users import KIND_PEDESTRIAN, KIND_VEHICLE, RoadUserNoise, merged_rows, merged_rows_reference
from couplers.sensing.sensor_frame import relative_states, relative_states_reference


def _det(rng, o, n, k, with_kind=True):
    feature = np.where(rng.random(o) < 0.5, rng.integers(0, k, o), -1)
    kind = rng.integers(0, 5, o).astype(np.int8) if with_kind else None
    return Detections(z=rng.normal(0, 30, (o, 4)), owner=np.sort(rng.integers(0, n, o)),
                      R=rng.normal(0, 1, (o, 4, 4)), feature=feature, sensor=rng.integers(0, 3, o),
                      klass=rng.integers(0, 3, o).astype(np.int8), kind=kind)


@pytest.mark.parametrize("with_kind", [True, False])
def test_relative_states_equal_the_numpy_reference(with_kind):
    rng = np.random.default_rng(21)
    for o in (0, 1, 57, 400):
        n, k = 12, 30
        det = _det(rng, o, n, k, with_kind)
        x_true, feats = rng.normal(0, 100, (n, 4)), rng.normal(0, 100, (k, 4))
        new, ref = relative_states(det, x_true, feats), relative_states_reference(det, x_true, feats)
        assert new.shape == ref.shape == (o, 4)
        assert new.tobytes() == ref.tobytes()
    if with_kind:  # the moving road users keep their row's velocity, the rest the vehicle's negated one
        moving = (det.feature < 0) & np.isin(det.kind, (KIND_VEHICLE, KIND_PEDESTRIAN))
        assert moving.any() and np.array_equal(new[moving, 2:], det.z[moving, 2:])


@pytest.mark.parametrize("class_error", [0.0, 0.2])
def test_merged_rows_equal_the_numpy_reference(class_error):
    """Same rows, order, covariances, dtypes and random streams as the numpy merge, with none, one and two extra
    blocks of rows."""
    rng = np.random.default_rng(5)
    for o, sizes in ((0, []), (40, []), (40, [25]), (0, [7]), (60, [10, 15])):
        n = 9
        det = _det(rng, o, n, 30)
        extra = [(rng.integers(0, n, m), rng.normal(0, 20, (m, 4)), rng.uniform(0.1, 2, m), rng.uniform(0.1, 1, m),
                  rng.integers(0, 3, m), rng.integers(0, 3, m).astype(np.int8), rng.integers(1, 5, m).astype(np.int8))
                 for m in sizes]
        new = merged_rows(det, extra, RoadUserNoise(3), class_error)
        ref = merged_rows_reference(det, extra, RoadUserNoise(3), class_error)
        for name in ("z", "owner", "R", "feature", "sensor", "klass", "kind"):
            a, b = getattr(new, name), getattr(ref, name)
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), name
        if sizes:
            assert (new.feature == -1).sum() >= sum(sizes)


def test_satellite_receiver_kernels_equal_the_numpy_expressions():
    """The receivers' multipath update and pseudorange sum (couplers.sensing.gnss_satellites) against the numpy
    expressions they replace, bit for bit."""
    from couplers.sensing.gnss_satellites import _carried_multipath, _pseudorange_sum

    rng = np.random.default_rng(8)
    n, s = 40, 48
    z, u_prev, white = rng.standard_normal((n, s)), rng.standard_normal((n + 5, s)), rng.standard_normal((n, s))
    carried = rng.random(n) < 0.7
    prev = rng.permutation(n + 5)[:n][carried]
    a = np.exp(-rng.uniform(0, 30, carried.sum()) / 5.0)
    ref = z.copy()
    ref[carried] = a[:, None] * u_prev[prev] + np.sqrt(1.0 - a[:, None] * a[:, None]) * z[carried]
    u = _carried_multipath(np.flatnonzero(carried), prev, a, u_prev, z)
    assert u.tobytes() == ref.tobytes()
    common, sig_n, mp = rng.normal(0, 3, s), rng.uniform(0.2, 2, s), rng.uniform(0.3, 6, s)
    ref_eps = common[None, :] + sig_n[None, :] * white + mp[None, :] * u
    assert _pseudorange_sum(common, sig_n, white, mp, u).tobytes() == ref_eps.tobytes()
