"""summary.json's gnss_world block (experiments.gnss_world): receiver errors by zone and their correlation
against separation, on frames whose errors are drawn with a known correlation."""

from types import SimpleNamespace

import numpy as np
import pytest

from experiments.gnss_world import GnssWorldTally


def _frame(xy, err, zone):
    x_true = np.hstack([xy, np.zeros_like(xy)])
    gnss_z = np.hstack([xy + err, np.zeros_like(xy)])
    return SimpleNamespace(gnss_z=gnss_z, truth=SimpleNamespace(x_true=x_true, zone=np.asarray(zone, dtype=object)))


def test_zone_errors_and_pair_correlation_per_separation_bin():
    """Per step, clusters of two vehicles 20 m apart whose errors correlate by 0.8, the clusters 5 km apart
    (no pair in the other bins) and independent; 2000 steps x 50 clusters = 1e5 pairs per axis: the standard
    error of the correlation is ~(1 - 0.64) / sqrt(1e5) ~ 0.001; tolerance 0.02."""
    rng = np.random.default_rng(0)
    tally = GnssWorldTally()
    rho, k = 0.8, 50
    all_err = {"A": [], "C": []}
    for _ in range(2000):
        base = np.stack([np.arange(k) * 5000.0, np.zeros(k)], axis=1)
        xy = np.concatenate([base, base + [20.0, 0.0]])
        a = rng.standard_normal((k, 2))
        b = rho * a + np.sqrt(1 - rho ** 2) * rng.standard_normal((k, 2))
        scale = np.where(np.arange(k) % 2 == 0, 3.0, 15.0)[:, None]
        err = np.concatenate([a * scale, b * scale])
        zone = np.concatenate([np.where(np.arange(k) % 2 == 0, "A", "C")] * 2)
        tally.add(_frame(xy, err, zone))
        for z in ("A", "C"):
            all_err[z].append(np.hypot(*err[zone == z].T))
    s = tally.summary()
    corr = s["error_correlation_by_separation"]
    assert corr["10-50m"]["pairs"] == 2000 * k
    assert corr["50-200m"]["pairs"] == 0 and corr["50-200m"]["x"] is None
    # scales 3 and 15 mixed within the bin: the pooled correlation is still rho (both members share the scale)
    assert corr["10-50m"]["x"] == pytest.approx(rho, abs=0.02)
    assert corr["10-50m"]["y"] == pytest.approx(rho, abs=0.02)
    for z in ("A", "C"):
        e = np.concatenate(all_err[z])
        got = s["receiver_error_by_zone"][z]
        assert got["n"] == e.size
        assert got["rms_2d_m"] == pytest.approx(float(np.sqrt(np.mean(e * e))), rel=1e-12)
        assert got["p95_2d_m"] == pytest.approx(float(np.percentile(e, 95)), rel=1e-12)
    assert s["receiver_error_by_zone"]["all"]["n"] == 2000 * 2 * k


def test_independent_errors_do_not_correlate():
    rng = np.random.default_rng(1)
    tally = GnssWorldTally()
    for _ in range(300):
        xy = rng.uniform(0, 1500, (60, 2))
        tally.add(_frame(xy, rng.standard_normal((60, 2)) * 5, ["B"] * 60))
    for block in tally.summary()["error_correlation_by_separation"].values():
        assert block["pairs"] > 1000
        # the standard error of a null correlation over n pairs is ~ 1 / sqrt(n): tolerance 5 of them
        tol = 5.0 / np.sqrt(block["pairs"])
        assert abs(block["x"]) < tol and abs(block["y"]) < tol


def test_correlation_by_zone_keeps_the_pairs_of_one_zone():
    """Zone A pairs share most of their error (rho 0.9), zone C pairs none, and mixed pairs (one vehicle in each
    zone, 30 m apart) are independent too: the pooled rho mixes them, the per-zone blocks give each zone's own;
    a mixed pair counts in no zone. 1500 steps x 40 pairs per kind: tolerance 0.03 (standard errors < 0.01)."""
    rng = np.random.default_rng(2)
    tally = GnssWorldTally()
    k, rho = 40, 0.9
    for _ in range(1500):
        base = np.stack([np.arange(3 * k) * 3000.0, np.zeros(3 * k)], axis=1)
        xy = np.concatenate([base, base + [30.0, 0.0]])
        a = rng.standard_normal((3 * k, 2))
        b = rng.standard_normal((3 * k, 2))
        b[:k] = rho * a[:k] + np.sqrt(1 - rho ** 2) * b[:k]
        zone = np.array(["A"] * k + ["C"] * k + ["A"] * k + ["A"] * k + ["C"] * k + ["C"] * k, dtype=object)
        tally.add(_frame(xy, np.concatenate([a, b]), zone))
    s = tally.summary()
    by_zone = s["error_correlation_by_zone_and_separation"]
    assert by_zone["A"]["10-50m"]["pairs"] == by_zone["C"]["10-50m"]["pairs"] == 1500 * k
    assert by_zone["A"]["10-50m"]["x"] == pytest.approx(rho, abs=0.03)
    assert by_zone["C"]["10-50m"]["y"] == pytest.approx(0.0, abs=0.03)
    assert by_zone["A"]["200-1000m"]["pairs"] == 0 and by_zone["A"]["200-1000m"]["x"] is None
    assert s["error_correlation_by_separation"]["10-50m"]["pairs"] == 1500 * 3 * k
    assert s["error_correlation_by_separation"]["10-50m"]["x"] == pytest.approx(rho / 3, abs=0.03)
