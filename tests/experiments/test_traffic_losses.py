"""Nothing lost silently: vehicles never inserted / dropped at load are counted and reported, unsorted route
files are refused (or sorted on request), a user's demand gets the gridlock trial, and default layouts
of zones and areas are called placeholders in summary.json, the map and the captions."""

from __future__ import annotations

import json
import shutil
import tomllib
from pathlib import Path

import numpy as np
import pandas as pd

from couplers.net.check import check_net_folder
from couplers.net.importer.sumocfg import first_unsorted, sorted_routes_text
from experiments.cli import main

CONFIG = """
[run]
name = "{name}"
seed = 1
duration_s = {duration}
methods = ["gnss"]

[scenario]
kind = "sumo"
net_dir = "{net}"
control = "tlr"

[report]
track_area = "{area}"
"""

# 120 cars departing at the same second from one lane (SC, 400 m, single lane): SUMO inserts them one
# after the other as the lane clears, far fewer than 120 within 30 s.
BURST = """<routes>
  <vType id="car" length="4.5" minGap="2.5"/>
  <route id="sn" edges="SC CN"/>
{vehicles}
</routes>
"""

UNSORTED = """<routes>
  <vType id="car"/>
  <route id="we" edges="WC CE"/>
  <vehicle id="late" type="car" route="we" depart="100"/>
  <vehicle id="early" type="car" route="we" depart="5"/>
  <vehicle id="v2" type="car" route="we" depart="8"/>
  <flow id="f" type="car" route="we" begin="3" end="50" period="10"/>
</routes>
"""


def _config(tmp: Path, net: Path, name: str = "losses", duration: float = 30.0, area: str = "3") -> Path:
    path = tmp / f"{name}.toml"
    path.write_text(CONFIG.format(name=name, net=net, duration=duration, area=area))
    return path


