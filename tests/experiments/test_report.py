"""Tests for experiments.report: run and comparison reports from synthetic run directories."""

from __future__ import annotations

import hashlib
import json
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from couplers.publish import MARKER  # noqa: E402
from experiments import report  # noqa: E402
from experiments.report import styles  # noqa: E402

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
METHODS = ["gnss", "icp_da_lc"]
AREAS = [str(i) for i in range(1, 7)]
ZONES = ["A", "B", "C"]


# --------------------------------------------------------------------------- #
# Synthetic inputs
# --------------------------------------------------------------------------- #


def _rect(x0, y0, x1, y1):
    return [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]


@pytest.fixture(scope="module")
def net_dir(tmp_path_factory) -> Path:
    """Tiny net folder: a 2-node, 600 m road built with netconvert, zones, areas, features."""
    sumolib = pytest.importorskip("sumolib")
    d = tmp_path_factory.mktemp("net")
    (d / "n.nod.xml").write_text(
        '<nodes><node id="a" x="0" y="0"/><node id="b" x="600" y="0"/></nodes>\n')
    (d / "n.edg.xml").write_text(
        '<edges><edge id="ab" from="a" to="b" numLanes="2"/><edge id="ba" from="b" to="a"/></edges>\n')
    try:
        exe = sumolib.checkBinary("netconvert")
        subprocess.run([exe, "-n", "n.nod.xml", "-e", "n.edg.xml", "-o", "tlr.net.xml",
                        "--no-warnings"], cwd=d, check=True, capture_output=True, timeout=60)
    except Exception as exc:  # pragma: no cover - environment without SUMO
        pytest.skip(f"netconvert unavailable: {exc!r}")
    zones = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"zone": z, "sigma_p": sp, "sigma_v": sv},
         "geometry": {"type": "Polygon", "coordinates": _rect(200 * i, -50, 200 * (i + 1), 50)}}
        for i, (z, sp, sv) in enumerate([("A", 3, 0.1), ("C", 15, 0.45), ("B", 8, 0.17)])]}
    areas = {"type": "FeatureCollection", "features": [
        {"type": "Feature", "properties": {"area": a},
         "geometry": {"type": "Polygon", "coordinates": _rect(100 * i, -30, 100 * (i + 1), 30)}}
        for i, a in enumerate(AREAS)]}
    (d / "zones.geojson").write_text(json.dumps(zones))
    (d / "areas.geojson").write_text(json.dumps(areas))
    pois = "".join(f'<poi id="f{i}" type="sign" x="{50 + 100 * i}" y="8" color="red"/>' for i in range(6))
    (d / "features.add.xml").write_text(f"<additional>{pois}</additional>\n")
    (d / "scenario.toml").write_text(
        '[files]\nnet = "tlr.net.xml"\nzones = "zones.geojson"\nareas = "areas.geojson"\n'
        'features = "features.add.xml"\n')
    return d


