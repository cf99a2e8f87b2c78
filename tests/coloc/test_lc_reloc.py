"""Relocalization of a lost vehicle (coloc/methods/lc_reloc.py, ``[lc] relocalize_radius_m``)."""

from dataclasses import replace

import numpy as np
import pytest

from coloc.inference.params import IcpParams
from coloc.methods.icp_da_lc import IcpDaLc, LcParams
from coloc.methods.lc_reloc import relocalization_offsets
from scenes import road_frames
from tests.coloc.test_icp_known_da import MOTION


def _seen(true_xy, tracks, rng, reach=30.0, noise=0.1):
    """Rows of a vehicle at ``true_xy``: every track within ``reach``, relative, with noise."""
    near = np.flatnonzero(np.hypot(*(tracks - true_xy).T) <= reach)
    return tracks[near] - true_xy + rng.normal(0.0, noise, (near.size, 2))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_shifted_vehicle_is_moved_back_onto_an_irregular_map(seed):
    rng = np.random.default_rng(seed)
    tracks = rng.uniform(-60.0, 60.0, (60, 2))
    true_xy = np.zeros(2)
    z = _seen(true_xy, tracks, rng)
    assert z.shape[0] >= 4
    err = rng.uniform(-7.0, 7.0, 2)
    v_mean = np.array([[*(true_xy + err), 10.0, 0.0], [5.0, 5.0, 0.0, 0.0]])
    owner = np.zeros(z.shape[0], dtype=np.int64)
    off = relocalization_offsets(v_mean, owner, z, np.array([True, True]), tracks, 10.0, 1.5, 3)
    np.testing.assert_allclose(off[0], -err, atol=0.15)
    np.testing.assert_array_equal(off[1], 0.0)  # lost, but no rows
    # not lost, or fewer rows than the support asked for: left alone
    assert not relocalization_offsets(v_mean, owner, z, np.array([False, False]), tracks, 10.0, 1.5, 3).any()
    assert not relocalization_offsets(v_mean, owner, z, np.array([True, False]), tracks, 10.0, 1.5, z.shape[0] + 1).any()
    # a radius below the error: no translation reaches it
    assert not relocalization_offsets(v_mean, owner, z, np.array([True, False]), tracks,
                                      0.5 * float(np.hypot(*err)) - 1.5, 1.5, 3).any()


def test_a_periodic_layout_is_ambiguous_unless_the_radius_excludes_the_alias():
    """Landmarks 12.4 m apart on both sides of a road (the arterial's layout): a translation by one period
    explains the rows as well, so within a radius that holds it nothing is done; within one that does not,
    the vehicle is moved back."""
    rng = np.random.default_rng(4)
    xs = np.arange(-40, 41) * 12.4
    tracks = np.concatenate([np.stack([xs, np.full(xs.size, 9.4)], 1), np.stack([xs, np.full(xs.size, -9.4)], 1)])
    z = _seen(np.zeros(2), tracks, rng)
    v_mean = np.array([[4.0, 0.5, 10.0, 0.0]])
    owner = np.zeros(z.shape[0], dtype=np.int64)
    lost = np.array([True])
    assert not relocalization_offsets(v_mean, owner, z, lost, tracks, 12.0, 1.5, 3).any()  # -4 and +8.4 tie
    np.testing.assert_allclose(relocalization_offsets(v_mean, owner, z, lost, tracks, 6.0, 1.5, 3)[0], [-4.0, -0.5],
                               atol=0.15)


def test_on_when_no_vehicle_is_lost_changes_nothing():
    """Features 30 m apart, every row paired from the third step (test_icp_da_lc): the relocalization finds
    no lost vehicle with a confirmed track around and the estimates are byte for byte those without it."""
    frames = road_frames(seed=1, steps=12, v2v_range=25.0)
    params = IcpParams(motion=MOTION)
    off, on = IcpDaLc(params, LcParams(sensing_range_m=30.0)), IcpDaLc(
        params, LcParams(sensing_range_m=30.0, relocalize_radius_m=10.0))
    for f in frames:
        a, b = off.step(f.without_truth()), on.step(f.without_truth())
        assert a.mean.tobytes() == b.mean.tobytes() and a.cov.tobytes() == b.cov.tobytes()
        np.testing.assert_array_equal(a.v2f_assignment, b.v2f_assignment)


