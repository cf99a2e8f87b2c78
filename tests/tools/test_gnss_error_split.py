"""tools/gnss_error_split.py: removing the receivers' shared error zone by zone."""
from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from gnss_error_split import shared_removed  # noqa: E402


@dataclass(frozen=True)
class _Truth:
    x_true: np.ndarray
    zone: np.ndarray


@dataclass(frozen=True)
class _Frame:
    gnss_z: np.ndarray
    truth: _Truth


def test_shared_removed_zeroes_each_zone_mean_and_keeps_the_rest():
    rng = np.random.default_rng(7)
    x = rng.normal(size=(5, 4))
    z = x + rng.normal(scale=3.0, size=(5, 4))
    zone = np.array(["C", "C", "A", "C", "B"])
    fr = _Frame(gnss_z=z.copy(), truth=_Truth(x_true=x, zone=zone))
    (out,) = list(shared_removed([fr]))
    e = out.gnss_z[:, :2] - x[:, :2]
    for name in ("C",):
        assert np.allclose(e[zone == name].mean(axis=0), 0.0, atol=1e-12)
    # per-vehicle deviations from the zone mean are kept
    ec = (z[:, :2] - x[:, :2])[zone == "C"]
    assert np.allclose(e[zone == "C"], ec - ec.mean(axis=0))
    # a zone with one vehicle is left alone, velocities untouched, the input frame not modified
    assert np.array_equal(out.gnss_z[zone != "C"], z[zone != "C"])
    assert np.array_equal(out.gnss_z[:, 2:], z[:, 2:])
    assert np.array_equal(fr.gnss_z, z)
