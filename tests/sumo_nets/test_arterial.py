"""Tests for the sumo_nets/arterial net folder (written by tools/make_arterial.py)."""

from __future__ import annotations

import json
import shutil
import subprocess
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

sumolib = pytest.importorskip("sumolib")
shapely_geometry = pytest.importorskip("shapely.geometry")
from shapely.geometry import LineString, Point, shape  # noqa: E402

from couplers.net.build import CONFIG_NAME, NET_NAME, NetBuildError, build_net  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
FOLDER = ROOT / "sumo_nets" / "arterial"
STEP = "0.75"


@pytest.fixture(scope="module")
def net():
    return sumolib.net.readNet(str(FOLDER / NET_NAME), withPrograms=True)


@pytest.fixture(scope="module")
def net_internal():
    return sumolib.net.readNet(str(FOLDER / NET_NAME), withInternal=True)


@pytest.fixture(scope="module")
def scenario():
    with open(FOLDER / "scenario.toml", "rb") as fh:
        return tomllib.load(fh)


@pytest.fixture(scope="module")
def lane_points(net_internal):
    pts = []
    for edge in net_internal.getEdges(withInternal=True):
        for lane in edge.getLanes():
            pts.extend(lane.getShape())
    return pts


def _polygons(name):
    doc = json.loads((FOLDER / name).read_text())
    assert doc["type"] == "FeatureCollection"
    assert doc["crs"]["properties"]["name"] == "urn:coloc:sumo-net-xy"
    return [(f["properties"], shape(f["geometry"])) for f in doc["features"]]


# --------------------------------------------------------------------------
# net structure
# --------------------------------------------------------------------------

def test_scenario_lists_existing_files(scenario):
    assert scenario["name"] == "arterial"
    for key in ("net", "routes", "zones", "areas", "features", "buildings"):
        assert (FOLDER / scenario["files"][key]).is_file(), key
    assert scenario["controls"]["tlr"]["tls_off"] is False
    assert scenario["controls"]["vsr"]["tls_off"] is True
    assert scenario["sumo"]["step_length"] == 0.75
    assert scenario["sumo"]["end"] == 3600


def test_arterial_geometry(net):
    east = [e for e in net.getEdges() if e.getID().startswith("ae")]
    west = [e for e in net.getEdges() if e.getID().startswith("aw")]
    assert east and west
    for edges in (east, west):
        assert all(e.getLaneNumber() == 2 for e in edges)
        assert all(abs(e.getSpeed() - 13.89) < 0.01 for e in edges)
        length = sum(e.getLength() for e in edges)
        assert 1800 < length < 2200, length
    xs = [x for e in east for x, _ in e.getShape()]
    assert min(xs) == pytest.approx(0.0, abs=1.0)
    assert max(xs) == pytest.approx(2000.0, abs=1.0)
    # coordinates are those written in the sources (no offset normalisation)
    assert list(net.getLocationOffset()) == [0.0, 0.0]
    assert net.getNode("JP2").getCoord() == pytest.approx((1020.0, 0.0))


def test_junctions(net, scenario):
    tls = sorted(t.getID() for t in net.getTrafficLights())
    assert len(tls) == 5
    assert tls == sorted(scenario["derived"]["traffic_lights"])
    prim = scenario["derived"]["primary_crossings"]
    sec = scenario["derived"]["secondary_crossings"]
    assert len(prim) >= 3 and len(sec) >= 4
    for j in prim + sec:
        node = net.getNode(j)
        assert len(node.getIncoming()) == 4 and len(node.getOutgoing()) == 4, j
    for j in prim:
        assert net.getNode(j).getType() == "traffic_light"
        assert all(e.getLaneNumber() == 2 for e in net.getNode(j).getIncoming())
    for j in scenario["derived"]["priority_junctions"]:
        assert net.getNode(j).getType() == "priority"
    # priorities: arterial > primary > secondary
    assert net.getEdge("ae1").getPriority() > net.getEdge("P1n_in").getPriority() > net.getEdge("S1n_in").getPriority()


