"""summary.json blocks of realistic sensing: the 2-D position NEES (a consistent Gaussian gives mean 2, median
2 ln 2 and 95 % of its samples inside the 95 % ellipse) and the association shares per GNSS zone (they add up
to the run's)."""

import numpy as np

from coloc.core.frame import StepEstimate
from experiments.runner import EstimateLog
from experiments.scoring import nees_summary


def test_nees_of_samples_drawn_from_the_reported_covariance_is_two():
    """Errors drawn from N(0, P) with correlated P: mean NEES within 4 standard errors of 2
    (NEES ~ chi-square 2, variance 4), and per zone likewise."""
    rng = np.random.default_rng(3)
    log = EstimateLog()
    n, steps = 50, 200
    for t in range(steps):
        a = rng.normal(size=(n, 2, 2))
        p2 = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(2)
        cov = np.repeat(np.eye(4)[None], n, 0)
        cov[:, :2, :2] = p2
        x_true = rng.normal(size=(n, 4))
        e = np.einsum("nij,nj->ni", np.linalg.cholesky(p2), rng.normal(size=(n, 2)))
        mean = x_true.copy()
        mean[:, :2] += e
        log.truth_parts.append((np.full(n, float(t)), np.arange(n).astype(str), x_true, np.zeros(n),
                                np.where(np.arange(n) < 25, "A", "B"), np.full(n, "1")))
        log.add("m", StepEstimate(mean=mean, cov=cov))
    nees = log.position_nees("m")
    zone = np.concatenate([p[4] for p in log.truth_parts])
    out = nees_summary(nees, zone)
    se = 2.0 / np.sqrt(nees.size)
    assert abs(out["mean"] - 2.0) < 4 * se
    assert out["n"] == nees.size
    # the share inside the 95 % ellipse: binomial(n, 0.95), two-sided 0.1 % band (z = 3.29)
    half = 3.29 * np.sqrt(0.95 * 0.05 / nees.size)
    assert abs(out["inside_95"] - 0.95) < half
    # the median of a chi-square with 2 dof is 2 ln 2; its standard error ~ 1 / (2 f(m) sqrt(n)), f(m) = 1/4
    assert abs(out["median"] - 2.0 * np.log(2.0)) < 4 * 2.0 / np.sqrt(nees.size)
    for z in ("A", "B"):
        b = out["by_zone"][z]
        assert abs(b["mean"] - 2.0) < 4 * 2.0 / np.sqrt(nees.size / 2)
        assert abs(b["inside_95"] - 0.95) < 3.29 * np.sqrt(0.95 * 0.05 / b["n"])
    # the same errors against a covariance claiming half the spread: overconfident, far outside the band
    over = nees_summary(2.0 * nees, zone)
    assert over["inside_95"] < 0.95 - 10 * half and abs(over["mean"] - 4.0) < 8 * se


def test_association_by_zone_adds_up_to_the_run_totals():
    from experiments.scoring import association_by_group, score_association

    rng = np.random.default_rng(5)
    steps, groups = [], []
    for _ in range(30):
        o = rng.integers(0, 12)
        truth = rng.integers(-1, 5, o)
        assign = np.where(rng.random(o) < 0.8, truth + rng.integers(0, 2, o) * 7, -1)
        steps.append((assign, truth))
        groups.append(rng.choice(["A", "B", "C"], o))
    counts, labels = score_association(steps)
    by = association_by_group(steps, groups, labels)
    for i, key in enumerate(("correct", "wrong", "discarded")):
        assert sum(b[key] for b in by.values()) == counts[:, i].sum()
