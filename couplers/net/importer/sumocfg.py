"""A researcher's SUMO scenario as a ``.sumocfg`` (``coloc net import --sumocfg``), and the clock of a demand.

:func:`read_sumocfg` reads what a SUMO configuration names: the net, every route file (plain or
gzipped, several), the additional files and the scenario's own clock (``begin`` / ``end`` /
``step-length``). Both layouts SUMO writes and reads are accepted: options grouped in sections
(``<input><net-file value="..."/></input>``) and options directly under the root element; file
lists are comma or space separated, paths relative to the configuration (SUMO's own rule).

:func:`demand_departures` reads the departures of route files (first and last departure, what
departs before a begin time). SUMO, given ``--begin B``, drops every vehicle and trip whose depart
is before B when it loads the routes, and starts a flow that began before B at B (its departures
before B are dropped too); checked with SUMO 1.28 (a vehicle at 25000 s, a trip at 25150 s and a flow
from 25100 s every 20 s, begin 25200 s: the vehicle and the trip never depart, the flow's first
vehicle departs at 25200 s).
"""

from __future__ import annotations

import functools
import gzip
import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from couplers.errors import InputError

# SUMO option names (and their one-letter synonyms) read from a configuration.
_NET = ("net-file", "n")
_ROUTES = ("route-files", "r")
_ADDITIONAL = ("additional-files", "a")
_BEGIN = ("begin", "b")
_END = ("end", "e")
_STEP = ("step-length",)
_USED = {*_NET, *_ROUTES, *_ADDITIONAL, *_BEGIN, *_END, *_STEP}
# Options that only name outputs or logging: nothing of the scenario's traffic; not listed as left out.
_QUIET = re.compile(r".*(-output|-log|log|verbose|no-warnings|no-step-log|duration-log.*|xml-validation.*|"
                    r"gui-settings-file|start|quit-on-end|window-size|window-pos|delay|breakpoints|"
                    r"output-prefix|precision|configuration-file|save-configuration|write-license)$")


@dataclass(frozen=True)
class SumoCfg:
    """What a ``.sumocfg`` names, paths resolved against its folder."""

    path: Path
    net: Path
    routes: tuple[Path, ...]
    additional: tuple[Path, ...]
    begin: float | None  # s on the scenario's clock (SUMO's default 0 when None)
    end: float | None
    step_length: float | None
    ignored: tuple[str, ...]  # other options of the configuration, which coloc does not apply


def is_sumocfg(path: Path) -> bool:
    """Whether ``path`` is a SUMO configuration (by name, else by its root element)."""
    path = Path(path)
    if path.name.endswith((".sumocfg", ".sumo.cfg")):
        return True
    try:
        with _open(path) as fh:
            for _event, elem in ET.iterparse(fh, events=("start",)):
                return elem.tag in ("configuration", "sumoConfiguration")
    except (OSError, ET.ParseError, EOFError):
        return False
    return False


def _open(path: Path):
    """A binary file object; gzip when the file starts with gzip's magic bytes (SUMO reads both)."""
    with open(path, "rb") as fh:
        gz = fh.read(2) == b"\x1f\x8b"
    return gzip.open(path, "rb") if gz else open(path, "rb")


def is_gzip(path: Path) -> bool:
    with open(path, "rb") as fh:
        return fh.read(2) == b"\x1f\x8b"


def parse_time(text: str, path: Path, field: str) -> float:
    """A SUMO time: seconds ("25200", "25200.5") or clock time ("07:00:00", "1:07:00:00" with days)."""
    s = str(text).strip()
    try:
        if ":" in s:
            parts = [float(p) for p in s.split(":")]
            if len(parts) not in (3, 4) or any(p < 0 for p in parts):
                raise ValueError
            val = 0.0
            for p, unit in zip(reversed(parts), (1.0, 60.0, 3600.0, 86400.0)):
                val += p * unit
        else:
            val = float(s)
    except ValueError:
        raise InputError(path, field, f"not a time: {text!r} (seconds, or h:m:s)") from None
    if not math.isfinite(val):
        raise InputError(path, field, f"not a finite time: {text!r}")
    return val