def test_vehicles_never_inserted_are_counted_and_reported(cross_net, tmp_path, capsys):
    net = tmp_path / "net"
    shutil.copytree(cross_net, net)
    vehicles = "\n".join(f'  <vehicle id="b{i}" type="car" route="sn" depart="0" departLane="0"/>'
                         for i in range(120))
    (net / "demand.rou.xml").write_text(BURST.format(vehicles=vehicles))
    out = tmp_path / "run"
    assert main(["run", str(_config(tmp_path, net)), "--out", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out
    tr = json.loads((out / "summary.json").read_text())["traffic"]
    assert tr["never_inserted"] > 0
    assert tr["inserted"] > 0
    assert tr["inserted"] + tr["never_inserted"] == 120  # every vehicle due is accounted for
    assert tr["dropped_at_load"] == 0 and tr["collisions"] == 0
    assert f"{tr['never_inserted']} never inserted" in printed
    assert "backlog" not in printed or tr["jammed"]
    # the insertion backlog is the gridlock rule's third sign (more than 20 waiting)
    assert tr["jammed"] and "waiting to enter" in tr["jam_verdict"] and "JAMMED" in printed
    # traffic.parquet keeps its schema (the counters live in summary.json only)
    assert "never_inserted" not in pd.read_parquet(out / "traffic.parquet").columns


def test_vehicles_dropped_at_load_are_counted_from_sumo_warnings(cross_net, tmp_path):
    """A folder that bypasses the check (the SUMO layer itself): SUMO's 'should be sorted' warnings are
    read from its error log, not lost with the console's --no-warnings. SUMO reads the file ahead in
    chunks of 200 s (--route-steps) and warns when it reaches the vehicles: the run covers that."""
    from couplers.traffic.sumo import SumoOptions, SumoTraffic

    routes = tmp_path / "unsorted.rou.xml"
    routes.write_text(UNSORTED)
    opts = SumoOptions(net=cross_net / "tlr.net.xml", routes=routes, seed=1, end=300.0)
    with SumoTraffic(opts) as traffic:
        while not traffic.done():
            traffic.step()
    got = traffic.losses()
    assert got["dropped_unsorted"] == 3 and got["first_dropped"] == "unsorted 'early'"  # early, v2, flow f
    assert got["dropped_at_load"] == 3 and got["inserted"] == 1


def test_unsorted_routes_found_and_sorted(tmp_path):
    path = tmp_path / "r.rou.xml"
    path.write_text(UNSORTED)
    why = first_unsorted(path)
    assert why is not None and "'early'" in why and "'late'" in why
    text, moved = sorted_routes_text(path)
    (tmp_path / "s.rou.xml").write_text(text)
    assert first_unsorted(tmp_path / "s.rou.xml") is None
    assert moved > 0
    order = [line.split('id="')[1].split('"')[0] for line in text.splitlines() if "<vehicle" in line
             or "<flow" in line]
    assert order == ["f", "early", "v2", "late"]
    assert text.index("<vType") < text.index("<route id") < text.index("<flow")


def test_net_check_refuses_unsorted_routes(cross_net, tmp_path):
    net = tmp_path / "net"
    shutil.copytree(cross_net, net)
    (net / "demand.rou.xml").write_text(UNSORTED)
    problems, _ = check_net_folder(net)
    assert len(problems) == 1
    assert "demand.rou.xml: depart: not sorted by departure" in problems[0] and "'early'" in problems[0]
    assert main(["net", "check", str(net)]) == 1


def _import(tmp: Path, cross_net: Path, *extra: str) -> Path:
    out = tmp / "imp"
    argv = ["net", "import", "--net", str(cross_net / "tlr.net.xml"), "--name", "imp", "--out", str(out),
            "--experiments-dir", str(tmp / "exps"), *extra]
    assert main(argv) == 0
    return out


def test_import_sorts_routes_on_request_and_trials_the_users_demand(cross_net, tmp_path, capsys):
    routes = tmp_path / "unsorted.rou.xml"
    routes.write_text(UNSORTED)
    out = _import(tmp_path, cross_net, "--routes", str(routes), "--sort-routes")
    printed = capsys.readouterr().out
    assert "not sorted by departure; the folder's demand.rou.xml holds it sorted" in printed
    assert "gridlock trial of the demand" in printed
    assert first_unsorted(out / "demand.rou.xml") is None
    assert routes.read_text() == UNSORTED  # the user's file is not touched
    scen = tomllib.loads((out / "scenario.toml").read_text())
    assert "demand.rou.xml" in scen["derived"]["routes_sorted"]
    trial = scen["derived"]["demand_gridlock_trial"]
    assert trial["rescaled"] is False and trial["vsr"]["verdict"]
    assert scen["import"]["sort_routes"] is True and scen["import"]["calibrate"] is True
    # the user's demand is kept as given (sorted), never rescaled: the same vehicles
    assert (out / "demand.rou.xml").read_text().count("<vehicle") == 3
    assert check_net_folder(out)[0] == []


def test_no_calibrate_skips_the_users_demand_trial(cross_net, tmp_path, capsys):
    out = _import(tmp_path, cross_net, "--routes", str(cross_net / "demand.rou.xml"), "--no-calibrate")
    capsys.readouterr()
    scen = tomllib.loads((out / "scenario.toml").read_text())
    assert "demand_gridlock_trial" not in scen["derived"]
    assert any("gridlock trial of the user's demand: skipped" in x for x in scen["not_derived"]["items"])


def test_placeholder_zones_and_areas_are_said_so(cross_net, tmp_path, capsys):
    out = _import(tmp_path, cross_net, "--routes", str(cross_net / "demand.rou.xml"), "--no-calibrate")
    scen = tomllib.loads((out / "scenario.toml").read_text())
    assert any(x.startswith("analysis areas from data") for x in scen["not_derived"]["items"])
    run = tmp_path / "run"
    areas = json.loads((out / "areas.geojson").read_text())["features"]
    assert main(["run", str(_config(tmp_path, out, "placeholders", area=areas[0]["properties"]["area"])),
                 "--out", str(run), "--quiet"]) == 0
    capsys.readouterr()
    summary = json.loads((run / "summary.json").read_text())
    assert set(summary["placeholders"]) == {"zones", "areas"}
    assert "not derived from data" in summary["placeholders"]["zones"]
    html = (run / "report.html").read_text()
    assert "GNSS degrades from open-sky to built-up zones" not in html
    assert "the zones are a default layout" in html
    assert "The areas are a default grid" in html
    assert "sample count n" in html


def test_shipped_folder_has_no_placeholders(cross_net, tmp_path, capsys):
    run = tmp_path / "run"
    assert main(["run", str(_config(tmp_path, cross_net)), "--out", str(run), "--quiet"]) == 0
    capsys.readouterr()
    summary = json.loads((run / "summary.json").read_text())
    assert summary["placeholders"] == {}
    assert "GNSS degrades from open-sky to built-up zones" in (run / "report.html").read_text()


def test_default_areas_without_a_road_are_dropped():
    from shapely.geometry import LineString

    from couplers.net.importer import _Report
    from couplers.net.importer.regions import _default_areas

    # an L of roads: along the south edge and up the west edge of a 900 x 600 box
    lines = [LineString([(0, 0), (900, 0)]), LineString([(0, 0), (0, 600)])]
    xy = np.array([p for line in lines for p in line.coords])
    report = _Report()
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "areas.geojson"
        _default_areas(path, xy, report, lines)
        names = [f["properties"]["area"] for f in json.loads(path.read_text())["features"]]
    assert names == ["1", "2", "3", "4"]  # 3 x 2 grid: 5 and 6 (north-middle, north-east) have no road
    assert any("areas 5, 6 of the default grid: no road crosses them" in x for x in report.not_derived)


def test_default_areas_keep_a_cell_that_holds_only_a_footpath():
    """A cell crossed by no drivable lane but holding shape points of another lane (a footpath, a rail) is
    kept: ``coloc net check`` wants every lane shape point covered, so dropping it wrote a folder the
    check refused (an imported Berlin: 148 of 74866 points uncovered)."""
    import shapely
    from shapely.geometry import LineString

    from couplers.net.importer import _Report
    from couplers.net.importer.regions import _default_areas

    lines = [LineString([(0, 0), (900, 0)]), LineString([(0, 0), (0, 600)])]
    footpath = np.array([[700.0, 500.0], [850.0, 550.0]])  # in cell 6 only
    xy = np.vstack([np.array([p for line in lines for p in line.coords]), footpath])
    report = _Report()
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "areas.geojson"
        _default_areas(path, xy, report, lines)
        feats = json.loads(path.read_text())["features"]
    assert [f["properties"]["area"] for f in feats] == ["1", "2", "3", "4", "6"]
    union = shapely.union_all([shapely.geometry.shape(f["geometry"]) for f in feats])
    assert shapely.intersects_xy(union, xy[:, 0], xy[:, 1]).all()  # what net check tests
    assert any("areas 5 of the default grid" in x for x in report.not_derived)


def test_cdf_panels_show_the_sample_count(monkeypatch, tmp_path):
    from experiments.report import figures
    from experiments.report.digest import digest_estimates
    from experiments.report.load import _Run

    rng = np.random.default_rng(0)
    n = {"A": 300, "B": 100}
    rows = []
    for zone, k in n.items():
        for m in ("gnss", "icp_da_lc"):
            rows.append(pd.DataFrame({"zone": zone, "method": m, "t": np.arange(k) * 0.75, "err_pos": rng.random(k)}))
    est = pd.concat(rows, ignore_index=True)
    est.to_parquet(tmp_path / "estimates.parquet", index=False)
    run = _Run(run_dir=tmp_path, config={}, summary={})
    run.digest = digest_estimates(tmp_path / "estimates.parquet", None)
    drawn = {}
    monkeypatch.setattr(figures, "_save", lambda fig, path: drawn.setdefault("fig", fig))
    figures._fig_cdf(run, "zone", tmp_path / "cdf.png", "zone")
    titles = [ax.get_title() for ax in drawn["fig"].axes if ax.get_visible()]
    assert titles == ["zone A (n = 300, 75.0% of samples)", "zone B (n = 100, 25.0% of samples)"]


def test_cold_numba_cache_is_announced(tmp_path, monkeypatch):
    from experiments.warm import CORE, cold_cache_note, kernel_index_files

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "empty"))
    note = cold_cache_note()
    assert note is not None and note.startswith("coloc: compiling numba kernels (first run after install")
    files = kernel_index_files(None, CORE)
    assert len(files) >= 10 and all(str(f).startswith(str(tmp_path / "empty")) for f in files)
    for f in files:  # numba's index files in place: warm
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b"")
    assert cold_cache_note() is None


