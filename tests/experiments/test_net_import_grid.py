"""`coloc net import` over a grid of option values: every import that exits 0 writes a folder that
`coloc net check` accepts, and every other one is refused with one line, nothing written.

The values sit at the edges of the options' ranges (experiments/ranges.py OPTION_RANGES) and in odd
combinations: a single feature, more features than places, one kind only, a demand of one second, the
smallest fringe factor and zone cell, the extreme seeds, an extract without buildings or signals, the
signal modes, a tiny net, a SUMO net with the user's routes (sorted by the import, or empty), a SUMO
configuration. Refused here before anything is written: no features, a kind with no place in the
net, a demand that rounds to no vehicle, more zone cells than the import computes.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from couplers.net.check import check_net_folder
from experiments.cli import main
from netfixture import build_cross_net
from osmfixture import write_osm_grid
from sumocfgfixture import build_sumocfg_scenario

NO_CALIBRATION = ("--no-calibrate",)  # the gridlock trials are the import's slowest part; one case keeps them

TINY_OSM = """<?xml version="1.0"?>
<osm version="0.6">
<node id="1" lat="45.07" lon="7.68"/>
<node id="2" lat="45.07" lon="7.682"/>
<way id="1"><nd ref="1"/><nd ref="2"/><tag k="highway" v="residential"/></way>
</osm>
"""

UNSORTED_ROUTES = """<routes>
  <vType id="car"/>
  <route id="we" edges="WC CE"/>
  <vehicle id="late" type="car" route="we" depart="100"/>
  <vehicle id="early" type="car" route="we" depart="50"/>
