"""tools/nees_diagnosis.py: the NEES with the cross term, the covariates from the files, and the bins."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tools"))
from nees_diagnosis import GATE, load, pivot, table  # noqa: E402


def _run(tmp_path: Path, rng: np.random.Generator) -> Path:
    """Two methods, vehicle a present at switch-on (t = 600), vehicle b entering at 650; errors drawn from
    each row's covariance (cross term included) for "gnss", twice that covariance for "m"."""
    rows = []
    cov = np.array([[4.0, 1.5], [1.5, 2.0]])
    chol = np.linalg.cholesky(cov)
    for t in np.arange(600.75, 900.0, 0.75):  # the first estimated step after a switch-on at 600
        for v, t0 in (("a", 600.0), ("b", 650.0)):
            if t < t0:
                continue
            for m, k in (("gnss", 1.0), ("m", 2.0)):
                e = np.sqrt(k) * chol @ rng.standard_normal(2)
                rows.append(dict(method=m, t=t, vehicle=v, px=e[0], py=e[1], px_true=0.0, py_true=0.0,
                                 vx_true=3.0, vy_true=4.0, err_pos=float(np.hypot(*e)), zone="A",
                                 var_px=cov[0, 0], var_py=cov[1, 1], cov_pxy=cov[0, 1]))
    d = tmp_path / "run"
    d.mkdir()
    pd.DataFrame(rows).to_parquet(d / "estimates.parquet")
    return d


def test_nees_covariates_and_bins(tmp_path):
    d = load([_run(tmp_path, np.random.default_rng(7))], 600.0)
    # NEES with the cross term: chi-square 2 for the consistent method, twice that for the other
    assert abs(d[d.method == "gnss"].nees.mean() - 2.0) < 0.15
    assert abs(d[d.method == "m"].nees.mean() - 4.0) < 0.3
    assert np.allclose(d.speed, 5.0)
    assert d[d.vehicle == "a"].since_entry.isna().all()  # present at switch-on: not an entry
    b = d[d.vehicle == "b"]
    assert b.since_entry.min() == 0.0 and np.allclose(b.since_entry, b.t - 650.25)  # first step on or after 650
    assert np.allclose(d.since_on, d.t - 600.0) and d.since_on.min() == 0.75
    # the gnss method's own NEES joins on (run, t, vehicle)
    g = d[d.method == "gnss"]
    assert np.allclose(g.nees, g.gnss_nees)
    t = table(d, "since_on", zones=False)
    assert (t.loc["gnss"].inside_95 > 0.9).all()
    assert (t.loc["m"].inside_95 < 0.9).all()  # expected 1 - exp(-5.99 / 4) = 0.78
    p = pivot(d, "since_entry")
    assert list(p.columns) == ["on", "0-15", "15-60", "60-120", "120-300.1"]
    on = d[(d.method == "gnss") & d.since_entry.isna()]
    assert p.loc[("gnss", "all"), "on"].startswith(f"{100 * np.mean(on.nees <= GATE):.1f} (")


def test_rows_before_the_scored_window_left_out(tmp_path):
    """A sensed warm-up keeps its rows in the file: the cells score t >= --from only, as summary.json does, and the
    entries are still found on every row (vehicle b, now on from the run's first row, is not an entry; a is)."""
    rng = np.random.default_rng(3)
    run = _run(tmp_path, rng)
    f = pd.read_parquet(run / "estimates.parquet")
    early = f[f.vehicle == "b"].copy()
    early["t"] -= 200.0  # vehicle b's rows moved to 450.25-699.25: it entered before the window
    early["px"] += 50.0  # and those rows are far off, so scoring them would show
    pd.concat([f[f.vehicle == "a"], early]).to_parquet(run / "estimates.parquet")
    every = load([run], 600.0)
    scored = load([run], 600.0, 600.0)
    assert every.t.min() < 600.0 and scored.t.min() >= 600.0
    assert len(scored) == int((every.t >= 600.0).sum())
    assert scored[scored.vehicle == "b"].since_entry.isna().all()  # on at the run's first row, before the window
    a = scored[scored.vehicle == "a"]
    assert np.allclose(a.since_entry, a.t - 600.75)
    assert table(scored, "speed", zones=False).loc["gnss"].inside_95.min() < 0.9 < \
        table(scored[scored.vehicle == "a"], "speed", zones=False).loc["gnss"].inside_95.min()
