"""Tests for sumo_nets/arterial_ped (tools/make_arterial_ped.py): the arterial with sidewalks,
signalised pedestrian crossings and walkers."""

from __future__ import annotations

import shutil
import subprocess
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

sumolib = pytest.importorskip("sumolib")

from couplers.net.build import NET_NAME, build_net  # noqa: E402
from couplers.net.check import check_net_folder  # noqa: E402
from couplers.net.folder import load_net_folder  # noqa: E402
from tests.scriptload import load_script  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
FOLDER = ROOT / "sumo_nets" / "arterial_ped"
ARTERIAL = ROOT / "sumo_nets" / "arterial"
SHARED = ("arterial.nod.xml", "arterial.edg.xml", "arterial.con.xml", "demand.rou.xml", "zones.geojson",
          "areas.geojson", "features.add.xml")


@pytest.fixture(scope="module")
def net():
    return sumolib.net.readNet(str(FOLDER / NET_NAME), withPrograms=True, withPedestrianConnections=True)


def test_folder_loads_and_net_check_passes():
    folder = load_net_folder(FOLDER)
    assert folder.persons == (FOLDER / "pedestrians.rou.xml").resolve()
    assert sorted(folder.tls_off) == ["tlr"]
    problems, info = check_net_folder(FOLDER)
    assert problems == [], problems
    assert "40 person flows" in info
    # the paper's arterial has no persons
    assert load_net_folder(ARTERIAL).persons is None


def test_same_sources_demand_and_data_as_the_arterial():
    for name in SHARED:
        assert (FOLDER / name).read_bytes() == (ARTERIAL / name).read_bytes(), name


def test_sidewalks_crossings_and_pedestrian_signals(net):
    scen = tomllib.loads((FOLDER / "scenario.toml").read_text())
    for e in net.getEdges(withInternal=False):
        if e.getFunction():
            continue
        lanes = e.getLanes()
        assert lanes[0].allows("pedestrian") and not lanes[0].allows("passenger"), e.getID()
        assert all(not ln.allows("pedestrian") for ln in lanes[1:]), e.getID()
    root = ET.parse(FOLDER / NET_NAME).getroot()
    crossings = [e for e in root.iter("edge") if e.get("function") == "crossing"]
    at = {e.get("id").split("_")[0].lstrip(":") for e in crossings}
    assert set(scen["derived"]["traffic_lights"]) <= at
    for tl in net.getTrafficLights():
        (program,) = tl.getPrograms().values()
        phases = program.getPhases()
        assert sum(p.duration for p in phases) == pytest.approx(75.0)
        n_links = len(phases[0].state)
        veh = {c[2] for c in tl.getConnections() if not c[0].getEdge().getID().startswith(":")}
        assert len(veh) < n_links  # pedestrian signals are part of the program
        # every vehicle stream keeps the arterial's green (35 s arterial, 28 s side road)
        greens = sorted({sum(p.duration for p in phases if p.state[i] in "Gg") for i in veh})
        assert greens == [28.0, 35.0], (tl.getID(), greens)


def test_rebuild_is_byte_identical(tmp_path):
    copy = tmp_path / "arterial_ped"
    shutil.copytree(FOLDER, copy)
    (copy / NET_NAME).unlink()
    assert build_net(copy).read_bytes() == (FOLDER / NET_NAME).read_bytes()


def test_generator_reproduces_the_folder(tmp_path):
    gen = load_script("tools/make_arterial_ped.py")
    out = tmp_path / "gen"
    assert gen.main(["--out", str(out)]) == 0
    for p in sorted(FOLDER.iterdir()):
        assert (out / p.name).read_bytes() == p.read_bytes(), p.name


def test_short_run_with_pedestrians(tmp_path):
    cmd = [sumolib.checkBinary("sumo"), "-n", str(FOLDER / NET_NAME),
           "-r", f"{FOLDER / 'demand.rou.xml'},{FOLDER / 'pedestrians.rou.xml'}",
           "--step-length", "0.75", "--seed", "1", "--end", "600", "--no-step-log", "true",
           "--duration-log.disable", "true", "--no-warnings", "true",
           "--statistic-output", str(tmp_path / "stat.xml"), "--person-summary-output", str(tmp_path / "p.xml")]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    stat = ET.parse(tmp_path / "stat.xml").getroot()
    assert int(stat.find("teleports").get("total")) == 0
    assert int(stat.find("safety").get("collisions")) == 0
    assert int(stat.find("personTeleports").get("total")) == 0
    steps = list(ET.parse(tmp_path / "p.xml").getroot().iter("step"))
    assert int(steps[-1].get("arrived")) > 100  # walkers cross and leave