def clock(t: float) -> str:
    """Seconds since midnight as a clock time, e.g. 25200 -> "07:00" ("07:00:30" with seconds, "+1d" past 24 h)."""
    whole = int(math.floor(t + 1e-9))
    days, rest = divmod(whole, 86400)
    h, rest = divmod(rest, 3600)
    m, s = divmod(rest, 60)
    text = f"{h:02d}:{m:02d}" + (f":{s:02d}" if s else "")
    return text + (f" +{days}d" if days else "")


def _files(value: str) -> list[str]:
    return [x for x in re.split(r"[,\s]+", value.strip()) if x]


def read_sumocfg(path: Path) -> SumoCfg:
    """Read a SUMO configuration; :class:`InputError` naming the file and option on anything unusable."""
    path = Path(path)
    try:
        with _open(path) as fh:
            root = ET.parse(fh).getroot()
    except FileNotFoundError:
        raise InputError(path, None, "file not found") from None
    except (ET.ParseError, EOFError, OSError) as exc:
        raise InputError(path, None, f"not valid XML ({exc})") from None
    if root.tag not in ("configuration", "sumoConfiguration"):
        raise InputError(path, None, f"not a SUMO configuration (root element <{root.tag}>, expected "
                                     "<configuration> or <sumoConfiguration>)")
    opts: dict[str, str] = {}
    for elem in root.iter():
        if elem is root or "value" not in elem.attrib and "v" not in elem.attrib:
            continue
        opts[elem.tag] = elem.attrib.get("value", elem.attrib.get("v", ""))

    def get(names: tuple[str, ...]) -> tuple[str, str] | None:
        for n in names:
            if n in opts:
                return n, opts[n]
        return None

    base = path.parent

    def files(names: tuple[str, ...]) -> tuple[Path, ...]:
        got = get(names)
        if got is None:
            return ()
        out = []
        for name in _files(got[1]):
            p = Path(name) if Path(name).is_absolute() else base / name
            if not p.is_file():
                raise InputError(path, got[0], f"{name}: file not found (paths are relative to the configuration)")
            out.append(p)
        return tuple(out)

    nets = files(_NET)
    if len(nets) != 1:
        raise InputError(path, "net-file", "the configuration names no net" if not nets else
                                           f"names {len(nets)} nets; coloc takes one")
    routes = files(_ROUTES)
    if not routes:
        raise InputError(path, "route-files", "the configuration names no route file (coloc simulates its demand)")

    def time(names: tuple[str, ...]) -> float | None:
        got = get(names)
        return None if got is None else parse_time(got[1], path, got[0])

    begin, end, step = time(_BEGIN), time(_END), time(_STEP)
    if begin is not None and begin < 0:
        raise InputError(path, "begin", f"must be >= 0, got {begin:g}")
    if end is not None and end < 0:  # SUMO's -1: until the last vehicle has left
        end = None
    if begin is not None and end is not None and not end > begin:
        raise InputError(path, "end", f"{end:g} s is not after begin {begin:g} s")
    if step is not None and not step > 0:
        raise InputError(path, "step-length", f"must be positive, got {step:g}")
    ignored = tuple(sorted(k for k in opts if k not in _USED and not _QUIET.fullmatch(k)))
    return SumoCfg(path=path, net=nets[0], routes=routes, additional=files(_ADDITIONAL), begin=begin, end=end,
                   step_length=step, ignored=ignored)


@dataclass(frozen=True)
class Departures:
    """The departures of a demand (vehicles, trips and flows of its route files)."""

    first: float | None  # earliest depart / flow begin; None: no timed departure
    last: float | None  # latest depart / flow end
    vehicles: int  # vehicles and trips with a numeric depart
    flows: int
    early: tuple[float, ...]  # sorted departs of vehicles and trips (for counting those before a begin)
    flow_begins: tuple[float, ...]  # sorted flow begins

    def before(self, begin: float) -> tuple[int, int]:
        """(vehicles and trips departing before ``begin``, flows beginning before it): what SUMO drops."""
        import bisect

        return bisect.bisect_left(self.early, begin - 1e-9), bisect.bisect_left(self.flow_begins, begin - 1e-9)

    def describe_before(self, begin: float) -> str:
        """One clause: what departs before ``begin`` and what SUMO does with it ("" when nothing does)."""
        nv, nf = self.before(begin)
        if not nv and not nf:
            return ""
        what = []
        if nv:
            what.append(f"{nv} of {self.vehicles} vehicles/trips depart before it")
        if nf:
            what.append(f"{nf} of {self.flows} flows begin before it")
        dropped = " and ".join((["those vehicles"] if nv else []) + (["the flows' departures before it"] if nf else []))
        return (" and ".join(what) + f": SUMO drops {dropped} when it loads the routes (as it does when it runs "
                "the scenario's own configuration)")


