"""Infrastructure mode on the coupler side: RSU links, radar detections, odometry (couplers.sensing.infra)."""

import numpy as np
import pytest

from couplers.errors import InputError
from couplers.sensing.infra import InfraSetup, InfraSynth, junction_positions
from couplers.net.folder import load_net_folder
from couplers.sensing.sensors import SensorParams
from couplers.sumo_coupler import SumoCoupler, SumoScenario

SETUP = InfraSetup(rsu_ids=("A", "B"), rsu_xy=np.array([[0.0, 0.0], [100.0, 0.0]]), range_m=60.0,
                   radar_sigma_m=0.3, pose_offset_sigma_m=4.0, odom_sigma_m=0.05)


def _steps(seed, n_steps=5):
    rng = np.random.default_rng(0)
    ids = np.array([f"v{i}" for i in range(30)], dtype=object)
    xy = rng.uniform(-80, 180, (30, 2)) * [1, 0.3]
    synth = InfraSynth(SETUP, seed)
    out = []
    for k in range(n_steps):
        entered = np.zeros(30, bool) if k else np.ones(30, bool)
        out.append((xy.copy(), *synth.step(ids, entered, xy)))
        xy = xy + [8.0, 0.5]
    return synth, out


def test_detections_are_rotated_translated_truth_and_v2i_is_the_range():
    synth, steps = _steps(seed=4)
    for xy, infra, veh in steps:
        d = np.hypot(*(xy[None] - SETUP.rsu_xy[:, None]).transpose(2, 0, 1))
        np.testing.assert_array_equal(infra.v2i.toarray(), d <= SETUP.range_m)
        assert infra.radar_z.shape[0] == int((d <= SETUP.range_m).sum())
        # Detections of RSU r are exactly its V2I vehicles (P_D = 1), grouped by RSU.
        for r in range(2):
            rows = infra.radar_owner == r
            assert sorted(veh[rows]) == sorted(np.flatnonzero(d[r] <= SETUP.range_m))
        assert np.all(np.diff(infra.radar_owner) >= 0)
        # Undo the radar pose: residuals are the radar noise.
        th = synth.radar_theta[infra.radar_owner]
        c, s = np.cos(th), np.sin(th)
        back = np.stack([c * infra.radar_z[:, 0] - s * infra.radar_z[:, 1],
                         s * infra.radar_z[:, 0] + c * infra.radar_z[:, 1]], axis=1) + synth.radar_xy[infra.radar_owner]
        res = back - xy[veh]
        assert np.abs(res).max() < 5 * SETUP.radar_sigma_m
        assert infra.radar_var == pytest.approx(SETUP.radar_sigma_m**2)
    # The pose is not the RSU's: offset and rotation were drawn.
    assert np.all(np.hypot(*(synth.radar_xy - SETUP.rsu_xy).T) > 0.0)
    # Odometry: NaN when entered, then true displacement + small noise.
    assert np.isnan(steps[0][1].odom).all()
    odom = steps[1][1].odom
    assert np.abs(odom - [8.0, 0.5]).max() < 5 * SETUP.odom_sigma_m


def test_same_seed_identical_other_seed_different():
    _, a = _steps(seed=7)
    _, b = _steps(seed=7)
    _, c = _steps(seed=8)
    for (_, fa, va), (_, fb, vb) in zip(a, b):
        assert fa.radar_z.tobytes() == fb.radar_z.tobytes() and np.array_equal(va, vb)
        assert np.array_equal(fa.odom, fb.odom, equal_nan=True)
    assert a[1][1].radar_z.tobytes() != c[1][1].radar_z.tobytes()


def test_unknown_junction_names_the_field(cross_net, tmp_path):
    net = load_net_folder(cross_net)
    np.testing.assert_allclose(junction_positions(net.net, ("C",), tmp_path / "x.toml", "infra.rsu_junctions"), [[0, 0]])
    with pytest.raises(InputError, match=r"infra\.rsu_junctions\[1\].*nowhere"):
        junction_positions(net.net, ("C", "nowhere"), tmp_path / "x.toml", "infra.rsu_junctions")


def _frames(net, infra, duration=45.0):
    sc = SumoScenario(net=net, control="tlr", seed=2, duration_s=duration)
    with SumoCoupler(sc, SensorParams(), infra) as c:
        return list(c.frames())


def test_infra_leaves_the_vehicle_measurements_unchanged(cross_net):
    """The infrastructure stream is separate: gnss / V2F / prior / accel are the same bytes with and without it."""
    net = load_net_folder(cross_net)
    setup = InfraSetup(rsu_ids=("C",), rsu_xy=np.array([[0.0, 0.0]]), range_m=80.0)
    plain = _frames(net, None)
    infra = _frames(net, setup)
    assert len(plain) == len(infra) > 50
    seen = 0
    for a, b in zip(plain, infra):
        assert a.infra is None and b.infra is not None and a.truth.radar_vehicle is None
        for name in ("gnss_z", "v2f_z", "accel", "prior_z", "v2f_owner"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes(), name
        seen += b.infra.radar_z.shape[0]
        np.testing.assert_array_equal(b.truth.radar_vehicle.shape, (b.infra.radar_z.shape[0],))
    assert seen > 100
