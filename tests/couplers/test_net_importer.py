"""coloc net import / net check on a small OSM extract written by the test (tests/osmfixture.py)."""

from __future__ import annotations

import json
import shutil
import subprocess
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
from shapely.geometry import LineString, Point
import pytest

sumolib = pytest.importorskip("sumolib")

from couplers.errors import InputError  # noqa: E402
from couplers.net.check import check_net_folder  # noqa: E402
from couplers.net.folder import load_net_folder  # noqa: E402
from couplers.net.importer import ImportOptions, import_net  # noqa: E402
from couplers.net.importer.demand import ARTERIAL_LANE_KM, ARTERIAL_MEAN_ROUTE_M, VTYPE, falling_profile_bins  # noqa: E402
from couplers.net.importer.geometry import _drivable_edges  # noqa: E402
from couplers.publish import MARKER  # noqa: E402
from couplers.net.zones import RegionIndex  # noqa: E402
from osmfixture import DLAT, DLON, LAT0, LON0, _nid, write_osm_grid  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
ARTERIAL = ROOT / "sumo_nets" / "arterial"
CALIB_S = 900.0  # gridlock trials over the peak only: keeps the tests short
FILES = ("tlr.net.xml", "demand.rou.xml", "zones.geojson", "areas.geojson", "features.add.xml", "scenario.toml",
         "buildings.geojson")


@pytest.fixture(scope="module")
def osm(tmp_path_factory) -> Path:
    return write_osm_grid(tmp_path_factory.mktemp("osm") / "grid.osm")


@pytest.fixture(scope="module")
def imported(tmp_path_factory, osm):
    out = tmp_path_factory.mktemp("nets") / "grid"
    res = import_net(ImportOptions(name="grid", out=out, osm=osm, seed=3, calibration_s=CALIB_S))
    return out, res


def _no_leftovers(parent: Path) -> list[str]:
    return sorted(p.name for p in parent.iterdir()) if parent.exists() else []


# --------------------------------------------------------------------------
# the import
# --------------------------------------------------------------------------

def test_osm_import_writes_a_loadable_net_folder(imported):
    out, res = imported
    assert sorted(p.name for p in out.iterdir()) == sorted((*FILES, MARKER))  # MARKER: the manifest
    folder = load_net_folder(out)
    assert folder.tls_off == {"tlr": False, "vsr": True}
    net = sumolib.net.readNet(str(folder.net))
    # the two OSM signals became traffic lights; roads are cars-only
    assert len(net.getTrafficLights()) == 2
    assert all(e.allows("passenger") for e in net.getEdges())
    assert "dated" not in (out / "tlr.net.xml").read_text()[:400]
    assert "generated on" not in (out / "tlr.net.xml").read_text()[:400]
    problems, _ = check_net_folder(out)
    assert problems == []


def test_features_from_signals_bus_stop_car_park_and_signs(imported):
    out, _ = imported
    folder = load_net_folder(out)
    kinds = dict(zip(*np.unique(folder.features.kinds.astype(str), return_counts=True)))
    # 2 signalised junctions with 4 approaches each -> 8 stop-line poles; the OSM stop on a
    # two-way street -> 2 bus stops; 1 car park; signs at the minor approaches
    assert kinds["traffic_light"] == 8
    assert kinds["bus_stop"] == 2
    assert kinds["parking"] == 1
    assert kinds["sign"] >= 4
    xy = folder.features.xy
    d = np.hypot(*(xy[:, None, :] - xy[None, :, :]).transpose(2, 0, 1))
    assert d[np.triu_indices(len(xy), 1)].min() >= 4.0  # no two features on the same spot
    scen = tomllib.loads((out / "scenario.toml").read_text())
    # fewer candidate places than the 64 asked for: said plainly
    assert any("64 features" in s for s in scen["not_derived"]["items"])


