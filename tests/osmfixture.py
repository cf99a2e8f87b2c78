"""A small OpenStreetMap extract written by the tests themselves.

A 5 x 4 street grid near Turin (45.07 N, 7.68 E; about 160 m between
streets): a two-lane primary street along the middle row, a secondary street
down the middle column, residential streets elsewhere; traffic signals where
the primary crosses the secondary and the next column east; a bus stop on the
primary; dense buildings in the two central blocks, a few sparse ones on the
outskirts; one car park. Hand-written data (no third-party licence).
"""

from __future__ import annotations

from pathlib import Path

LAT0, LON0 = 45.0700, 7.6800
DLAT, DLON = 0.0015, 0.0020  # ~167 m, ~157 m
COLS, ROWS = 5, 4
PRIMARY_ROW = 1
SECONDARY_COL = 2
SIGNALS = [(2, 1), (3, 1)]  # (col, row) of signalised crossings


def _nid(c: int, r: int) -> int:
    return 1 + r * COLS + c


def osm_grid(*, roads: bool = True, buildings: bool = True, signals: bool = True, bus_stop: bool = True) -> str:
    """The extract as OSM XML text; switches leave parts out for the bad-input tests."""
    nodes: list[str] = []
    ways: list[str] = []
    for r in range(ROWS):
        for c in range(COLS):
            tags = ""
            if signals and (c, r) in SIGNALS:
                tags = '<tag k="highway" v="traffic_signals"/>'
            nodes.append(f'  <node id="{_nid(c, r)}" version="1" lat="{LAT0 + r * DLAT:.7f}" '
                         f'lon="{LON0 + c * DLON:.7f}">{tags}</node>')
    next_node = 1000
    next_way = 1
    if roads:
        for r in range(ROWS):
            refs = "".join(f'<nd ref="{_nid(c, r)}"/>' for c in range(COLS))
            if r == PRIMARY_ROW:
                tags = '<tag k="highway" v="primary"/><tag k="lanes" v="4"/><tag k="maxspeed" v="50"/><tag k="name" v="Corso Test"/>'
                if bus_stop:
                    # a stop position on the primary between columns 0 and 1
                    stop = next_node
                    next_node += 1
                    nodes.append(f'  <node id="{stop}" version="1" lat="{LAT0 + r * DLAT:.7f}" '
                                 f'lon="{LON0 + 0.5 * DLON:.7f}"><tag k="highway" v="bus_stop"/>'
                                 '<tag k="public_transport" v="stop_position"/><tag k="bus" v="yes"/>'
                                 '<tag k="name" v="Fermata Test"/></node>')
                    refs = (f'<nd ref="{_nid(0, r)}"/><nd ref="{stop}"/>'
                            + "".join(f'<nd ref="{_nid(c, r)}"/>' for c in range(1, COLS)))
            else:
                tags = '<tag k="highway" v="residential"/>'
            ways.append(f'  <way id="{next_way}" version="1">{refs}{tags}</way>')
            next_way += 1
        for c in range(COLS):
            refs = "".join(f'<nd ref="{_nid(c, r)}"/>' for r in range(ROWS))
            kind = "secondary" if c == SECONDARY_COL else "residential"
            ways.append(f'  <way id="{next_way}" version="1">{refs}<tag k="highway" v="{kind}"/></way>')
            next_way += 1
    else:
        # a footpath only: no road for cars
        refs = "".join(f'<nd ref="{_nid(c, 0)}"/>' for c in range(COLS))
        ways.append(f'  <way id="{next_way}" version="1">{refs}<tag k="highway" v="footway"/></way>')
        next_way += 1

    def closed_way(lat0, lon0, lat1, lon1, tags):
        nonlocal next_node, next_way
        ids = []
        for la, lo in ((lat0, lon0), (lat0, lon1), (lat1, lon1), (lat1, lon0)):
            nodes.append(f'  <node id="{next_node}" version="1" lat="{la:.7f}" lon="{lo:.7f}"/>')
            ids.append(next_node)
            next_node += 1
        refs = "".join(f'<nd ref="{i}"/>' for i in ids + ids[:1])
        ways.append(f'  <way id="{next_way}" version="1">{refs}{tags}</way>')
        next_way += 1

    if buildings:
        # dense: 3 x 3 buildings filling most of the blocks between columns 1..3, rows 1..2
        for bc in (1, 2):
            for k in range(3):
                for m in range(3):
                    la0 = LAT0 + PRIMARY_ROW * DLAT + (0.08 + 0.3 * k) * DLAT
                    lo0 = LON0 + bc * DLON + (0.08 + 0.3 * m) * DLON
                    closed_way(la0, lo0, la0 + 0.24 * DLAT, lo0 + 0.24 * DLON,
                              '<tag k="building" v="yes"/><tag k="building:levels" v="6"/>')
        # sparse: one small house in two outer blocks
        for bc, br in ((0, 0), (3, 2)):
            la0 = LAT0 + br * DLAT + 0.4 * DLAT
            lo0 = LON0 + bc * DLON + 0.4 * DLON
            closed_way(la0, lo0, la0 + 0.1 * DLAT, lo0 + 0.1 * DLON,
                      '<tag k="building" v="house"/>' + ('<tag k="height" v="7.5 m"/>' if bc == 0 else ''))
        # a car park south of the primary, between columns 3 and 4
        la0 = LAT0 + 0.55 * DLAT
        lo0 = LON0 + 3.2 * DLON
        closed_way(la0, lo0, la0 + 0.3 * DLAT, lo0 + 0.5 * DLON, '<tag k="amenity" v="parking"/>')
    return ('<?xml version="1.0" encoding="UTF-8"?>\n<osm version="0.6" generator="coloc tests">\n'
            f'  <bounds minlat="{LAT0 - 0.0005:.7f}" minlon="{LON0 - 0.0005:.7f}" '
            f'maxlat="{LAT0 + (ROWS - 1) * DLAT + 0.0005:.7f}" maxlon="{LON0 + (COLS - 1) * DLON + 0.0005:.7f}"/>\n'
            + "\n".join(nodes) + "\n" + "\n".join(ways) + "\n</osm>\n")


def write_osm_grid(path: Path, **kw) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(osm_grid(**kw))
    return path
