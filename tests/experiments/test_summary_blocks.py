"""summary.json blocks of realistic sensing: the mean 2-D position NEES (a consistent Gaussian gives 2) and the
association shares per GNSS zone (they add up to the run's)."""

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
    for z in ("A", "B"):
        assert abs(out["by_zone"][z] - 2.0) < 4 * 2.0 / np.sqrt(nees.size / 2)


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
