"""tools/coop_replay.py: the row bookkeeping and the table cells it prints."""

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tools.coop_replay import row_fate, table_row  # noqa: E402


def test_row_fate_counts_each_landmarks_majority_track_and_the_clutter_used():
    # landmark 0: tracks 5, 5, 5, 7, discarded; landmark 1: 9, 9; clutter: used once of 2; persistent: 1 of 1
    kind = np.array([0, 0, 0, 0, 0, 0, 0, 1, 1, 2])
    feat = np.array([0, 0, 0, 0, 0, 1, 1, -1, -1, -1])
    track = np.array([5, 5, 5, 7, -1, 9, 9, 3, -1, 4])
    out = row_fate({"kind": kind, "feat": feat, "track": track})
    assert out["landmark rows"] == 7
    assert out["on majority track %"] == pytest.approx(100 * 5 / 7)
    assert out["on other track %"] == pytest.approx(100 / 7)
    assert out["discarded %"] == pytest.approx(100 / 7)
    assert out["clutter used %"] == pytest.approx(50.0)
    assert out["persistent used %"] == pytest.approx(100.0)


def test_table_row_pools_errors_and_averages_each_runs_nees():
    runs = [{"err": np.array([3.0, 4.0]), "nees": np.array([1.0, 9.0]), "zone": np.array(["A", "C"])},
            {"err": np.array([0.0, 0.0]), "nees": np.array([1.0, 1.0]), "zone": np.array(["A", "A"])}]
    cells = table_row("x", runs).strip("| ").split(" | ")
    assert cells[0] == "x"
    a, b, c, total = cells[1:]
    # zone A: errors 3, 0, 0 -> RMSE sqrt(3); NEES means 1 (run 1) and 1 (run 2); all inside
    assert a.startswith(f"{np.sqrt(3.0):.2f} / ") and a.endswith(", 1.00, 100.0")
    assert b == "-"
    assert c == "4.00 / 4.00, 9.00, 0.0"  # NEES 9 > 5.99: outside the 95 % ellipse
    # all: run means 5 and 1 -> 3; one sample of four outside
    assert total.endswith(", 3.00, 75.0") and total.startswith(f"{np.sqrt(25 / 4):.2f} / ")
