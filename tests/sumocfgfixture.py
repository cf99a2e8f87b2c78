"""A researcher's SUMO scenario as the tests build it: the test cross (tests/netfixture.py) with a
``.sumocfg`` on its own clock (begin 25200 s = 07:00), two route files (one gzipped, named routes shared
between them), departures before the begin (a cut of a larger file) and an additional file."""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

from netfixture import build_cross_net

BEGIN = 25200.0  # 07:00
END = 28800.0  # 08:00

# a.rou.xml: the vehicle type and the named routes, vehicles every 8 s from 25000 s (25 of them before the begin)
# b.rou.xml.gz: vehicles on a's routes every 15 s from 25050 s (10 before the begin), and a flow from 25100 s
A_DEPARTS = [25000.0 + 8.0 * i for i in range(60)]  # 25000 .. 25472
B_DEPARTS = [25050.0 + 15.0 * i for i in range(30)]  # 25050 .. 25485
A_BEFORE = sum(d < BEGIN for d in A_DEPARTS)  # 25
B_BEFORE = sum(d < BEGIN for d in B_DEPARTS)  # 10


def _vehicles(prefix: str, departs: list[float], routes: list[str]) -> list[str]:
    return [f'    <vehicle id="{prefix}{i}" type="car" route="{routes[i % len(routes)]}" depart="{d:.2f}" '
            'departLane="best" departSpeed="max"/>' for i, d in enumerate(departs)]


def build_sumocfg_scenario(folder: Path, *, begin: float = BEGIN, end: float | None = END,
                           flat: bool = False) -> Path:
    """Write the scenario into ``folder`` (net in net/, routes in routes/, additionals in add/); returns
    the .sumocfg. ``flat``: options directly under the root element instead of in sections."""
    folder.mkdir(parents=True, exist_ok=True)
    build_cross_net(folder / ".cross")
    (folder / "net").mkdir(exist_ok=True)
    shutil.copyfile(folder / ".cross" / "tlr.net.xml", folder / "net" / "cross.net.xml")
    shutil.rmtree(folder / ".cross")
    (folder / "routes").mkdir(exist_ok=True)
    a = ["<routes>",
         '    <vType id="car" accel="2.6" decel="4.5" sigma="0.5" length="4.5" minGap="2.5" maxSpeed="15"/>',
         '    <route id="we" edges="WC CE"/>', '    <route id="ew" edges="EC CW"/>',
         '    <route id="sn" edges="SC CN"/>', '    <route id="ws" edges="WC CS"/>',
         *_vehicles("a", A_DEPARTS, ["we", "ew", "sn", "ws"]), "</routes>"]
    (folder / "routes" / "a.rou.xml").write_text("\n".join(a) + "\n")
    # b: its vehicles and the flow, sorted by departure (SUMO ignores what is out of order)
    flow = (25100.0, '    <flow id="fb" type="car" route="sn" begin="25100" end="25400" period="40" '
                     'departLane="best" departSpeed="max"/>')
    items = sorted([*zip(B_DEPARTS, _vehicles("b", B_DEPARTS, ["ew", "we"])), flow])
    b = ["<routes>", *(line for _, line in items), "</routes>"]
    with gzip.open(folder / "routes" / "b.rou.xml.gz", "wt") as fh:
        fh.write("\n".join(b) + "\n")
    (folder / "add").mkdir(exist_ok=True)
    # the scenario's own signal program for C: the net's phases with the east-west green cut to 20 s and the
    # north-south green 60 s (a calibrated program; SUMO runs the program loaded last)
    net_text = (folder / "net" / "cross.net.xml").read_text()
    states = [line.split('state="')[1].split('"')[0] for line in net_text.splitlines() if "<phase " in line]
    phases = "".join(f'        <phase duration="{d}" state="{st}"/>\n' for d, st in zip((20, 3, 60, 3), states))
    (folder / "add" / "stops.add.xml").write_text(
        "<additional>\n"
        '    <busStop id="bs_w" lane="WC_0" startPos="150" endPos="170"/>\n'
        '    <inductionLoop id="det_e" lane="CE_0" pos="50" period="60" file="det.xml"/>\n'
        f'    <tlLogic id="C" type="static" programID="cfg" offset="0">\n{phases}    </tlLogic>\n'
        "</additional>\n")
    opts = {"net-file": "net/cross.net.xml", "route-files": "routes/a.rou.xml, routes/b.rou.xml.gz",
            "additional-files": "add/stops.add.xml", "begin": f"{begin:g}", "step-length": "0.75",
            "time-to-teleport": "300"}
    if end is not None:
        opts["end"] = f"{end:g}"
    if flat:
        body = "\n".join(f'    <{k} value="{v}"/>' for k, v in opts.items())
    else:
        sections = {"input": ("net-file", "route-files", "additional-files"), "time": ("begin", "end", "step-length"),
                    "processing": ("time-to-teleport",)}
        body = "\n".join(f"    <{sec}>\n" + "\n".join(f'        <{k} value="{opts[k]}"/>' for k in keys if k in opts)
                         + f"\n    </{sec}>" for sec, keys in sections.items())
    cfg = folder / "scenario.sumocfg"
    cfg.write_text(f'<?xml version="1.0" encoding="UTF-8"?>\n<configuration>\n{body}\n</configuration>\n')
    return cfg