def demand_departures(paths) -> Departures:
    """The departures of route files (``paths``: one path or several; plain or gzipped)."""
    if isinstance(paths, (str, Path)):
        paths = (paths,)
    key = tuple((str(p), p.stat().st_mtime_ns, p.stat().st_size) for p in map(Path, paths) if p.is_file())
    return _departures(key)


@functools.lru_cache(maxsize=8)
def _departures(key: tuple) -> Departures:
    # key: (path, mtime, size) per file, so that a changed file is read again
    departs: list[float] = []
    begins: list[float] = []
    ends: list[float] = []
    for name, _mtime, _size in key:
        path = Path(name)
        try:
            with _open(path) as fh:
                for _event, el in ET.iterparse(fh, events=("end",)):
                    tag = el.tag
                    if tag in ("vehicle", "trip"):
                        d = el.get("depart")
                        if d is not None and d[:1].isdigit():
                            departs.append(parse_time(d, path, f"{tag} {el.get('id')!r} depart"))
                        el.clear()
                    elif tag == "flow":
                        b = parse_time(el.get("begin", "0"), path, f"flow {el.get('id')!r} begin")
                        begins.append(b)
                        e = el.get("end")
                        ends.append(parse_time(e, path, f"flow {el.get('id')!r} end") if e and e[:1].isdigit() else b)
                        el.clear()
                    elif tag in ("person", "personFlow", "container"):
                        el.clear()
        except (ET.ParseError, EOFError, OSError) as exc:
            raise InputError(path, None, f"not valid XML ({exc})") from None
    departs.sort()
    begins.sort()
    firsts = ([departs[0]] if departs else []) + ([begins[0]] if begins else [])
    lasts = ([departs[-1]] if departs else []) + ([max(ends)] if ends else [])
    return Departures(first=min(firsts) if firsts else None, last=max(lasts) if lasts else None,
                      vehicles=len(departs), flows=len(begins), early=tuple(departs), flow_begins=tuple(begins))


# Elements of additional files that set the signal programs (loaded into coloc's runs); the others
# (detectors, stops, rerouters, ...) are not.
SIGNAL_TAGS = ("tlLogic", "WAUT", "wautJunction")


def signal_programs(paths, source: str) -> tuple[str | None, list[str], dict[str, int]]:
    """The signal programs of additional files as one additional file's text (None: there are none), the
    programs (``tlLogic 'ID' program 'P'``) and the counts of every other top-level element, by tag."""
    kept: list[ET.Element] = []
    programs: list[str] = []
    others: dict[str, int] = {}
    for path in paths:
        try:
            with _open(path) as fh:
                root = ET.parse(fh).getroot()
        except (ET.ParseError, EOFError, OSError) as exc:
            raise InputError(path, None, f"not valid XML ({exc})") from None
        for el in root:
            if not isinstance(el.tag, str):
                continue  # a comment
            if el.tag in SIGNAL_TAGS:
                kept.append(el)
                if el.tag == "tlLogic":
                    programs.append(f"tlLogic {el.get('id')!r} program {el.get('programID')!r}")
            else:
                others[el.tag] = others.get(el.tag, 0) + 1
    if not kept:
        return None, programs, others
    note = (f"the signal programs ({', '.join(SIGNAL_TAGS)}) of {source}, as given; loaded into every run as a "
            "SUMO additional file").replace("--", "-")  # an XML comment may not hold "--"
    lines = ['<?xml version="1.0" encoding="UTF-8"?>', f"<!-- {note} -->", "<additional>"]
    for el in kept:
        el.tail = None
        ET.indent(el, space="    ", level=1)
        lines.append("    " + ET.tostring(el, encoding="unicode").rstrip())
    lines.append("</additional>")
    return "\n".join(lines) + "\n", programs, others