def test_a_lost_vehicle_pairs_its_rows_again():
    """A vehicle whose belief is moved 6 m off after the map is built pairs none of its rows without the
    relocalization (all outside its gate), and pairs them with the tracks the others use with it."""
    frames = road_frames(seed=2, steps=10, v2v_range=25.0)
    params = IcpParams(motion=MOTION)
    lc = LcParams(sensing_range_m=30.0, gate_probability=0.99, relocalize_min_support=2)  # two features in view
    results = {}
    for radius in (0.0, 10.0):
        est = IcpDaLc(params, LcParams(**{**lc.__dict__, "relocalize_radius_m": radius}))
        for f in frames[:-1]:
            est.step(f.without_truth())
        st = est.state
        moved = st.mean.copy()
        moved[0, :2] += [6.0, -3.0]
        cov = st.cov.copy()
        cov[0, :2, :2] = 0.04 * np.eye(2)  # a confident belief, off the map
        own = st.own_mean.copy()
        own[0, :2] += [6.0, -3.0]
        own_cov = st.own_cov.copy()
        own_cov[0, :2, :2] = 0.04 * np.eye(2)
        est.state = type(st)(**{**st.__dict__, "mean": moved, "cov": cov, "own_mean": own, "own_cov": own_cov})
        last = frames[-1]
        results[radius] = (est.step(last.without_truth()), last, st.ids[0])
    e0, last, vid = results[0.0]
    e1 = results[10.0][0]
    rows0 = np.asarray(last.v2f_owner) == list(last.vehicle_ids).index(vid)
    assert rows0.sum() >= 2
    fe = last.truth.v2f_feature

    def on_the_others_tracks(e):
        others = ~rows0 & (e.v2f_assignment >= 0)
        track_of = dict(zip(fe[others].tolist(), e.v2f_assignment[others].tolist()))
        mine = [(f, t) for f, t in zip(fe[rows0].tolist(), e.v2f_assignment[rows0].tolist()) if f in track_of]
        assert mine
        return [track_of[f] == t for f, t in mine]

    # without: off the map, every row outside its gate starts a new track; with: on the others' tracks
    assert not any(on_the_others_tracks(e0))
    assert all(on_the_others_tracks(e1))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_vehicle_partly_on_the_map_is_moved_when_the_vote_gains_enough_rows(seed):
    """``relocalize_min_gain``: a vehicle whose mean is off by a few metres, with one row that happens to land
    on a track (the zero translation's support 1 or so), is moved back when the vote gains at least g rows, left
    alone when g is more than the vote can gain, or when it is not asked (g = 0, ``partial`` None); a vehicle on
    the map gains nothing and stays."""
    rng = np.random.default_rng(seed)
    tracks = rng.uniform(-60.0, 60.0, (60, 2))
    z = _seen(np.zeros(2), tracks, rng)
    err = rng.uniform(3.0, 7.0, 2) * rng.choice([-1.0, 1.0], 2)
    v_mean = np.array([[*err, 10.0, 0.0]])
    owner = np.zeros(z.shape[0], dtype=np.int64)
    lost, partial = np.array([False]), np.array([True])
    implied = err + z
    sup0 = int((np.min(np.hypot(*(implied[:, None] - tracks[None]).transpose(2, 0, 1)), axis=1) <= 1.5).sum())
    gain = z.shape[0] - sup0
    assert gain >= 2
    off = relocalization_offsets(v_mean, owner, z, lost, tracks, 10.0, 1.5, 3, partial, gain)
    np.testing.assert_allclose(off[0], -err, atol=0.15)
    assert not relocalization_offsets(v_mean, owner, z, lost, tracks, 10.0, 1.5, 3, partial, gain + 1).any()
    assert not relocalization_offsets(v_mean, owner, z, lost, tracks, 10.0, 1.5, 3, partial, 0).any()
    assert not relocalization_offsets(v_mean, owner, z, lost, tracks, 10.0, 1.5, 3).any()
    on_map = np.array([[0.05, -0.05, 10.0, 0.0]])
    assert not relocalization_offsets(on_map, owner, z, lost, tracks, 10.0, 1.5, 3, partial, 1).any()