def test_left_turns_from_arterial_at_main_junctions(net, scenario):
    for j in scenario["derived"]["traffic_lights"]:
        node = net.getNode(j)
        for inc in node.getIncoming():
            if not inc.getID().startswith(("ae", "aw")):
                continue
            dirs = {conn.getDirection() for conns in inc.getOutgoing().values() for conn in conns}
            assert "l" in dirs and "r" in dirs and "s" in dirs, (j, inc.getID(), dirs)


def test_signal_programs_favour_arterial(net):
    for tl in net.getTrafficLights():
        (program,) = tl.getPrograms().values()
        phases = program.getPhases()
        assert sum(p.duration for p in phases) == pytest.approx(75.0)
        greens = sorted((p.duration for p in phases if "G" in p.state), reverse=True)
        assert greens[0] > greens[-1]


def test_rebuild_is_byte_identical(tmp_path):
    copy = tmp_path / "arterial"
    shutil.copytree(FOLDER, copy)
    (copy / NET_NAME).unlink()
    out = build_net(copy)
    assert out == copy / NET_NAME
    assert out.read_bytes() == (FOLDER / NET_NAME).read_bytes()
    assert b"generated on" not in out.read_bytes()[:2000]
    assert str(tmp_path).encode() not in out.read_bytes()


def test_build_errors_name_the_file(tmp_path):
    with pytest.raises(NetBuildError, match=CONFIG_NAME):
        build_net(tmp_path)
    shutil.copy(FOLDER / CONFIG_NAME, tmp_path / CONFIG_NAME)
    (tmp_path / "arterial.nod.xml").write_text("<nodes><node id='a'</nodes>")
    with pytest.raises(NetBuildError, match=CONFIG_NAME):
        build_net(tmp_path)
    assert not (tmp_path / NET_NAME).exists()
    assert not list(tmp_path.glob(".netbuild-*"))


# --------------------------------------------------------------------------
# zones, areas, features
# --------------------------------------------------------------------------

def _assert_partition(polys, points):
    for a in range(len(polys)):
        for b in range(a + 1, len(polys)):
            assert polys[a].intersection(polys[b]).area < 1e-6
    for x, y in points:
        p = Point(x, y)
        n = sum(1 for poly in polys if poly.contains(p))
        assert n == 1, (x, y, n)


def test_zones_partition_the_net(net, lane_points):
    zones = _polygons("zones.geojson")
    params = {"A": (3.0, 0.1), "B": (8.0, 0.17), "C": (15.0, 0.45)}
    names = set()
    for props, poly in zones:
        assert poly.is_valid and poly.geom_type == "Polygon"
        assert (props["sigma_p"], props["sigma_v"]) == params[props["zone"]]
        names.add(props["zone"])
    assert names == {"A", "B", "C"}
    _assert_partition([p for _, p in zones], lane_points)
    # the union covers the net bounding box with a margin
    xmin, ymin, xmax, ymax = net.getBBoxXY()[0] + net.getBBoxXY()[1]
    from shapely.ops import unary_union
    from shapely.geometry import box
    assert unary_union([p for _, p in zones]).contains(box(xmin - 10, ymin - 10, xmax + 10, ymax + 10))
    # outer zones at both ends are A, centre is C
    by_x = sorted(zones, key=lambda z: z[1].centroid.x)
    assert by_x[0][0]["zone"] == by_x[-1][0]["zone"] == "A"
    assert [z for z, _ in by_x if z["zone"] == "C"]


def test_areas_partition_the_net(lane_points):
    areas = _polygons("areas.geojson")
    assert sorted(a["area"] for a, _ in areas) == ["1", "2", "3", "4", "5", "6"]
    _assert_partition([p for _, p in areas], lane_points)
    zones = _polygons("zones.geojson")

    def zone_of(poly):
        best = max(zones, key=lambda z: z[1].intersection(poly).area)
        return best[0]["zone"]

    named = {a["area"]: p for a, p in areas}
    assert zone_of(named["1"]) == zone_of(named["6"]) == "A"
    assert zone_of(named["4"]) == zone_of(named["5"]) == "C"