def test_cache_dir_index_files_are_where_numba_puts_them(tmp_path, monkeypatch):
    """Under NUMBA_CACHE_DIR numba names a source folder's cache <name>_<sha1 of its path> (an earlier
    guess, the source path under the cache dir, saw a filled cache as cold)."""
    from numba.core.caching import _CacheLocator

    from experiments.warm import CORE, kernel_index_files

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    root = Path(__file__).resolve().parents[2]
    for src in CORE:
        f = kernel_index_files(None, (src,))[0]
        assert f.parent == tmp_path / _CacheLocator.get_suitable_cache_subpath(str(root / src))


def test_eta_is_timed_after_the_first_batches(monkeypatch, capsys):
    """The progress line's ETA leaves out the first steps (numba compiles there on a cold cache)."""
    from types import SimpleNamespace

    from experiments import runner

    clock = {"t": 0.0}
    monkeypatch.setattr(runner.time, "perf_counter", lambda: clock["t"])
    monkeypatch.setattr(runner.sys.stderr, "isatty", lambda: False, raising=False)

    def frames():
        for k in range(1, 801):
            clock["t"] += 100.0 if k == 1 else 0.1  # 100 s of compilation in the first step
            yield SimpleNamespace(t=k * 0.75)

    list(runner.progress_frames(frames(), 800, "r", None))
    line = capsys.readouterr().err.strip().splitlines()[0]
    # step 400 of 800: 400 steps left at 0.1 s each = 40 s, not (100 + 40) s
    assert "step 400 of 800" in line and "about 40 s left" in line, line