</routes>
"""


def _source(kind: str, tmp: Path) -> list[str]:
    if kind == "osm":
        return ["--osm", str(write_osm_grid(tmp / "grid.osm"))]
    if kind == "osm_no_buildings":
        return ["--osm", str(write_osm_grid(tmp / "grid.osm", buildings=False))]
    if kind == "osm_no_signals":
        return ["--osm", str(write_osm_grid(tmp / "grid.osm", signals=False))]
    if kind == "osm_no_bus_stop":
        return ["--osm", str(write_osm_grid(tmp / "grid.osm", bus_stop=False))]
    if kind == "osm_tiny":
        (tmp / "tiny.osm").write_text(TINY_OSM)
        return ["--osm", str(tmp / "tiny.osm")]
    if kind == "sumocfg":
        return ["--sumocfg", str(build_sumocfg_scenario(tmp / "scenario"))]
    cross = build_cross_net(tmp / "cross")
    if kind == "net":
        return ["--net", str(cross / "tlr.net.xml")]
    if kind == "net_unsorted_routes":
        (tmp / "unsorted.rou.xml").write_text(UNSORTED_ROUTES)
        return ["--net", str(cross / "tlr.net.xml"), "--routes", str(tmp / "unsorted.rou.xml"), "--sort-routes"]
    if kind == "net_empty_routes":
        (tmp / "empty.rou.xml").write_text("<routes>\n</routes>\n")
        return ["--net", str(cross / "tlr.net.xml"), "--routes", str(tmp / "empty.rou.xml")]
    raise AssertionError(kind)


# name: (source, options, None if the import must succeed, else words of its one error line)
GRID = {
    "defaults": ("osm", [], None),
    "calibrated": ("osm", ["--calibration-s", "300"], None),
    "one_feature": ("osm", ["--features", "1"], None),
    "more_features_than_places": ("osm", ["--features", "100000"], None),
    "signs_only": ("osm", ["--feature-kinds", "sign"], None),
    "one_second_of_demand": ("osm", ["--duration", "1"], None),
    "smallest_fringe_factor": ("osm", ["--fringe-factor", "1e-9"], None),
    "smallest_zone_cell": ("osm", ["--zone-cell", "10"], None),
    "seed_0": ("osm", ["--seed", "0"], None),
    "largest_seed": ("osm", ["--seed", "2147483647"], None),
    "no_buildings": ("osm_no_buildings", [], None),
    "guessed_signals": ("osm_no_signals", ["--guess-signals"], None),
    "rebuilt_signals": ("osm", ["--rebuild-signals"], None),
    "kept_signals": ("osm", ["--keep-signals"], None),
    "sumo_net": ("net", [], None),
    "sorted_user_routes": ("net_unsorted_routes", [], None),
    "sumocfg": ("sumocfg", [], None),
    # refused: each would have written a folder `coloc net check` refuses
    "no_features": ("osm", ["--features", "0"], ["--features", "outside [1, 100000]"]),
    "a_kind_without_places": ("osm_no_bus_stop", ["--feature-kinds", "bus_stop"],
                              ["--feature-kinds", "no place for a feature", "no bus stops"]),
    "no_demand": ("osm", ["--demand", "0", "0"], ["--demand", "no vehicle"]),
    "demand_scaled_to_nothing": ("osm", ["--demand-scale", "1e-9"], ["--demand-scale", "no vehicle"]),
    "density_cap_at_nothing": ("osm", ["--max-density-scale", "1e-9"], ["no vehicle"]),
    "empty_user_routes": ("net_empty_routes", [], ["empty.rou.xml", "no vehicles, flows or trips"]),
    "no_signals": ("osm_no_signals", [], ["no traffic lights", "--guess-signals"]),
    "tiny_net": ("osm_tiny", [], ["tiny.osm", "no edge open to passenger cars"]),
}
# cases that end before netconvert runs (option checks): fast; the others import (tens of seconds each)
FAST = ("no_features",)


def _import(name: str, tmp_path: Path, capsys) -> tuple[int, Path, list[str]]:
    source, options, _ = GRID[name]
    out = tmp_path / "nets" / "g"
    capsys.readouterr()
    rc = main(["net", "import", *_source(source, tmp_path), "--name", "g", "--out", str(out),
               "--experiments-dir", str(tmp_path / "exps"), *options,
               *(NO_CALIBRATION if "--calibration-s" not in options else ())])
    return rc, out, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("name", [pytest.param(n, marks=() if n in FAST else pytest.mark.slow) for n in GRID])
def test_an_import_writes_a_folder_net_check_accepts_or_refuses_in_one_line(name, tmp_path, capsys):
    rc, out, err = _import(name, tmp_path, capsys)
    words = GRID[name][2]
    if rc == 0:
        assert words is None, f"imported, but expected a refusal naming {words}"
        problems, info = check_net_folder(out)
        assert problems == [], problems
        assert main(["net", "check", str(out)]) == 0
        return
    assert rc == 2 and len(err) == 1 and err[0].startswith("coloc: error: "), err
    assert words is not None, err[0]
    assert all(w in err[0] for w in words), err[0]
    assert not (tmp_path / "nets").exists() and not (tmp_path / "exps").exists()  # nothing written


def test_an_import_that_exits_0_writes_a_folder_net_check_accepts(tmp_path, capsys):
    """The fast case of the grid: the defaults on the test grid, without the gridlock trials."""
    rc, out, err = _import("defaults", tmp_path, capsys)
    assert rc == 0, err
    assert check_net_folder(out)[0] == []
    scen = (out / "scenario.toml").read_text()
    assert "feature_count = 64" in scen


def test_a_zone_cell_giving_more_cells_than_the_cap_is_refused(tmp_path, capsys, monkeypatch):
    from couplers.net.importer import regions

    monkeypatch.setattr(regions, "ZONE_CELLS_MAX", 10)  # 200 m cells over the test grid: 5 x 5
    rc, _, err = _import("defaults", tmp_path, capsys)
    assert rc == 2 and len(err) == 1 and "--zone-cell" in err[0] and "more than 10" in err[0], err
    assert not (tmp_path / "nets").exists()
