"""Association scoring outside the estimator: track labels over the run, correct / wrong / discarded rows."""

import numpy as np
import pytest

from experiments.scoring import association_summary, score_association, track_labels


def test_hand_made_example():
    # Track 5 is paired with features 0, 1, 0 -> label 0; track 7 with 1, 1, 0 -> label 1;
    # track 9 with 2 and 3 once each -> tie, the smallest feature (2) wins.
    steps = [
        (np.array([5, 5, -1, 7]), np.array([0, 1, 2, 1])),
        (np.array([5, 7, 7, 9]), np.array([0, 1, 0, 2])),
        (np.array([], dtype=int), np.array([], dtype=int)),  # a step without V2F rows
        (np.array([9, -1, -1]), np.array([3, 0, 1])),
    ]
    counts, labels = score_association(steps)
    assert labels == {5: 0, 7: 1, 9: 2}
    assert counts.tolist() == [
        [2, 1, 1],  # (5,0) ok, (5,1) wrong, discarded, (7,1) ok
        [3, 1, 0],  # (5,0) ok, (7,1) ok, (7,0) wrong, (9,2) ok
        [0, 0, 0],
        [0, 1, 2],  # (9,3) wrong, two discarded
    ]
    s = association_summary(*counts.sum(axis=0).tolist())
    assert (s["correct"], s["wrong"], s["discarded"]) == (5, 3, 3)
    assert s["correct_pct"] == pytest.approx(100 * 5 / 11)
    assert s["correct_pct"] + s["wrong_pct"] + s["discarded_pct"] == pytest.approx(100.0)


def test_true_assignment_is_all_correct_and_no_rows_gives_no_percentages():
    rng = np.random.default_rng(3)
    steps = [(f, f) for f in (rng.integers(0, 6, size=n) for n in (0, 4, 9, 2))]
    counts, labels = score_association(steps)
    assert counts[:, 1:].sum() == 0 and counts[:, 0].sum() == 15
    assert all(k == v for k, v in labels.items())
    assert association_summary(0, 0, 0)["correct_pct"] is None


def test_labels_ignore_discarded_rows_and_shapes_must_match():
    assert track_labels(np.array([], dtype=int), np.array([], dtype=int)) == {}
    with pytest.raises(ValueError):
        score_association([(np.array([1, 2]), np.array([1]))])


def test_clutter_rows_kept_on_any_track_are_wrong():
    """Clutter (true index -1): kept on a real feature's track or on a ghost track born from clutter
    (label -1), it is wrong; discarded, it is discarded."""
    steps = [
        (np.array([3, 3, 4, 4, -1]), np.array([0, -1, -1, -1, -1])),  # track 4: clutter only -> label -1
        (np.array([3, 4, 4]), np.array([0, -1, 1])),
    ]
    counts, labels = score_association(steps)
    assert labels == {3: 0, 4: -1}
    assert counts.tolist() == [
        [1, 3, 1],  # (3,0) ok; clutter on track 3, twice on the ghost track 4: wrong; one discarded
        [1, 2, 0],  # (3,0) ok; clutter on 4 wrong; feature 1 on the ghost track wrong
    ]


def test_ghost_tracks_have_no_feature_error(tmp_path):
    """A track labelled -1 (born from clutter) is not scored against any true feature."""
    from types import SimpleNamespace

    from experiments.runner import EstimateLog

    log = EstimateLog()
    truth = SimpleNamespace(v2f_feature=np.array([0, -1, -1]), features_true=np.array([[0.0, 0.0, 0, 0], [50.0, 0, 0, 0]]),
                            zone=np.array(["A"]))
    frame = SimpleNamespace(t=1.0, truth=truth, v2f_owner=np.array([0, 0, 0]))
    est = SimpleNamespace(v2f_assignment=np.array([10, 11, 11]), feature_mean=np.array([[0.5, 0, 0, 0], [49.0, 0, 0, 0]]),
                          feature_track_ids=np.array([10, 11]))
    log.add_association("icp_da_lc", frame, est)
    log.add_features("icp_da_lc", frame, est)
    scores = log.association_scores()
    table = log.feature_table(["icp_da_lc"], scores)
    assert table["track"].tolist() == [10] and table["err_pos"].tolist() == [0.5]


def test_track_labels_equal_the_unique_rows_reference():
    """The lexsort runs give the labels of np.unique(axis=0)'s counts: most frequent feature per track,
    ties to the smallest (random pairs with many ties, clutter -1, large ids)."""
    def reference(track, feature):
        pairs, counts = np.unique(np.stack([track, feature], axis=1), axis=0, return_counts=True)
        order = np.lexsort((pairs[:, 1], -counts, pairs[:, 0]))
        pairs = pairs[order]
        first = np.ones(len(pairs), dtype=bool)
        first[1:] = pairs[1:, 0] != pairs[:-1, 0]
        return {int(t): int(f) for t, f in pairs[first]}

    rng = np.random.default_rng(11)
    for n, n_tracks, n_features in ((1, 1, 1), (50, 5, 3), (20000, 300, 40), (5000, 2000, 5)):
        track = rng.integers(0, n_tracks, n) * 7919 + 10**9
        feature = rng.integers(-1, n_features, n)
        assert track_labels(track, feature) == reference(track, feature)