def test_zones_follow_building_density(imported):
    out, _ = imported
    folder = load_net_folder(out)
    net = sumolib.net.readNet(str(folder.net))
    zones = RegionIndex(folder.zones)
    # dense buildings fill the blocks around the secondary street north of the primary
    a = np.array(net.getNode(str(_nid(2, 1))).getCoord())
    b = np.array(net.getNode(str(_nid(2, 2))).getCoord())
    dense = zones.names_at(((a + b) / 2)[None, :])[0]
    outskirts = zones.names_at(np.array(net.getNode(str(_nid(1, 0))).getCoord())[None, :])[0]
    assert (dense, outskirts) == ("C", "A")
    scen = tomllib.loads((out / "scenario.toml").read_text())
    assert "building density" in scen["derived"]["zones"]


def test_buildings_from_osm_with_heights_from_tags(imported):
    """polyconvert's footprints in net x/y, height from ``height`` or 3 m a level, none over a lane."""
    out, res = imported
    folder = load_net_folder(out)
    assert len(folder.buildings) == 20  # 18 dense + 2 houses of the extract
    h = folder.buildings.heights
    assert np.sum(h == 18.0) == 18  # building:levels = 6
    assert np.sum(h == 7.5) == 1  # height = "7.5 m"
    assert np.isnan(h).sum() == 1  # the house without tags
    net = sumolib.net.readNet(str(folder.net))
    lanes = [LineString(l.getShape()) for e in net.getEdges() for l in e.getLanes()]
    assert not any(b.intersects(l) for b in folder.buildings.polygons for l in lanes)
    # every footprint lies where the zones put the dense class: the 18 of the two central blocks in C
    zones = RegionIndex(folder.zones)
    cls = zones.names_at(np.array([[p.centroid.x, p.centroid.y] for p in folder.buildings.polygons]))
    assert np.sum(cls == "C") >= 18
    scen = tomllib.loads((out / "scenario.toml").read_text())
    assert scen["files"]["buildings"] == "buildings.geojson"
    assert scen["derived"]["buildings"] == {"footprints": 20, "with_height": 19, "over_lanes_left_out": 0}
    assert any(line.startswith("buildings: 20 footprints") for line in res.lines)


def test_osm_without_buildings_says_so(tmp_path):
    osm = write_osm_grid(tmp_path / "bare.osm", buildings=False)
    out = tmp_path / "bare"
    res = import_net(ImportOptions(name="bare", out=out, osm=osm, seed=3, calibrate=False))
    assert not (out / "buildings.geojson").exists()
    assert load_net_folder(out).buildings is None
    assert "buildings" not in tomllib.loads((out / "scenario.toml").read_text())["files"]
    assert any("buildings.geojson: the extract has no buildings" in line for line in res.lines)


def test_demand_follows_the_falling_profile_and_every_route_exists(imported):
    out, _ = imported
    scen = tomllib.loads((out / "scenario.toml").read_text())
    dem = scen["derived"]["demand"]
    per_bin = dem["vehicles_per_bin"]
    assert len(per_bin) == 12 and all(x >= y for x, y in zip(per_bin, per_bin[1:]))
    expected = falling_profile_bins(2800 * dem["scale"], 1800 * dem["scale"], 3600.0)
    assert per_bin == [int(round(x)) for x in expected]
    assert per_bin[0] / per_bin[-1] == pytest.approx(2758.3 / 1841.7, rel=0.03)
    root = ET.parse(out / "demand.rou.xml").getroot()
    vehicles = root.findall("vehicle")
    assert len(vehicles) == sum(per_bin) == dem["vehicles"]
    departs = [float(v.get("depart")) for v in vehicles]
    assert departs == sorted(departs) and departs[-1] < 3600.0
    net = sumolib.net.readNet(str(out / "tlr.net.xml"))
    for r in root.findall("route"):
        edges = [net.getEdge(e) for e in r.get("edges").split()]
        assert all(b in a.getOutgoing() for a, b in zip(edges, edges[1:]))


def test_reimport_gives_identical_files_and_another_seed_other_demand(tmp_path, osm, imported):
    out, _ = imported
    again = tmp_path / "grid"
    import_net(ImportOptions(name="grid", out=again, osm=osm, seed=3, calibration_s=CALIB_S))
    for name in FILES:
        assert (again / name).read_bytes() == (out / name).read_bytes(), name
    other = tmp_path / "grid7"
    import_net(ImportOptions(name="grid", out=other, osm=osm, seed=7, calibrate=False))
    assert (other / "tlr.net.xml").read_bytes() == (out / "tlr.net.xml").read_bytes()
    assert (other / "demand.rou.xml").read_bytes() != (out / "demand.rou.xml").read_bytes()