def test_features(net):
    root = ET.parse(FOLDER / "features.add.xml").getroot()
    pois = list(root.iter("poi"))
    assert len(pois) == 64
    assert len({p.get("id") for p in pois}) == 64
    types = {p.get("type") for p in pois}
    assert types == {"bus_stop", "traffic_light", "sign", "parking"}
    lanes = [LineString(lane.getShape()) for e in net.getEdges() for lane in e.getLanes()]
    for p in pois:
        pt = Point(float(p.get("x")), float(p.get("y")))
        d = min(ls.distance(pt) for ls in lanes)
        assert d <= 15.0, (p.get("id"), d)
        assert d >= 1.6, (p.get("id"), d)  # not on the carriageway centre line of a lane
    centre = [p for p in pois if 850 <= float(p.get("x")) < 1550]
    assert len(centre) / 700 > len(pois) / 2000  # denser in the centre


# --------------------------------------------------------------------------
# demand
# --------------------------------------------------------------------------

def test_routes_are_connected(net):
    root = ET.parse(FOLDER / "demand.rou.xml").getroot()
    routes = {r.get("id"): r.get("edges").split() for r in root.iter("route")}
    assert routes
    for rid, edges in routes.items():
        for a, b in zip(edges, edges[1:]):
            assert net.getEdge(b) in net.getEdge(a).getOutgoing(), (rid, a, b)
    vtypes = list(root.iter("vType"))
    assert [v.get("id") for v in vtypes] == ["car"]
    v = vtypes[0].attrib
    assert (v["accel"], v["decel"], v["sigma"], v["tau"], v["length"], v["minGap"], v["maxSpeed"]) == (
        "2.6", "4.5", "0.5", "1.0", "4.5", "2.5", "15")
    flows = list(root.iter("flow"))
    assert all(f.get("route") in routes for f in flows)
    # hourly demand falls from ~2800 to ~1800 veh/h in 5-min bins
    per_bin = [0] * 12
    for f in flows:
        per_bin[int(float(f.get("begin")) // 300)] += int(f.get("number"))
        period = (float(f.get("end")) - float(f.get("begin"))) / int(f.get("number"))
        last = float(f.get("begin")) + (int(f.get("number")) - 1) * period
        assert last < (int(float(f.get("begin")) // 300) + 1) * 300
    assert 2650 <= per_bin[0] * 12 <= 2850
    assert 1750 <= per_bin[-1] * 12 <= 1950
    assert all(a >= b for a, b in zip(per_bin, per_bin[1:]))


# --------------------------------------------------------------------------
# SUMO runs
# --------------------------------------------------------------------------

def _run(tmp_path: Path, control: str, end: int) -> dict:
    out = tmp_path / control
    out.mkdir()
    cmd = [sumolib.checkBinary("sumo"), "-n", str(FOLDER / NET_NAME), "-r", str(FOLDER / "demand.rou.xml"),
           "--step-length", STEP, "--seed", "1", "--end", str(end),
           "--no-step-log", "true", "--duration-log.disable", "true", "--no-warnings", "true",
           "--summary-output", str(out / "summary.xml"), "--statistic-output", str(out / "stat.xml")]
    if control == "vsr":
        cmd += ["--tls.all-off", "true"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    steps = [s.attrib for s in ET.parse(out / "summary.xml").getroot().iter("step")]
    stat = ET.parse(out / "stat.xml").getroot()
    n = len(steps)
    return {
        "arrived": int(steps[-1]["arrived"]),
        "loaded": int(stat.find("vehicles").get("loaded")),
        "teleports": int(stat.find("teleports").get("total")),
        "collisions": int(stat.find("safety").get("collisions")),
        "mean_running": sum(int(s["running"]) for s in steps) / n,
        "mean_halting": sum(int(s["halting"]) for s in steps) / n,
        "backlog_end": int(steps[-1]["waiting"]),
    }


@pytest.mark.parametrize("control", ["tlr", "vsr"])
def test_short_run(tmp_path, control):
    r = _run(tmp_path, control, 600)
    assert r["arrived"] > 300
    assert r["teleports"] == 0
    assert r["collisions"] == 0


@pytest.mark.slow
def test_full_hour_tlr_queues_more_than_vsr(tmp_path):
    tlr = _run(tmp_path, "tlr", 3600)
    vsr = _run(tmp_path, "vsr", 3600)
    for r in (tlr, vsr):
        assert r["teleports"] <= 0.01 * r["loaded"]
        assert r["backlog_end"] < 10  # no gridlock: vehicles keep entering
        assert r["arrived"] > 0.9 * r["loaded"]
    assert tlr["mean_running"] > 1.2 * vsr["mean_running"]
    assert tlr["mean_halting"] > 15
    assert vsr["mean_halting"] < 3
    assert tlr["mean_halting"] > 5 * vsr["mean_halting"]


# --------------------------------------------------------------------------
# buildings (the occluders of the realistic perception)
# --------------------------------------------------------------------------

def test_buildings_keep_off_lanes_and_features(net_internal):
    from couplers.net.folder import load_net_folder

    folder = load_net_folder(FOLDER)
    b = folder.buildings
    assert b is not None and len(b) > 200
    assert (b.heights >= 6.0).all()
    from shapely import union_all
    built = union_all(list(b.polygons))
    # plots never overlap: the union's area is the sum of the footprints
    assert built.area == pytest.approx(sum(p.area for p in b.polygons), rel=1e-9)
    for edge in net_internal.getEdges(withInternal=True):
        for lane in edge.getLanes():
            line = LineString(lane.getShape()) if len(lane.getShape()) > 1 else Point(lane.getShape()[0])
            assert built.distance(line) >= lane.getWidth() / 2 + 1.5 - 0.02, lane.getID()
    for x, y in folder.features.xy:
        assert built.distance(Point(x, y)) >= 3.0 - 0.02


def test_buildings_denser_and_taller_where_gnss_is_class_c():
    """Plan-area fraction within 50 m of the arterial's axis (the NLOS GNSS density of
    couplers.sensing.gnss_error) and mean height, by the GNSS class of the zone strip."""
    import numpy as np

    from couplers.sensing.gnss_error import building_density_grid
    from couplers.net.folder import load_net_folder
    from couplers.net.zones import RegionIndex

    folder = load_net_folder(FOLDER)
    grid = building_density_grid(folder.buildings, 50.0)
    xy = np.c_[np.arange(0.0, 2000.0, 5.0), np.full(400, 3.2)]
    zone = RegionIndex(folder.zones).names_at(xy)
    dens = {z: grid.at(xy[zone == z]).mean() for z in ("A", "B", "C")}
    assert dens["C"] > 0.3 > dens["B"] > 0.1 > dens["A"] > 0.0, dens
    cls = RegionIndex(folder.zones).names_at(np.array([[p.centroid.x, p.centroid.y] for p in folder.buildings.polygons]))
    h = {z: folder.buildings.heights[cls == z].mean() for z in ("A", "B", "C")}
    assert h["C"] > h["B"] > h["A"], h


def test_buildings_are_regenerated_byte_identical(tmp_path):
    import sys

    sys.path.insert(0, str(ROOT / "tools"))
    try:
        import make_arterial
    finally:
        sys.path.pop(0)
    copy = tmp_path / "arterial"
    shutil.copytree(FOLDER, copy)
    (copy / "buildings.geojson").unlink()
    make_arterial.write_buildings(copy)
    assert (copy / "buildings.geojson").read_bytes() == (FOLDER / "buildings.geojson").read_bytes()