def test_min_gain_keeps_the_lost_vehicles_rule():
    """A lost vehicle's translation does not depend on ``relocalize_min_gain``."""
    rng = np.random.default_rng(7)
    tracks = rng.uniform(-60.0, 60.0, (60, 2))
    z = _seen(np.zeros(2), tracks, rng)
    v_mean = np.array([[4.0, -3.0, 10.0, 0.0]])
    owner = np.zeros(z.shape[0], dtype=np.int64)
    a = relocalization_offsets(v_mean, owner, z, np.array([True]), tracks, 10.0, 1.5, 3)
    b = relocalization_offsets(v_mean, owner, z, np.array([True]), tracks, 10.0, 1.5, 3, np.array([False]), 50)
    np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(a[0], [-4.0, 3.0], atol=0.15)


def test_min_gain_must_not_be_negative():
    with pytest.raises(ValueError, match="relocalize_min_gain"):
        LcParams(relocalize_min_gain=-1)


@pytest.mark.parametrize("seed", [1, 2])
def test_map_support_counts_distinct_tracks_as_a_brute_force_count(seed):
    """``map_support``: per vehicle, the distinct confirmed tracks within the tolerance of its rows' implied
    positions, against a double loop (two rows on one track count once)."""
    from coloc.methods.lc_reloc import map_support

    rng = np.random.default_rng(seed)
    tracks = rng.uniform(-30.0, 30.0, (40, 2))
    n = 6
    xy = rng.uniform(-10.0, 10.0, (n, 2))
    owner = rng.integers(0, n - 1, 50)  # the last vehicle has no rows
    z = tracks[rng.integers(0, 40, 50)] - xy[owner] + rng.normal(0.0, 1.0, (50, 2))
    got = map_support(xy, owner, z, tracks, 1.5, n)
    want = np.zeros(n, dtype=np.int64)
    for i in range(n):
        hit = set()
        for r in np.flatnonzero(owner == i):
            d = np.hypot(*(tracks - (xy[i] + z[r])).T)
            if d.min() <= 1.5:
                hit.add(int(np.argmin(d)))
        want[i] = len(hit)
    np.testing.assert_array_equal(got, want)
    assert want[-1] == 0 and want.sum() > 0
    assert not map_support(xy, owner, z, np.zeros((0, 2)), 1.5, n).any()


def test_a_kept_vehicle_is_not_reset_to_its_own_track():
    """``reset_map_margin``: the reset's veto only removes vehicles from the gate's decision."""
    from coloc.methods.icp_da_lc import own_consistency_reset

    own_mean = np.zeros((3, 4))
    own_cov = np.repeat(np.diag([4.0, 4.0, 0.1, 0.1])[None], 3, 0)
    mean = np.array([[9.0, 0.0, 0, 0], [9.0, 0.0, 0, 0], [1.0, 0.0, 0, 0]])
    cov = np.repeat(np.eye(4)[None] * 0.01, 3, 0)
    m, c, reset = own_consistency_reset(mean, cov, own_mean, own_cov, 0.9999, np.array([True, False, True]))
    assert reset.tolist() == [False, True, False]
    np.testing.assert_array_equal(m[0], mean[0])
    np.testing.assert_array_equal(m[1], own_mean[1])
    with pytest.raises(ValueError, match="reset_map_margin"):
        LcParams(reset_map_margin=-1)


def test_the_map_keeps_a_vehicle_whose_receiver_goes_off():
    """A vehicle's receiver jumps 15 m off the road for the last steps of a run whose landmarks are mapped. With
    the reset alone it takes its own track and follows the receiver; with ``reset_map_margin`` its rows, which
    still land on the mapped landmarks, keep it near its true position while they do."""
    frames = road_frames(seed=3, n=5, steps=22, n_feat=10, v2f_range=45.0, gnss_sp=1.0)
    bad = []
    for t, fr in enumerate(frames):
        if t >= 12:
            gz = fr.gnss_z.copy()
            gz[2, 1] += 15.0
            fr = replace(fr, gnss_z=gz)
        bad.append(fr)
    params = IcpParams(motion=MOTION)
    err = {}
    for m in (0, 2):
        lc = LcParams(sensing_range_m=45.0, own_consistency_gate=0.9999, reset_map_margin=m)
        est = IcpDaLc(params, lc)
        e = [est.step(fr.without_truth()).mean[2, :2] - fr.truth.x_true[2, :2] for fr in bad]
        err[m] = np.hypot(*np.array(e[14:]).T)
    assert (err[0][:5] > 6.0).all()  # followed the receiver
    # kept while its rows land on the map (here no fault exclusion: the fixes still pull it, until its rows leave
    # the tolerance and the gate decides again)
    assert (err[2][:5] < 2.5).all()



