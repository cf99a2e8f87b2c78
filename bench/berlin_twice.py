"""Build a stand-in for a real city of about 2000 junctions: the wheel's Berlin OSM net, twice.

No OpenStreetMap extract or SUMO net of a real ~2000-junction city can be had on this
machine (the largest real net shipped on PyPI that we found is the eclipse-sumo wheel's
Berlin extract, ``sumo/tools/game/DRT/osm.net.xml``, 1033 junctions). A random
``netgenerate`` net of 2000 junctions has 853 lane-km, about five times the road length a
real city of that junction count has, and so carries far more demand. This script keeps
real OSM street topology at the target size instead: the Berlin net, a copy of it
shifted east by its width plus ``--gap`` metres with every id prefixed ``b_``, and
two-way single-lane links across the seam, one pair every 300 m of northing between the
easternmost junction of the west copy and the westernmost of the east copy (junctions
with at least two edges). Deterministic: the same inputs give the same bytes.

    python bench/berlin_twice.py --out /tmp/berlin2.net.xml
    python bench/net_import.py --net /tmp/berlin2.net.xml

Not a test; a fixture for ``bench/net_import.py``.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import xml.etree.ElementTree as ET
from pathlib import Path

import sumo  # the eclipse-sumo wheel
import sumolib

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from couplers.net.importer.tools import normalise_header  # noqa: E402

BERLIN = Path(sumo.SUMO_HOME) / "tools" / "game" / "DRT" / "osm.net.xml"
SEAM_STEP_M = 300.0


def _plain(net: Path, prefix: Path, extra: list[str]) -> None:
    subprocess.run([sumolib.checkBinary("netconvert"), "-s", str(net), "--plain-output-prefix", str(prefix),
                    "--no-warnings", *extra], check=True, capture_output=True)


def _junctions(prefix: Path) -> tuple[dict[str, tuple[float, float]], dict[str, int]]:
    xy = {n.get("id"): (float(n.get("x")), float(n.get("y")))
          for n in ET.parse(f"{prefix}.nod.xml").getroot().iter("node")}
    degree: dict[str, int] = {}
    for e in ET.parse(f"{prefix}.edg.xml").getroot().iter("edge"):
        for end in ("from", "to"):
            degree[e.get(end)] = degree.get(e.get(end), 0) + 1
    return xy, degree


def seam_edges(west: Path, east: Path, height: float) -> list[str]:
    """Two-way links between the copies, one pair per SEAM_STEP_M band of northing."""
    (wxy, wdeg), (exy, edeg) = _junctions(west), _junctions(east)
    out = []
    for band, y0 in enumerate(range(int(SEAM_STEP_M / 2), int(height), int(SEAM_STEP_M))):
        w = [(x, n) for n, (x, y) in wxy.items() if abs(y - y0) < SEAM_STEP_M / 2 and wdeg.get(n, 0) >= 2]
        e = [(x, n) for n, (x, y) in exy.items() if abs(y - y0) < SEAM_STEP_M / 2 and edeg.get(n, 0) >= 2]
        if w and e:
            a, b = max(w)[1], min(e)[1]
            for k, (f, t) in enumerate(((a, b), (b, a))):
                out.append(f'    <edge id="seam{band}_{k}" from="{f}" to="{t}" priority="7" numLanes="1" '
                           f'speed="13.89"/>')
    return out


def build(out: Path, source: Path = BERLIN, gap: float = 100.0) -> None:
    boundary = sumolib.net.readNet(str(source)).getBoundary()  # xmin, ymin, xmax, ymax
    width, height = boundary[2] - boundary[0], boundary[3] - boundary[1]
    with tempfile.TemporaryDirectory() as tmp:
        west, east = Path(tmp) / "w", Path(tmp) / "e"
        _plain(source, west, [])
        _plain(source, east, ["--prefix", "b_", "--offset.x", f"{width + gap:.2f}"])
        seam = Path(tmp) / "seam.edg.xml"
        seam.write_text("<edges>\n" + "\n".join(seam_edges(west, east, height)) + "\n</edges>\n")
        subprocess.run([sumolib.checkBinary("netconvert"), "-n", f"{west}.nod.xml,{east}.nod.xml",
                        "-e", f"{west}.edg.xml,{east}.edg.xml,{seam}", "-x", f"{west}.con.xml,{east}.con.xml",
                        "-i", f"{west}.tll.xml,{east}.tll.xml", "-t", f"{west}.typ.xml", "-o", str(out),
                        "--no-warnings"], check=True, capture_output=True)
    # netconvert's header comment holds the date and the temporary paths
    out.write_text(normalise_header(out.read_text(), "built by bench/berlin_twice.py"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True, help="net file to write")
    ap.add_argument("--gap", type=float, default=100.0, help="metres between the two copies")
    args = ap.parse_args(argv)
    build(Path(args.out), gap=args.gap)
    net = sumolib.net.readNet(args.out)
    drivable = [e for e in net.getEdges() if e.allows("passenger")]
    print(f"{args.out}: {len(net.getNodes())} junctions, {len(drivable)} drivable edges, "
          f"{len(net.getTrafficLights())} traffic lights")
    return 0


if __name__ == "__main__":
    sys.exit(main())
