"""A run's frames recorded to a file, one pickle after the other, and read back one at a time: the
recordings that ``tools/gnss_model_replay.py`` and ``bench/lc_replay.py`` replay estimators on."""

from __future__ import annotations

import pickle
from collections.abc import Iterable, Iterator
from pathlib import Path


def write_frames(frames: Iterable, path: Path) -> None:
    """Pickle every frame of ``frames`` to ``path`` (protocol 5), in order."""
    with open(path, "wb") as f:
        for frame in frames:
            pickle.dump(frame, f, protocol=5)


def read_frames(path: Path) -> Iterator:
    """The frames ``write_frames`` wrote to ``path``, in order, without holding them all in memory."""
    with open(path, "rb") as f:
        while True:
            try:
                yield pickle.load(f)
            except EOFError:
                return