def test_net_input_with_user_zones_areas_and_routes(tmp_path, imported):
    """A .net.xml input: re-written by netconvert, the user's GeoJSON and route file taken as given."""
    out, _ = imported
    routes = tmp_path / "mine.rou.xml"
    shutil.copyfile(out / "demand.rou.xml", routes)
    dest = tmp_path / "fromnet"
    res = import_net(ImportOptions(name="fromnet", out=dest, net=out / "tlr.net.xml", zones=out / "zones.geojson",
                                   areas=out / "areas.geojson", routes=routes, seed=3))
    assert (dest / "zones.geojson").read_bytes() == (out / "zones.geojson").read_bytes()
    assert (dest / "demand.rou.xml").read_bytes() == routes.read_bytes()
    scen = tomllib.loads((dest / "scenario.toml").read_text())
    items = " ".join(scen["not_derived"]["items"])
    assert "bus_stop" in items and "parking" in items  # a .net.xml holds no stops: said so
    assert "check it before sharing" in scen["licence"]
    assert check_net_folder(dest)[0] == []
    assert any("user's route file" in line for line in res.lines)


def test_scaling_constants_are_the_shipped_arterials():
    net = sumolib.net.readNet(str(ARTERIAL / "tlr.net.xml"))
    lane_km = sum(e.getLength() * e.getLaneNumber() for e in _drivable_edges(net)) / 1000.0
    assert lane_km == pytest.approx(ARTERIAL_LANE_KM, abs=0.01)
    root = ET.parse(ARTERIAL / "demand.rou.xml").getroot()
    length = {r.get("id"): sum(net.getEdge(e).getLength() for e in r.get("edges").split()) for r in root.iter("route")}
    n = sum(int(f.get("number")) for f in root.iter("flow"))
    mean = sum(int(f.get("number")) * length[f.get("route")] for f in root.iter("flow")) / n
    assert mean == pytest.approx(ARTERIAL_MEAN_ROUTE_M, abs=0.5)
    # imported demand drives the arterial's car
    assert root.find("vType").attrib == VTYPE


# --------------------------------------------------------------------------
# bad inputs: one clear message, nothing left behind
# --------------------------------------------------------------------------

def _expect_error(tmp_path, match: str, **kw) -> InputError:
    parent = tmp_path / "nets"
    parent.mkdir(exist_ok=True)
    before = _no_leftovers(parent)
    with pytest.raises(InputError, match=match) as exc:
        import_net(ImportOptions(name="bad", out=parent / "new" / "bad", **kw))
    assert _no_leftovers(parent) == before  # no folder, no temporary folder, no created parent ("new")
    return exc.value


def test_non_xml_osm_and_net(tmp_path):
    junk = tmp_path / "junk.osm"
    junk.write_bytes(b"\x89PNG\r\n not xml at all")
    err = _expect_error(tmp_path, "not valid XML", osm=junk)
    assert err.path == str(junk)
    junk_net = tmp_path / "junk.net.xml"
    junk_net.write_text("hello")
    _expect_error(tmp_path, "not valid XML", net=junk_net)
    other = tmp_path / "other.osm"
    other.write_text("<routes/>")
    _expect_error(tmp_path, "not an OpenStreetMap file", osm=other)


def test_osm_without_roads(tmp_path):
    osm = write_osm_grid(tmp_path / "paths.osm", roads=False)
    err = _expect_error(tmp_path, "no road open to cars", osm=osm)
    assert err.field == "way[highway]"


