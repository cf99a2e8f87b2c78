"""The inputs of ``coloc net import``: the OSM extract or SUMO net checked, and netconvert's net."""

from __future__ import annotations

import gzip
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

from couplers.errors import InputError
from couplers.net.importer.tools import _binary, _run, _sumo_home, normalise_header

if TYPE_CHECKING:
    from couplers.net.importer import ImportOptions, _Report

# OSM highway values netconvert's osmNetconvert typemap opens to passenger cars.
CAR_HIGHWAYS = frozenset({
    "motorway", "motorway_link", "trunk", "trunk_link", "primary", "primary_link", "secondary",
    "secondary_link", "tertiary", "tertiary_link", "unclassified", "residential", "living_street",
    "service", "road",
})


# --------------------------------------------------------------------------
# Inputs
# --------------------------------------------------------------------------

def _open_xml(path: Path):
    if path.suffix == ".gz":
        return gzip.open(path, "rb")
    return open(path, "rb")


def scan_osm(path: Path) -> dict:
    """Count car roads, signals, buildings, bus stops and car parks of an OSM extract.

    Raises :class:`InputError` when the file is missing, not XML, not OSM, or has
    no road open to cars.
    """
    counts = {"car_roads": 0, "signals": 0, "buildings": 0, "bus_stops": 0, "parking": 0}
    try:
        with _open_xml(path) as fh:
            it = ET.iterparse(fh, events=("start", "end"))
            _, root = next(it)
            if root.tag != "osm":
                raise InputError(path, None, f"not an OpenStreetMap file (root element <{root.tag}>, expected <osm>)")
            for event, elem in it:
                if event != "end" or elem.tag not in ("node", "way", "relation"):
                    continue
                tags = {t.get("k"): t.get("v") for t in elem.iter("tag")}
                if elem.tag == "way":
                    if tags.get("highway") in CAR_HIGHWAYS:
                        counts["car_roads"] += 1
                    if "building" in tags:
                        counts["buildings"] += 1
                if tags.get("highway") == "traffic_signals":
                    counts["signals"] += 1
                if tags.get("highway") == "bus_stop" or (tags.get("public_transport") == "stop_position" and tags.get("bus") == "yes"):
                    counts["bus_stops"] += 1
                if tags.get("amenity") == "parking":
                    counts["parking"] += 1
                elem.clear()
                root.clear()
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (ET.ParseError, EOFError, OSError, StopIteration) as exc:
        raise InputError(path, None, f"not valid XML ({exc or 'empty file'})") from None
    if counts["car_roads"] == 0:
        raise InputError(path, "way[highway]",
                         "the extract has no road open to cars (no way tagged highway="
                         "motorway/trunk/primary/secondary/tertiary/unclassified/residential/service/...)")
    return counts


def _check_net_xml(path: Path) -> None:
    try:
        with _open_xml(path) as fh:
            for _event, elem in ET.iterparse(fh, events=("start",)):
                if elem.tag != "net":
                    raise InputError(path, None, f"not a SUMO net (root element <{elem.tag}>, expected <net>)")
                break
            else:
                raise InputError(path, None, "not valid XML (empty file)")
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (ET.ParseError, EOFError, OSError) as exc:
        raise InputError(path, None, f"not valid XML ({exc})") from None


def _netconvert(opts: ImportOptions, work: Path, report: _Report) -> Path:
    """Write ``work/tlr.net.xml`` (and ``work/.stops.add.xml`` from OSM)."""
    src = opts.source.resolve()
    out = work / "tlr.net.xml"
    cmd = [_binary("netconvert")]
    if opts.osm is not None:
        typemaps = _sumo_home() / "data" / "typemap"
        cmd += [
            # osmWebWizard's "urban" typemaps: roads without a maxspeed tag get urban speeds
            # (primary/secondary/tertiary 50 km/h instead of the rural 100/100/80 km/h)
            "--osm-files", str(src), "--type-files",
            f"{typemaps / 'osmNetconvert.typ.xml'},{typemaps / 'osmNetconvertUrbanDe.typ.xml'}",
            # SUMO's recommended OSM import (docs/architecture.md "SUMO notes")
            "--geometry.remove", "true", "--ramps.guess", "true", "--junctions.join", "true",
            "--tls.guess-signals", "true", "--tls.discard-simple", "true", "--tls.join", "true",
            "--roundabouts.guess", "true",
            # cars only: coloc simulates passenger cars
            "--keep-edges.by-vclass", "passenger", "--remove-edges.isolated", "true",
            "--output.street-names", "true", "--ptstop-output", ".stops.add.xml",
        ]
    else:
        cmd += ["--sumo-net-file", str(src), "--offset.disable-normalization", "true"]
    if opts.guess_signals:
        cmd += ["--tls.guess", "true"]
    if opts.signals == "rebuild":  # netconvert's static programs: 90 s cycle, every approach served
        cmd += ["--tls.rebuild", "true", "--tls.default-type", "static"]
    cmd += ["--output-file", out.name, "--no-warnings", "true", "--xml-validation", "never"]
    _run(cmd, work, opts.source, "netconvert")
    if not out.is_file() or out.stat().st_size == 0:
        raise InputError(opts.source, None, "netconvert wrote no net")
    text = out.read_text(encoding="utf-8")
    out.write_text(normalise_header(text, f"built by coloc net import from {opts.source.name}"),
                   encoding="utf-8", newline="\n")
    home = str(_sumo_home())
    report.derived["netconvert"] = " ".join(
        opts.source.name if a == str(src) else ",".join(Path(x).name for x in a.split(",")) if a.startswith(home)
        else "stops.add.xml(read,not-kept)" if a.startswith(".stops") else a for a in cmd[1:])
    return out