def test_fix_map_margin_must_not_be_negative():
    with pytest.raises(ValueError, match="fix_map_margin"):
        LcParams(fix_map_margin=-1)


def _anchor_scene():
    """Two vehicles, landmarks every 7 m along y = +-5; vehicle 0 sees four of them, vehicle 1 three."""
    from types import SimpleNamespace

    xs = np.arange(-6, 7) * 7.0
    tracks = np.concatenate([np.stack([xs, np.full(xs.size, 5.0)], 1), np.stack([xs, np.full(xs.size, -5.0)], 1)])
    true_xy = np.array([[0.0, 0.0], [21.0, 0.0]])
    z = np.array([[7.0, 5.0], [-7.0, 5.0], [0.0, -5.0], [7.0, -5.0], [0.0, 5.0], [7.0, 5.0], [0.0, -5.0]])
    owner = np.array([0, 0, 0, 0, 1, 1, 1])
    z = tracks[[np.argmin(np.hypot(*(tracks - true_xy[o] - zz).T)) for o, zz in zip(owner, z)]] - true_xy[owner]
    frame = SimpleNamespace(v2f_class=None, v2f_z=z, n_vehicles=2, dt=0.5, entered=np.array([False, True]))
    predicted = SimpleNamespace(size=tracks.shape[0], klass=None)
    return tracks, true_xy, owner, frame, predicted


def test_the_anchor_is_carried_by_the_velocity_and_taken_where_the_map_supports_it():
    """``anchor_margin``: the anchor moves with b^(0)'s velocity (an entering vehicle starts at b^(0)); a vehicle
    whose fix-updated mean is 4 m off its landmarks is associated at its anchor, one on them keeps its mean; the
    anchor is refreshed to a posterior that the map supports and kept otherwise."""
    from coloc.methods.lc_reloc import anchored_mean, map_rows, predicted_anchor, refreshed_anchor

    tracks, true_xy, owner, frame, predicted = _anchor_scene()
    lc = LcParams(anchor_margin=1)
    b0 = np.array([[0.0, 4.0, 2.0, 0.0], [21.0, 0.0, 0.0, 0.0]])  # vehicle 0 pulled 4 m across
    prev = np.array([[-1.0, 0.0], [99.0, 99.0]])
    anchor = predicted_anchor(prev, np.array([0, 1]), frame, b0)
    np.testing.assert_allclose(anchor, [[0.0, 0.0], [21.0, 0.0]])  # -1 + 0.5 * 2; entering: b^(0)
    assert predicted_anchor(None, np.array([0, 1]), frame, b0) is not None
    t_mean = np.concatenate([tracks, np.zeros_like(tracks)], 1)
    rows = map_rows(predicted, None, t_mean, frame, owner, lc)
    a = anchored_mean(b0, anchor, rows, lc.anchor_margin)
    np.testing.assert_array_equal(a[0, :2], [0.0, 0.0])
    np.testing.assert_array_equal(a[1], b0[1])
    np.testing.assert_array_equal(a[0, 2:], b0[0, 2:])
    far = anchor + [[0.0, 4.0], [0.0, 0.0]]  # an anchor off the map is not taken
    np.testing.assert_array_equal(anchored_mean(b0, far, rows, lc.anchor_margin), b0)
    post = np.array([[0.2, 0.1, 2.0, 0.0], [21.0, 4.0, 0.0, 0.0]])  # vehicle 1's posterior off the map
    np.testing.assert_allclose(refreshed_anchor(far, post, rows),
                               [[0.2, 0.1], far[1]])
    with pytest.raises(ValueError, match="anchor_margin"):
        LcParams(anchor_margin=-1)