def test_net_without_drivable_edges(tmp_path):
    (tmp_path / "f.nod.xml").write_text('<nodes><node id="a" x="0" y="0"/><node id="b" x="200" y="0"/>'
                                        '<node id="c" x="200" y="200"/></nodes>')
    (tmp_path / "f.edg.xml").write_text('<edges><edge id="ab" from="a" to="b" allow="pedestrian"/>'
                                        '<edge id="bc" from="b" to="c" allow="pedestrian bicycle"/></edges>')
    subprocess.run([sumolib.checkBinary("netconvert"), "-n", "f.nod.xml", "-e", "f.edg.xml", "-o", "foot.net.xml",
                    "--no-warnings", "true"], cwd=tmp_path, check=True, capture_output=True)
    _expect_error(tmp_path, "no edge open to passenger cars", net=tmp_path / "foot.net.xml")


def test_net_without_traffic_lights_asks_for_guess_signals(tmp_path):
    osm = write_osm_grid(tmp_path / "nosig.osm", signals=False)
    _expect_error(tmp_path, "--guess-signals", osm=osm)
    out = tmp_path / "guessed"
    res = import_net(ImportOptions(name="guessed", out=out, osm=osm, guess_signals=True, calibrate=False))
    net = sumolib.net.readNet(str(out / "tlr.net.xml"))
    assert len(net.getTrafficLights()) >= 1
    assert tomllib.loads((out / "scenario.toml").read_text())["import"]["guess_signals"] is True
    assert any("guessed by netconvert" in line for line in res.lines)


def _zones_doc(crs: str | None, x0: float, y0: float, x1: float, y1: float, area: bool = False) -> dict:
    props = {"area": "1"} if area else {"zone": "B", "sigma_p": 8.0, "sigma_v": 0.17}
    doc = {"type": "FeatureCollection",
           "features": [{"type": "Feature", "properties": props,
                         "geometry": {"type": "Polygon",
                                      "coordinates": [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]}}]}
    if crs is not None:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    return doc


def test_geojson_in_wrong_crs_or_outside_the_net(tmp_path, osm):
    other = tmp_path / "mercator.geojson"
    other.write_text(json.dumps(_zones_doc("EPSG:3857", 854000, 5630000, 855000, 5631000)))
    err = _expect_error(tmp_path, "'EPSG:3857' is not supported", osm=osm, zones=other)
    assert err.field == "crs"
    assert all(name in err.message for name in ("urn:ogc:def:crs:OGC:1.3:CRS84", "EPSG:4326",
                                                 "urn:ogc:def:crs:EPSG::4326", "urn:coloc:sumo-net-xy"))
    far = tmp_path / "far.geojson"
    far.write_text(json.dumps(_zones_doc("urn:coloc:sumo-net-xy", 1e6, 1e6, 1e6 + 500, 1e6 + 500)))
    _expect_error(tmp_path, "outside the net", osm=osm, zones=far)
    part = tmp_path / "part.geojson"
    part.write_text(json.dumps(_zones_doc("urn:coloc:sumo-net-xy", 0, 0, 100, 100, area=True)))
    _expect_error(tmp_path, "uncovered", osm=osm, areas=part)


# --------------------------------------------------------------------------
# WGS84 (RFC 7946) zones and areas: converted with the net's own projection
# --------------------------------------------------------------------------

def _positions(doc: dict) -> list[list[float]]:
    out = []
    for f in doc["features"]:
        g = f["geometry"]
        for poly in [g["coordinates"]] if g["type"] == "Polygon" else g["coordinates"]:
            for ring in poly:
                out += ring
    return out


def _to_lonlat(doc: dict, net, crs: str | None) -> dict:
    """A net x/y FeatureCollection back in lon/lat (sumolib convertXY2LonLat), with ``crs`` (None: RFC 7946)."""
    doc = json.loads(json.dumps(doc))
    for p in _positions(doc):
        p[:] = list(net.convertXY2LonLat(p[0], p[1]))
    doc.pop("crs", None)
    if crs is not None:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    return doc