def _make_run(root: Path, name: str, control: str, seed: int, net_dir: Path | None,
              with_features: bool = True) -> Path:
    d = root / name
    d.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    n_t, n_v = 40, 4
    t = np.repeat(np.arange(n_t) * 0.75 * 20, n_v)  # 0 .. ~585 s
    veh = np.tile([f"v{i}" for i in range(n_v)], n_t)
    rows = []
    for m, scale in (("gnss", 4.0), ("icp_da_lc", 0.7)):
        n = t.size
        ea, ec = rng.normal(0, scale, n), rng.normal(0, scale, n)
        x = rng.uniform(0, 600, n)
        rows.append(pd.DataFrame({
            "run": name, "method": m, "t": t, "vehicle": veh,
            "px": x + ea, "py": ec, "vx": 10.0, "vy": 0.0,
            "px_true": x, "py_true": 0.0, "vx_true": 10.0, "vy_true": 0.0,
            "err_pos": np.hypot(ea, ec), "err_vel": np.abs(rng.normal(0, scale / 10, n)),
            "err_along": ea, "err_cross": ec,
            "zone": np.array(ZONES)[np.minimum((x // 200).astype(int), 2)],
            "area": np.array(AREAS)[np.minimum((x // 100).astype(int), 5)],
            "var_px": scale ** 2, "var_py": scale ** 2,
        }))
    est = pd.concat(rows, ignore_index=True)
    est.to_parquet(d / "estimates.parquet", index=False)
    if with_features:
        ft = np.repeat(np.arange(20) * 30.0, 3)
        pd.DataFrame({"method": "icp_da_lc", "t": ft, "track": np.tile(["k0", "k1", "k2"], 20),
                      "err_pos": np.abs(rng.normal(0, 0.5, ft.size))}).to_parquet(
            d / "features.parquet", index=False)
    starts = np.arange(0, 3600, 300.0)
    pd.DataFrame({"interval_start_s": starts, "interval_end_s": starts + 300,
                  "mean_vehicles": 100 + rng.uniform(0, 20, starts.size),
                  "exit_flow_vph": np.linspace(2800, 1800, starts.size),
                  "mean_queue": np.linspace(40, 20, starts.size),
                  "stop_time_s_per_km": np.linspace(40, 35, starts.size),
                  "teleports": 0}).to_parquet(d / "traffic.parquet", index=False)
    pd.DataFrame({"method": "icp_da_lc", "t": [0.0, 0.75], "correct": [10, 12], "wrong": [1, 0],
                  "discarded": [2, 3]}).to_parquet(d / "association.parquet", index=False)

    def stats(g):
        e = g["err_pos"].to_numpy()
        return {"rmse_pos_m": float(np.sqrt(np.mean(e ** 2))), "p95_pos_m": float(np.quantile(e, 0.95)),
                "n": int(e.size)}

    methods = {}
    for m, g in est.groupby("method"):
        e = g["err_pos"].to_numpy()
        methods[m] = {
            "rmse_pos_m": float(np.sqrt(np.mean(e ** 2))),
            "rmse_vel_mps": float(np.sqrt(np.mean(g["err_vel"] ** 2))),
            "p50_pos_m": float(np.median(e)), "p95_pos_m": float(np.quantile(e, 0.95)),
            "by_area": {a: stats(gg) for a, gg in g.groupby("area")},
            "by_zone": {z: stats(gg) for z, gg in g.groupby("zone")},
            "seconds": 1.25,
        }
    summary = {"config": f"experiments/arterial_{control}.toml", "seed": seed, "sumo_version": "1.28.0",
               "git": "abc1234", "methods": methods,
               "association": {"icp_da_lc": {"correct": 22, "wrong": 1, "discarded": 5}},
               "traffic": {"mean_vehicles": 110.5, "exit_flow_vph": 2300.25, "mean_queue": 30.0,
                           "stop_time_s_per_km": 37.5}}
    (d / "summary.json").write_text(json.dumps(summary))
    scen = f'[scenario]\ncontrol = "{control}"\n'
    if net_dir is not None:
        scen += f'net_dir = "{net_dir.as_posix()}"\n'
    (d / "config.toml").write_text(
        f'[run]\nname = "{name}"\nseed = {seed}\n\n{scen}\n[report]\ntrack_area = "5"\n')
    return d


def _img_srcs(page: str) -> list[str]:
    return re.findall(r'<img src="([^"]+)"', page)


def _check_pngs(base: Path, srcs: list[str]) -> None:
    for s in srcs:
        p = base / s
        assert p.exists(), s
        data = p.read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 2000, s


# --------------------------------------------------------------------------- #
# Tests
# --------------------------------------------------------------------------- #


def test_run_report_full(tmp_path, net_dir):
    d = _make_run(tmp_path, "tlr", "tlr", 1, net_dir)
    out = report.write_run_report(d)
    assert out == d / "report.html"
    page = out.read_text(encoding="utf-8")
    srcs = _img_srcs(page)
    expected = {"rmse_time.png", "cdf_area.png", "cdf_zone.png", "track_errors.png", "traffic.png",
                "map.png"}
    assert {Path(s).name for s in srcs} == expected
    # Every figure file that exists is referenced, and every reference exists.
    on_disk = {p.name for p in (d / "figures").glob("*.png")}
    assert on_disk == expected
    _check_pngs(d, srcs)
    assert all(s.startswith("figures/") for s in srcs)
    # Summary table numbers.
    summary = json.loads((d / "summary.json").read_text())
    for m, s in summary["methods"].items():
        for k in ("rmse_pos_m", "rmse_vel_mps", "p50_pos_m", "p95_pos_m"):
            assert f"{s[k]:.3f}" in page, (m, k)
        for a, sa in s["by_area"].items():
            assert f"{sa['p95_pos_m']:.3f}" in page and f"/ {sa['n']}<" in page
        for z, sz in s["by_zone"].items():
            assert f"{sz['p95_pos_m']:.3f}" in page
    assert "GNSS" in page and "ICP-DA-LC" in page
    assert "2300.25" in page  # traffic summary
    assert "fraction correct" in page  # association table
    assert "1.28.0" in page and "abc1234" in page
    # Self-contained: no scripts, no external resources.
    assert "<script" not in page.lower()
    assert not re.search(r'(src|href)="(https?:)?//', page)
    # No temp directories left behind.
    assert not list(d.glob(".report-*"))
    # Deterministic: writing again gives identical HTML and PNG bytes.
    figs1 = {p.name: p.read_bytes() for p in (d / "figures").glob("*.png")}
    assert report.write_run_report(d).read_text(encoding="utf-8") == page
    assert {p.name: p.read_bytes() for p in (d / "figures").glob("*.png")} == figs1


def test_run_report_without_net_and_features(tmp_path):
    d = _make_run(tmp_path, "ctl", "tlr", 2, None, with_features=False)
    (d / "association.parquet").unlink()
    (d / "figures").mkdir()
    (d / "figures" / "stale.png").write_bytes(b"x")  # a previous report's figure (its manifest lists it) goes
    (d / MARKER).write_text(json.dumps({"kind": "run", "files": {"figures/stale.png": hashlib.sha256(b"x").hexdigest()}}))
    page = report.write_run_report(d).read_text(encoding="utf-8")
    srcs = _img_srcs(page)
    assert "figures/map.png" not in srcs
    assert not (d / "figures" / "map.png").exists()
    assert {Path(s).name for s in srcs} == {p.name for p in (d / "figures").glob("*.png")}
    _check_pngs(d, srcs)
    assert "feature position estimates" not in page  # no feature RMSE without features.parquet


def test_comparison_report(tmp_path, net_dir):
    a = _make_run(tmp_path / "runs", "arterial_tlr", "tlr", 1, net_dir)
    b = _make_run(tmp_path / "runs", "arterial_vsr", "vsr", 1, None)
    # Per-run reports are built on demand when missing.
    out_dir = tmp_path / "cmp"
    out = report.write_comparison_report([a, b], out_dir)
    assert out == out_dir / "report.html"
    page = out.read_text(encoding="utf-8")
    assert 'href="../runs/arterial_tlr/report.html"' in page
    assert 'href="../runs/arterial_vsr/report.html"' in page
    assert (a / "report.html").exists() and (b / "report.html").exists()
    srcs = _img_srcs(page)
    assert {Path(s).name for s in srcs} == {"compare_traffic.png", "compare_rmse_time.png"}
    _check_pngs(out_dir, srcs)
    # Per-area p95 table: every (run, method, area) value appears.
    for d in (a, b):
        s = json.loads((d / "summary.json").read_text())
        for m in s["methods"]:
            for sa in s["methods"][m]["by_area"].values():
                assert f"{sa['p95_pos_m']:.3f}" in page
    again = report.write_comparison_report([a, b], out_dir).read_bytes()
    assert again == out.read_bytes()


def test_method_styles():
    assert styles.method_label("gnss") == "GNSS"
    assert styles.method_color("icp_known_da") == "black"
    assert styles.method_label("my_new_method") == "my_new_method"
    assert styles.method_color("my_new_method") == styles.method_color("my_new_method")
    assert styles.order_methods(["zeta", "icp_da_lc", "gnss", "alpha"]) == ["gnss", "icp_da_lc", "alpha", "zeta"]


# --------------------------------------------------------------------------- #
# Speed-ups that must not change the report: worker processes, the CDF quantiles
# --------------------------------------------------------------------------- #


def _quantile_curves_reference(df: pd.DataFrame, group_col: str) -> dict:
    """The CDF points as computed before the one-sort grouping: pandas groups, np.quantile of each."""
    from experiments.report.load import _valid_label

    out = {}
    err = df["err_pos"].to_numpy(dtype=float)
    for (lab, m), idx in df.groupby([group_col, "method"], observed=True, sort=False).indices.items():
        e = err[idx]
        e = e[np.isfinite(e)]
        if _valid_label(lab) and e.size:
            out[(str(lab), str(m))] = np.quantile(e, styles._CDF_GRID)
    return out


@pytest.mark.parametrize("categorical", [True, False])
def test_quantile_curves_equal_reference(categorical):
    from experiments.report.figures import _quantile_curves

    rng = np.random.default_rng(7)
    n = 20000
    df = pd.DataFrame({
        "method": rng.choice(["gnss", "icp_da_lc", "b"], n),
        "area": rng.choice(["1", "2", "10", "", "nan", None], n),
        "err_pos": rng.gamma(2.0, 1.0, n),
    })
    df.loc[rng.random(n) < 0.05, "err_pos"] = np.nan
    df.loc[rng.random(n) < 0.01, "err_pos"] = np.inf
    df.loc[(df["method"] == "b") & (df["area"] == "2"), "err_pos"] = np.nan  # a group without finite errors
    if categorical:
        df = df.astype({"method": "category", "area": "category"})
    got, ref = _quantile_curves(df, "area"), _quantile_curves_reference(df, "area")
    assert sorted(got) == sorted(ref) and ("2", "b") not in got
    for k in ref:
        assert np.array_equal(got[k], ref[k]), k


def test_run_jobs_in_worker_processes():
    from experiments.report.parallel import run_jobs, split_by_weight

    assert split_by_weight([6.5, 3.5, 2, 2, 2, 2, 2], 2) == [[0, 4, 6], [1, 2, 3, 5]]
    assert split_by_weight([1.0], 3) == [[0], [], []]
    jobs = [(w, (lambda i=i: (i, os.getpid()))) for i, w in enumerate([1.0, 5.0, 1.0, 2.0])]
    assert run_jobs(jobs, 1) == [(i, os.getpid()) for i in range(4)]
    out = run_jobs(jobs, 2)
    assert [i for i, _ in out] == [0, 1, 2, 3]
    if threading.active_count() == 1:  # with other threads everything runs in this process
        assert out[1][1] == os.getpid() and {pid for _, pid in out} - {os.getpid()}


def test_run_jobs_error_in_worker(tmp_path):
    from experiments.report.parallel import run_jobs

    if threading.active_count() > 1:
        pytest.skip("jobs run in this process while other threads run")

    def bad():
        (tmp_path / "pid").write_text(str(os.getpid()))
        raise ValueError("figure failed")

    with pytest.raises(ValueError, match="figure failed") as info:
        run_jobs([(5.0, lambda: 1), (1.0, bad)], 2)
    assert any("worker process" in note for note in info.value.__notes__)
    pid = int((tmp_path / "pid").read_text())
    assert pid != os.getpid()
    with pytest.raises(ChildProcessError):  # the child has been waited for
        os.waitpid(pid, os.WNOHANG)


def test_run_report_workers_same_bytes(tmp_path, net_dir):
    """Two drawing processes give the same page and figure bytes as one; a map failure in a worker
    still becomes a note on the page and a warning here."""
    pages, figs = [], []
    for workers in (1, 2, 1):
        d = _make_run(tmp_path / f"w{len(pages)}", "tlr", "tlr", 1, net_dir)
        pages.append(report.write_run_report(d, workers=workers).read_text(encoding="utf-8")
                     .replace(str(d), "RUN"))
        figs.append({p.name: p.read_bytes() for p in (d / "figures").glob("*.png")})
    assert pages[0] == pages[1] == pages[2] and figs[0] == figs[1] == figs[2] and len(figs[0]) == 6

    bad_net = tmp_path / "bad_net"
    bad_net.mkdir()
    for f in net_dir.iterdir():
        (bad_net / f.name).write_bytes(f.read_bytes())
    (bad_net / "zones.geojson").write_text('{"type": "FeatureCollection", "features": [{"geometry": '
                                           '{"type": "Polygon", "coordinates": [[["x", 0], [1, 0], [1, 1]]]}}]}')
    d = _make_run(tmp_path / "bad", "tlr", "tlr", 1, bad_net)
    with pytest.warns(UserWarning, match="map skipped"):
        page = report.write_run_report(d, workers=2).read_text(encoding="utf-8")
    assert "map skipped" in page and "figures/map.png" not in page
    assert not (d / "figures" / "map.png").exists() and (d / "figures" / "cdf_area.png").exists()


def _table_after(page: str, heading: str) -> list[list[str]]:
    """The cells of the first table after ``heading`` (tags stripped), one list per body row."""
    body = page[page.index(heading):]
    body = body[body.index("<tbody>"):body.index("</tbody>")]
    return [[re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", tr)]
            for tr in re.findall(r"<tr>(.*?)</tr>", body)]


def test_comparison_report_shows_each_runs_nees(tmp_path):
    """The comparison's accuracy table has the NEES mean, median and share inside the 95 % ellipse of every
    (run, method), and the per-zone table the by-zone block, both equal to the runs' summary.json."""
    runs = []
    for k, (name, control) in enumerate((("arterial_tlr", "tlr"), ("arterial_vsr", "vsr"))):
        d = _make_run(tmp_path / "runs", name, control, 1, None, with_features=False)
        s = json.loads((d / "summary.json").read_text())
        for j, m in enumerate(sorted(s["methods"])):
            base = 1.5 + 0.75 * k + 2.0 * j
            s["methods"][m]["nees_pos"] = {
                "mean": base, "median": base * 0.6931, "inside_95": 0.9 - 0.1 * j - 0.05 * k, "n": 160,
                "by_zone": {z: {"mean": base + i, "median": (base + i) * 0.7, "inside_95": 0.8 + 0.05 * i, "n": 50}
                            for i, z in enumerate(ZONES)}}
        (d / "summary.json").write_text(json.dumps(s))
        runs.append(d)
    page = report.write_comparison_report(runs, tmp_path / "cmp", build_missing=False).read_text(encoding="utf-8")
    acc = _table_after(page, "<h2>Accuracy summary</h2>")
    assert all(len(r) == 10 for r in acc)  # run, method, 4 errors, 3 NEES columns, time
    zone_rows = {r[0]: r[1:] for r in _table_after(page, "<h2>Consistency per GNSS zone")}
    assert sorted(zone_rows) == sorted(ZONES)
    col = 0
    for d in runs:
        s = json.loads((d / "summary.json").read_text())
        for m in s["methods"]:  # the order the report lists a run's methods in
            n = s["methods"][m]["nees_pos"]
            row = next(r for r in acc if r[1].endswith(f"({m})") and r[0].startswith(d.name))
            assert row[6:9] == [f"{n['mean']:.3f}", f"{n['median']:.3f}", f"{100 * n['inside_95']:.1f}"]
            for z, b in n["by_zone"].items():
                assert zone_rows[z][col] == f"{b['mean']:.3f} / {b['median']:.3f} / {100 * b['inside_95']:.1f}"
            col += 1


def test_comparison_without_nees_has_no_zone_consistency_table(tmp_path):
    a = _make_run(tmp_path / "runs", "arterial_tlr", "tlr", 1, None, with_features=False)
    page = report.write_comparison_report([a], tmp_path / "cmp", build_missing=False).read_text(encoding="utf-8")
    assert "Consistency per GNSS zone" not in page
    assert all(r[6:9] == ["–", "–", "–"] for r in _table_after(page, "<h2>Accuracy summary</h2>"))
