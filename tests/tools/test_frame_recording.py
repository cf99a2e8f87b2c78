"""tools/frame_recording.py: frames written one pickle after the other come back in order, equal."""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from coloc.core.frame import empty_frame
from tools.frame_recording import read_frames, write_frames


def test_frames_come_back_in_order_and_equal(tmp_path):
    rng = np.random.default_rng(3)
    sent = [replace(empty_frame(float(t), 0.1), vehicle_ids=np.array(["a", f"b{t}"], dtype=object),
                    gnss_z=rng.normal(size=(2, 4))) for t in range(5)]
    path = tmp_path / "frames.pkl"
    write_frames(iter(sent), path)
    got = read_frames(path)
    assert iter(got) is got  # a generator: one frame at a time
    got = list(got)
    assert [f.t for f in got] == [0.0, 1.0, 2.0, 3.0, 4.0]
    for a, b in zip(got, sent):
        assert a.dt == b.dt and np.array_equal(a.gnss_z, b.gnss_z)
        assert list(a.vehicle_ids) == list(b.vehicle_ids)


def test_an_empty_recording_reads_as_no_frames(tmp_path):
    path = tmp_path / "frames.pkl"
    write_frames([], path)
    assert path.is_file() and list(read_frames(path)) == []