def test_lonlat_to_net_xy_matches_sumolib(imported):
    """The vectorised conversion is sumolib's convertLonLat2XY (projection, then netOffset added) to < 1 mm."""
    from couplers.net.georef import lonlat_to_xy, read_georef

    out, _ = imported
    net = sumolib.net.readNet(str(out / "tlr.net.xml"))
    georef = read_georef(out / "tlr.net.xml")
    assert georef.proj == net._location["projParameter"] and georef.proj.startswith("+proj=utm")
    assert georef.net_offset == tuple(net.getLocationOffset())
    rng = np.random.default_rng(0)
    lon, lat = rng.uniform(7.58, 7.79, 2000), rng.uniform(44.97, 45.17, 2000)  # +-10 km about the grid
    x, y = lonlat_to_xy(georef, lon, lat)
    ref = np.array([net.convertLonLat2XY(a, b) for a, b in zip(lon, lat)])
    assert np.abs(x - ref[:, 0]).max() < 1e-3 and np.abs(y - ref[:, 1]).max() < 1e-3
    # an OSM node of the grid lands where netconvert put its junction
    x0, y0 = lonlat_to_xy(georef, [LON0 + 2 * DLON], [LAT0 + 2 * DLAT])
    node = net.getNode(str(_nid(2, 2))).getCoord()
    assert np.hypot(x0[0] - node[0], y0[0] - node[1]) < 0.02


def test_wgs84_zones_and_areas_are_converted_to_net_xy(tmp_path, osm, imported):
    """Zones with crs CRS84 and RFC 7946 areas (no crs), made from the import's own: written back in net x/y."""
    out, _ = imported
    net = sumolib.net.readNet(str(out / "tlr.net.xml"))
    zones = json.loads((out / "zones.geojson").read_text())
    areas = json.loads((out / "areas.geojson").read_text())
    zw, aw = tmp_path / "zones_wgs84.geojson", tmp_path / "areas_rfc7946.geojson"
    zw.write_text(json.dumps(_to_lonlat(zones, net, "urn:ogc:def:crs:OGC:1.3:CRS84")))
    aw.write_text(json.dumps(_to_lonlat(areas, net, None)))
    dest = tmp_path / "wgs"
    res = import_net(ImportOptions(name="wgs", out=dest, osm=osm, zones=zw, areas=aw, routes=out / "demand.rou.xml",
                                   seed=3, calibrate=False))
    for name, orig in (("zones", zones), ("areas", areas)):
        got = json.loads((dest / f"{name}.geojson").read_text())
        assert got["crs"] == {"type": "name", "properties": {"name": "urn:coloc:sumo-net-xy"}}
        assert [f["properties"] for f in got["features"]] == [f["properties"] for f in orig["features"]]
        err = np.abs(np.array(_positions(got)) - np.array(_positions(orig))).max()
        assert err < 1e-3, (name, err)
    scen = tomllib.loads((dest / "scenario.toml").read_text())
    proj = "+proj=utm +zone=32 +ellps=WGS84 +datum=WGS84 +units=m +no_defs"
    assert "converted from WGS84 lon/lat (crs urn:ogc:def:crs:OGC:1.3:CRS84)" in scen["derived"]["zones"]
    assert "converted from WGS84 lon/lat (no crs member, RFC 7946)" in scen["derived"]["areas"]
    for key in ("zones_conversion", "areas_conversion"):
        assert scen["derived"][key]["projection"] == proj
        assert scen["derived"][key]["net_offset"] == list(net.getLocationOffset())
    assert sum(1 for line in res.lines if "converted from WGS84" in line and proj in line) == 2
    assert check_net_folder(dest)[0] == []
    assert load_net_folder(dest).zones[0].name == zones["features"][0]["properties"]["zone"]
    # a geo-referenced .net.xml input (re-written by netconvert, <location> kept): the same net x/y
    dest2 = tmp_path / "wgs_net"
    import_net(ImportOptions(name="wgs_net", out=dest2, net=out / "tlr.net.xml", zones=zw, areas=aw,
                             routes=out / "demand.rou.xml", seed=3, calibrate=False))
    for name in ("zones.geojson", "areas.geojson"):
        assert (dest2 / name).read_bytes() == (dest / name).read_bytes()


