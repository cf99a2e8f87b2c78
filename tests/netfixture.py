"""A small net folder built by the tests themselves: a signalised cross of 2 x 400 m roads."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import sumolib

NODES = """<nodes>
  <node id="C" x="0" y="0" type="traffic_light"/>
  <node id="W" x="-400" y="0"/> <node id="E" x="400" y="0"/>
  <node id="S" x="0" y="-400"/> <node id="N" x="0" y="400"/>
</nodes>"""
EDGES = """<edges>
  <edge id="WC" from="W" to="C" numLanes="2" speed="13.89" priority="3"/>
  <edge id="CE" from="C" to="E" numLanes="2" speed="13.89" priority="3"/>
  <edge id="EC" from="E" to="C" numLanes="2" speed="13.89" priority="3"/>
  <edge id="CW" from="C" to="W" numLanes="2" speed="13.89" priority="3"/>
  <edge id="SC" from="S" to="C" numLanes="1" speed="13.89" priority="1"/>
  <edge id="CN" from="C" to="N" numLanes="1" speed="13.89" priority="1"/>
  <edge id="NC" from="N" to="C" numLanes="1" speed="13.89" priority="1"/>
  <edge id="CS" from="C" to="S" numLanes="1" speed="13.89" priority="1"/>
</edges>"""
ROUTES = """<routes>
  <vType id="car" accel="2.6" decel="4.5" sigma="0.5" length="4.5" minGap="2.5" maxSpeed="15"/>
  <route id="we" edges="WC CE"/> <route id="ew" edges="EC CW"/>
  <route id="sn" edges="SC CN"/> <route id="ws" edges="WC CS"/>
  <flow id="f_we" type="car" route="we" begin="0" end="{end}" period="6" departLane="best" departSpeed="max"/>
  <flow id="f_ew" type="car" route="ew" begin="0" end="{end}" period="7" departLane="best" departSpeed="max"/>
  <flow id="f_sn" type="car" route="sn" begin="0" end="{end}" period="15" departLane="best" departSpeed="max"/>
  <flow id="f_ws" type="car" route="ws" begin="0" end="{end}" period="20" departLane="best" departSpeed="max"/>
</routes>"""
FEATURES = """<additional>
{pois}
</additional>"""


def _square(x0, y0, x1, y1):
    return [[[x0, y0], [x1, y0], [x1, y1], [x0, y1], [x0, y0]]]


def _collection(items):
    return {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": "urn:coloc:sumo-net-xy"}},
        "features": [{"type": "Feature", "properties": p, "geometry": {"type": "Polygon", "coordinates": c}} for p, c in items],
    }


def build_cross_net(folder: Path, end: float = 600.0) -> Path:
    """Write and build the net folder; returns it."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cross.nod.xml").write_text(NODES)
    (folder / "cross.edg.xml").write_text(EDGES)
    subprocess.run(
        [
            sumolib.checkBinary("netconvert"), "-n", "cross.nod.xml", "-e", "cross.edg.xml",
            "-o", "tlr.net.xml", "--offset.disable-normalization", "true", "--no-warnings", "true",
        ],
        cwd=folder, check=True, capture_output=True,
    )
    (folder / "demand.rou.xml").write_text(ROUTES.format(end=end))
    # Zones: west half A (3 m), east half C (15 m); areas: four quadrants.
    zones = [
        ({"zone": "A", "sigma_p": 3.0, "sigma_v": 0.1}, _square(-500, -500, 0, 500)),
        ({"zone": "C", "sigma_p": 15.0, "sigma_v": 0.45}, _square(0, -500, 500, 500)),
    ]
    areas = [
        ({"area": "1"}, _square(-500, -500, 0, 0)),
        ({"area": "2"}, _square(-500, 0, 0, 500)),
        ({"area": "3"}, _square(0, 0, 500, 500)),
        ({"area": "4"}, _square(0, -500, 500, 0)),
    ]
    (folder / "zones.geojson").write_text(json.dumps(_collection(zones)))
    (folder / "areas.geojson").write_text(json.dumps(_collection(areas)))
    pois = []
    for i, x in enumerate(range(-350, 351, 50)):
        pois.append(f'  <poi id="f{i}" type="sign" x="{x}.0" y="12.0" color="red"/>')
    pois.append('  <poi id="corner" type="traffic_light" x="10.0" y="-10.0" color="red"/>')
    (folder / "features.add.xml").write_text(FEATURES.format(pois="\n".join(pois)))
    (folder / "scenario.toml").write_text(
        'name = "cross"\ndescription = "test cross"\n'
        '[files]\nnet = "tlr.net.xml"\nroutes = "demand.rou.xml"\nzones = "zones.geojson"\n'
        'areas = "areas.geojson"\nfeatures = "features.add.xml"\n'
        "[controls]\ntlr = { tls_off = false }\nvsr = { tls_off = true }\n"
    )
    return folder


def arterial_config(extra: str = "") -> dict:
    """experiments/arterial_tlr.toml as a dict, its net folder made absolute, with the TOML tables of
    ``extra`` added (replacing tables of the same name)."""
    import tomllib

    root = Path(__file__).resolve().parents[1]
    base = tomllib.loads((root / "experiments" / "arterial_tlr.toml").read_text())
    base["scenario"]["net_dir"] = str(root / "sumo_nets" / "arterial")
    base.update(tomllib.loads(extra))
    return base