def program_problems(net, paths) -> list[str]:
    """Signal programs of additional files for traffic lights the net does not have (SUMO would not load)."""
    ids = {tls.getID() for tls in net.getTrafficLights()}
    out = []
    for path in paths:
        try:
            with _open(path) as fh:
                root = ET.parse(fh).getroot()
        except (ET.ParseError, EOFError, OSError) as exc:
            return [f"{path}: not valid XML ({exc})"]
        for el in root.iter("tlLogic"):
            if el.get("id") not in ids:
                out.append(f"{path}: tlLogic {el.get('id')!r}: the net has no traffic light of that id")
    return out


# Elements whose depart (a flow's begin) SUMO checks against the one read before it in the same route file
# (its route handler's "Route file should be sorted by departure time, ignoring ..." warning: the later ones
# are dropped without a word on the console; checked with SUMO 1.28: a flow beginning at 50 s then a vehicle
# at 10 s: the vehicle never departs).
_DEPARTING = ("vehicle", "trip", "person", "container")
_FLOWS = ("flow", "personFlow", "containerFlow")


def _depart_of(el: ET.Element, path: Path) -> float | None:
    d = el.get("begin") if el.tag in _FLOWS else el.get("depart")
    if d is None or not d[:1].isdigit():  # "triggered", "now", ...: not a given time
        return None
    return parse_time(d, path, f"{el.tag} {el.get('id')!r} {'begin' if el.tag in _FLOWS else 'depart'}")


def first_unsorted(path: Path) -> str | None:
    """The first vehicle (trip, person) of a route file departing before one listed earlier in the same file,
    as one clause naming both; None when the file is sorted. SUMO drops every such vehicle at load (checked
    with SUMO 1.28: a file of a vehicle at 200 s then 59 at 2..118 s runs 1 vehicle)."""
    path = Path(path)
    last, last_id = -math.inf, None
    try:
        with _open(path) as fh:
            depth = 0
            for event, el in ET.iterparse(fh, events=("start", "end")):
                if event == "start":
                    depth += 1
                    continue
                depth -= 1
                if depth != 1:
                    continue
                if el.tag in _DEPARTING or el.tag in _FLOWS:
                    d = _depart_of(el, path)
                    if d is not None:
                        if d < last:
                            return (f"{el.tag} {el.get('id')!r} departs at {d:g} s, before {last_id} at {last:g} s "
                                    "listed above it: SUMO would drop it and every later vehicle departing "
                                    "before that")
                        last, last_id = d, f"{el.tag} {el.get('id')!r}"
                el.clear()
    except (ET.ParseError, EOFError, OSError) as exc:
        raise InputError(path, None, f"not valid XML ({exc})") from None
    return None


def sorted_routes_text(path: Path) -> tuple[str, int]:
    """A route file's text with its vehicles, trips, persons and flows in departure order (stable: equal
    departs keep their order; flows by their begin), after every other element (vTypes, routes, ...), which
    keep theirs; and the number of elements that moved."""
    path = Path(path)
    with _open(path) as fh:
        root = ET.parse(fh).getroot()
    items = list(root)
    keyed = []
    for i, el in enumerate(items):
        if el.tag in _DEPARTING or el.tag in _FLOWS:
            d = _depart_of(el, path)
        else:
            continue
        keyed.append((math.inf if d is None else d, i, el))
    ordered = [el for _, _, el in sorted(keyed, key=lambda k: (k[0], k[1]))]
    moved = sum(1 for a, (_, _, b) in zip(ordered, keyed) if a is not b)
    moving = {id(k[2]) for k in keyed}
    rest = [el for el in items if id(el) not in moving]
    for el in items:
        root.remove(el)
    for el in rest + ordered:
        el.tail = None
        root.append(el)
    ET.indent(root, space="    ")
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n", moved