def test_wgs84_geojson_errors(tmp_path, osm, imported):
    out, _ = imported
    net = sumolib.net.readNet(str(out / "tlr.net.xml"))
    # metres without the crs marker are read as lon/lat: implausible, and the marker is shown
    metres = tmp_path / "metres.geojson"
    metres.write_text(json.dumps(_zones_doc(None, 0, 0, 800, 700)))
    err = _expect_error(tmp_path, r"\[800, 0\] is not a lon/lat", osm=osm, zones=metres)
    assert err.field == "features[0].geometry.coordinates"
    assert "no crs member, RFC 7946" in err.message and '"name": "urn:coloc:sumo-net-xy"' in err.message
    # lon/lat for a net without geo-reference (the arterial: plain XML nodes/edges)
    lonlat = tmp_path / "lonlat.geojson"
    lonlat.write_text(json.dumps(_to_lonlat(json.loads((out / "zones.geojson").read_text()), net, "EPSG:4326")))
    err = _expect_error(tmp_path, "has no geo-reference", net=ARTERIAL / "tlr.net.xml", zones=lonlat)
    assert err.path == str(lonlat) and err.field == "crs" and 'projParameter="!"' in err.message
    # the checks of net x/y polygons apply after the conversion: elsewhere (Paris), or covering part of the net
    paris = tmp_path / "paris.geojson"
    paris.write_text(json.dumps(_zones_doc(None, 2.34, 48.85, 2.36, 48.86)))
    err = _expect_error(tmp_path, "outside the net", osm=osm, zones=paris)
    assert "check the coordinate order" in err.message
    part = tmp_path / "part_lonlat.geojson"
    part.write_text(json.dumps(_zones_doc(None, 7.6795, 45.0695, 7.6841, 45.0731, area=True)))
    _expect_error(tmp_path, "uncovered", osm=osm, areas=part)


def test_existing_folder_needs_force(tmp_path, osm, imported):
    out, _ = imported
    with pytest.raises(InputError, match="--force"):
        import_net(ImportOptions(name="grid", out=out, osm=osm))


# --------------------------------------------------------------------------
# net check
# --------------------------------------------------------------------------

def test_check_passes_the_shipped_arterial():
    problems, info = check_net_folder(ARTERIAL)
    assert problems == []
    assert "64 features" in info and "316 buildings" in info


def test_check_reports_one_line_per_problem(tmp_path, imported):
    out, _ = imported
    bad = tmp_path / "broken"
    shutil.copytree(out, bad)
    # a feature far from any road
    feats = (bad / "features.add.xml").read_text()
    feats = feats.replace("</additional>", '    <poi id="lost" type="sign" x="5000" y="5000"/>\n</additional>')
    (bad / "features.add.xml").write_text(feats)
    # zones shrunk to a corner
    (bad / "zones.geojson").write_text(json.dumps(_zones_doc("urn:coloc:sumo-net-xy", 0, 0, 50, 50)))
    # a route through an edge that is not in the net
    dem = (bad / "demand.rou.xml").read_text()
    dem = dem.replace("</routes>", '    <vehicle id="ghost" depart="0"><route edges="nowhere"/></vehicle>\n</routes>')
    (bad / "demand.rou.xml").write_text(dem)
    # a building over a lane and one over a feature
    lane_xy = sumolib.net.readNet(str(bad / "tlr.net.xml")).getEdges()[0].getLanes()[0].getShape()[0]
    fxy = load_net_folder(out).features.xy[0]
    doc = json.loads((bad / "buildings.geojson").read_text())
    for x, y in (lane_xy, fxy):
        ring = [[x - 2, y - 2], [x + 2, y - 2], [x + 2, y + 2], [x - 2, y + 2], [x - 2, y - 2]]
        doc["features"].append({"type": "Feature", "properties": {}, "geometry": {"type": "Polygon", "coordinates": [ring]}})
    (bad / "buildings.geojson").write_text(json.dumps(doc))
    problems, _ = check_net_folder(bad)
    assert len(problems) == 6, problems
    # the ghost departs at 0 after vehicles departing later: SUMO would drop it too
    assert any("demand.rou.xml: depart: not sorted by departure: vehicle 'ghost'" in p for p in problems)
    assert any("buildings.geojson" in p and "lane shape points of drivable lanes lie inside buildings" in p
               for p in problems)
    assert any("buildings.geojson" in p and "lies inside building features[21]" in p for p in problems)
    assert any("'lost'" in p and "from the nearest drivable lane" in p for p in problems)
    assert any("zones.geojson" in p and "uncovered" in p for p in problems)
    assert any("'ghost'" in p and "'nowhere' is not in the net" in p for p in problems)


def test_check_refuses_a_folder_geojson_in_lonlat(tmp_path, imported):
    """A folder always holds net x/y: WGS84 belongs to net import, which converts it."""
    out, _ = imported
    bad = tmp_path / "lonlat"
    shutil.copytree(out, bad)
    doc = json.loads((bad / "areas.geojson").read_text())
    doc["crs"]["properties"]["name"] = "urn:ogc:def:crs:OGC:1.3:CRS84"
    (bad / "areas.geojson").write_text(json.dumps(doc))
    problems, _ = check_net_folder(bad)
    assert len(problems) == 1 and "areas.geojson: crs:" in problems[0] and "coloc net import" in problems[0]


def test_check_of_a_folder_that_does_not_load(tmp_path):
    problems, _ = check_net_folder(tmp_path / "missing")
    assert len(problems) == 1 and "not found" in problems[0]


def test_demand_too_high_for_the_net_is_scaled_down_until_no_gridlock(tmp_path, osm):
    """Ten times the density-matched demand jams the grid: the calibration scales it down and says so."""
    out = tmp_path / "jam"
    res = import_net(ImportOptions(name="jam", out=out, osm=osm, seed=3, demand_scale=10.0, calibration_s=600.0))
    scen = tomllib.loads((out / "scenario.toml").read_text())
    dem, cal = scen["derived"]["demand"], scen["derived"]["demand_calibration"]
    assert len(cal["trials"]) >= 2
    assert "no gridlock" not in cal["trials"][0]  # the first trial jammed
    assert cal["trials"][-1].count("no gridlock") == 2  # the last one passed under VSR and TLR
    assert dem["scale"] == pytest.approx(10.0 * dem["density_scale"] * 0.6 ** (len(cal["trials"]) - 1), rel=1e-3)
    assert sum(1 for line in res.lines if "gridlock trial" in line) == len(cal["trials"])


def test_net_input_takes_bus_stops_and_car_parks_from_additionals(tmp_path, imported):
    out, _ = imported
    net = sumolib.net.readNet(str(out / "tlr.net.xml"))
    lane = max((e for e in _drivable_edges(net)), key=lambda e: e.getLength()).getLane(0)
    add = tmp_path / "stops.add.xml"
    add.write_text(f'<additional><busStop id="bs1" lane="{lane.getID()}" startPos="10" endPos="25"/>'
                   f'<parkingArea id="pa1" lane="{lane.getID()}" startPos="-30" endPos="-5"/></additional>')
    dest = tmp_path / "withstops"
    import_net(ImportOptions(name="withstops", out=dest, net=out / "tlr.net.xml", additional=add, calibrate=False))
    folder = load_net_folder(dest)
    kinds = list(folder.features.kinds)
    assert kinds.count("bus_stop") == 1 and kinds.count("parking") == 1
    for kind in ("bus_stop", "parking"):
        xy = folder.features.xy[kinds.index(kind)]
        d = LineString(lane.getShape()).distance(Point(*xy))
        assert lane.getWidth() / 2 < d < lane.getWidth() / 2 + 4.0  # beside the lane, on the sidewalk


def test_feature_count_and_kinds_are_options(tmp_path, osm):
    out = tmp_path / "few"
    import_net(ImportOptions(name="few", out=out, osm=osm, feature_count=5, feature_kinds=("traffic_light",),
                             calibrate=False))
    kinds = list(load_net_folder(out).features.kinds)
    assert kinds == ["traffic_light"] * 5
    with pytest.raises(InputError, match="unknown kind 'tree'"):
        import_net(ImportOptions(name="bad", out=tmp_path / "bad", osm=osm, feature_kinds=("tree",)))
    assert not (tmp_path / "bad").exists()
