"""SUMO through libsumo: true vehicle states per step and traffic statistics.

libsumo holds one simulation per process (docs/architecture.md "SUMO notes"): parallel runs
are processes. Plain per-vehicle getters were measured faster than
subscriptions on these machines, so they are used here.
"""

from __future__ import annotations

import math
import os
import re
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit

from coloc.core.vehicles import match_ids
from couplers.errors import InputError
from couplers.net import gridlock as jam
from couplers.traffic.reference_point import REFERENCE_POINTS, centre_from_front

try:  # imported lazily by callers that only need the pure parts of couplers
    import libsumo
except ImportError:  # pragma: no cover - reported when a session starts
    libsumo = None
# The per-vehicle getters as SWIG functions (what libsumo.vehicle.getPosition etc. call); None
# where this libsumo build does not expose them, then the libsumo.vehicle methods are used.
_swig = getattr(getattr(libsumo, "libsumo", None), "_libsumo", None)
_GETTERS = (tuple(getattr(_swig, f"vehicle_{g}") for g in ("getPosition", "getSpeed", "getAngle"))
            if all(hasattr(_swig, f"vehicle_{g}") for g in ("getPosition", "getSpeed", "getAngle")) else None)

HALT_SPEED = 0.1  # m/s, SUMO's own halting threshold
# SUMO warnings (its error log) that mean a vehicle of the demand is dropped before it ever drives: an
# unsorted route file (SUMO ignores every vehicle departing before one read earlier in the same file) and a
# trip without a route. Message texts of SUMO 1.2x (MSRouteHandler, MSInsertionControl).
LOST_WARNINGS = {
    "unsorted": re.compile(r"Route file should be sorted by departure time, ignoring '([^']*)'"),
    "no_route": re.compile(r"No route for vehicle '([^']*)' found"),
}
STAT_INTERVAL_S = 300.0  # 5-minute aggregation (Brambilla Figs. 13-15)


@dataclass(frozen=True)
class SumoOptions:
    net: Path
    routes: Path
    seed: int
    step_length: float = 0.75
    end: float = 3600.0
    tls_off: bool = False
    # Ballistic position update: x_t = x_{t-1} + Ts (v_{t-1} + v_t)/2, the kinematics of
    # model (1) with piecewise-constant acceleration (SUMO's default Euler update
    # advances by Ts v_t, a 0.5 Ts^2 a mismatch with the motion model).
    ballistic: bool = True
    # Lane changes spread over this many seconds instead of SUMO's default one-step
    # jump of a lane width (measured on the test cross: cross-track model residual
    # 0.27 m rms with jumps, 0.08 m with 3 s manoeuvres).
    lanechange_duration: float = 3.0
    extra_args: tuple[str, ...] = ()
    # Further route files loaded after ``routes`` (a net folder's further route files and persons file).
    extra_routes: tuple[Path, ...] = ()
    # The scenario's begin on its own clock (s, SUMO's --begin): the run simulates [begin, end]; SUMO drops
    # vehicles departing before it when it loads the routes. 0: not passed (SUMO's default).
    begin: float = 0.0
    additional: tuple[Path, ...] = ()  # SUMO additional files (a net folder's [files] additional)

    def command(self) -> list[str]:
        cmd = [
            "sumo",
            "--net-file", str(self.net),
            "--route-files", ",".join(str(r) for r in (self.routes, *self.extra_routes)),
            "--step-length", repr(self.step_length),
            "--seed", str(int(self.seed)),
            *(("--begin", repr(self.begin)) if self.begin else ()),
            "--end", repr(self.end),
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
            "--log", "/dev/null" if Path("/dev/null").exists() else "NUL",
            "--step-method.ballistic", "true" if self.ballistic else "false",
            "--lanechange.duration", repr(self.lanechange_duration),
        ]
        if self.additional:
            cmd += ["--additional-files", ",".join(str(a) for a in self.additional)]
        if self.tls_off:
            cmd += ["--tls.all-off", "true"]
        return cmd + list(self.extra_args)


@dataclass
class VehicleStates:
    """True states of the vehicles in the net after one step."""

    t: float
    ids: np.ndarray  # (N,) str
    xy: np.ndarray  # (N, 2) position of the reference point (REFERENCE_POINTS; SumoTraffic.reference_point), m
    velocity: np.ndarray  # (N, 2) m/s
    heading: np.ndarray  # (N,) rad from +x, counter-clockwise
    accel: np.ndarray  # (N, 2) mean acceleration over the last step, m/s^2
    entered: np.ndarray  # (N,) bool: new, or back after a teleport / discontinuity
    # Derived per step by SumoTraffic.step so that the coupler does not recompute them (None: not given).
    direction: np.ndarray | None = None  # (N, 2) unit heading [cos, sin] (the values velocity was built from)
    prev_row: np.ndarray | None = None  # (N,) int, row of each vehicle in the previous step's states, -1 if new
    # (N,) distance from ``xy`` forward along ``direction`` to the front bumper, m (half the length with the
    # reference point "centre"); None: ``xy`` is the front bumper.
    front_offset: np.ndarray | None = None


@dataclass
class TrafficStats:
    """Per-step counters aggregated into 5-minute intervals (Figs. 13-15)."""

    step_length: float
    interval_s: float = STAT_INTERVAL_S
    origin: float = 0.0  # intervals are counted from here (the run's begin), s
    rows: list[dict] = field(default_factory=list)
    _acc: dict = field(default_factory=dict)

    def _reset(self, start: float) -> None:
        self._acc = dict(start=start, steps=0, vehicles=0, halting=0, arrived=0, dist_m=0.0, teleports=0)

    def add(self, t: float, n: int, halting: int, arrived: int, dist_m: float, teleports: int) -> None:
        # intervals (start, start + interval_s]: steps at begin + dt ... begin + 3600 s make 12 hourly rows;
        # a step at the begin itself (none today) joins the first interval rather than making a partial one
        start = self.origin + max(0, math.floor((t - self.origin - 1e-9) / self.interval_s)) * self.interval_s
        if not self._acc:
            self._reset(start)
        elif start != self._acc["start"]:
            self.flush()
            self._reset(start)
        a = self._acc
        a["steps"] += 1
        a["vehicles"] += n
        a["halting"] += halting
        a["arrived"] += arrived
        a["dist_m"] += dist_m
        a["teleports"] += teleports

    def flush(self) -> None:
        a = self._acc
        if not a or a["steps"] == 0:
            return
        span = a["steps"] * self.step_length
        stop_time = a["halting"] * self.step_length
        self.rows.append(
            dict(
                interval_start_s=a["start"],
                interval_end_s=a["start"] + span,
                mean_vehicles=a["vehicles"] / a["steps"],
                exit_flow_vph=a["arrived"] * 3600.0 / span,
                mean_queue=a["halting"] / a["steps"],
                stop_time_s_per_km=stop_time / (a["dist_m"] / 1000.0) if a["dist_m"] > 0 else 0.0,
                teleports=a["teleports"],
                vehicle_seconds=a["vehicles"] * self.step_length,
                distance_km=a["dist_m"] / 1000.0,
                arrived=a["arrived"],
            )
        )
        self._acc = {}


class SumoTraffic:
    """A running libsumo simulation; use as a context manager, then ``step()``."""

    # A jump larger than the distance covered at this speed over one step is a
    # discontinuity (teleport, re-route onto another lane): treat it as a re-entry.
    JUMP_SPEED = 40.0  # m/s

    def __init__(self, options: SumoOptions, reference_point: str = "front_bumper"):
        if reference_point not in REFERENCE_POINTS:
            raise ValueError(f"reference_point must be one of {REFERENCE_POINTS}, got {reference_point!r}")
        self.options = options
        self.reference_point = reference_point
        self._prev_half_length = np.empty(0)  # "centre": half the length of each vehicle of the previous step
        self.stats = TrafficStats(step_length=options.step_length, origin=options.begin)
        self._prev_ids = np.empty(0, dtype=object)
        self._prev_xy = np.empty((0, 2))
        self._prev_vel = np.empty((0, 2))
        self._teleporting: set[str] = set()
        self._back_from_teleport: set[str] = set()
        self.teleports = 0
        self.sumo_version = ""
        self._running = False
        # Vehicles of the demand over the run (losses()): counted with libsumo's per-step counters, a few
        # calls per step beside the three getters per vehicle.
        self.loaded = 0
        self.departed = 0
        self.collisions = 0
        self.never_inserted = 0
        self.lost_at_load: dict[str, list[str]] = {k: [] for k in LOST_WARNINGS}
        self.jam = jam.JamWatch(options.begin)
        self._every = max(1, int(round(jam.CHECK_S / options.step_length)))
        self._steps = 0
        self._log: Path | None = None

    def __enter__(self) -> "SumoTraffic":
        if libsumo is None:
            raise InputError(None, "libsumo", "the libsumo package is not installed (pip install libsumo)")
        # SUMO's warnings go to a temporary error log (not the console: --no-warnings stays), read at the end
        # for the vehicles SUMO dropped (LOST_WARNINGS).
        fd, name = tempfile.mkstemp(prefix="coloc-sumo-", suffix=".log")
        os.close(fd)
        self._log = Path(name)
        try:
            libsumo.start(self.options.command() + ["--error-log", name])
        except Exception as exc:  # libsumo raises its own (unpicklable) exception types
            self._log.unlink(missing_ok=True)
            raise InputError(self.options.net, None, f"SUMO could not load the scenario: {exc}") from None
        self._running = True
        self.sumo_version = str(libsumo.getVersion()[1])
        self.loaded = int(libsumo.simulation.getLoadedNumber())  # the vehicles loaded when SUMO starts
        return self

    def __exit__(self, *exc) -> None:
        if self._running:
            try:
                self.never_inserted = len(libsumo.simulation.getPendingVehicles())
            except Exception:  # noqa: BLE001 - a simulation that failed: the failure is what gets reported
                pass
            libsumo.close()
            self._running = False
        self._read_log()
        self.stats.flush()

    def _read_log(self) -> None:
        if self._log is None:
            return
        try:
            with open(self._log, encoding="utf-8", errors="replace") as fh:
                for line in fh:
                    for kind, pattern in LOST_WARNINGS.items():
                        m = pattern.search(line)
                        if m:
                            self.lost_at_load[kind].append(m.group(1))
        except OSError:
            pass
        self._log.unlink(missing_ok=True)
        self._log = None

    def losses(self) -> dict:
        """The demand's vehicles over the run, for summary.json's ``traffic`` block: loaded (read from the route
        files by SUMO, including vehicles read ahead that depart after the end), inserted (departed), never
        inserted (due by the end but still waiting to enter), dropped at load (SUMO warnings: unsorted route
        file, no route), teleports, vehicles in collisions, and the gridlock rule's verdict
        (:mod:`couplers.net.gridlock`)."""
        dropped = {k: len(v) for k, v in self.lost_at_load.items()}
        due = self.departed + self.never_inserted
        verdict = self.jam.verdict(self.teleports, due)
        out = {"loaded": self.loaded, "inserted": self.departed, "never_inserted": self.never_inserted,
               "dropped_at_load": sum(dropped.values()), "dropped_unsorted": dropped["unsorted"],
               "dropped_no_route": dropped["no_route"], "collisions": self.collisions,
               "jammed": bool(verdict), "jam_verdict": verdict or "no gridlock",
               "max_halting_share": round(self.jam.worst_share, 3), "max_backlog": self.jam.worst_backlog}
        first = next((f"{k} {v[0]!r}" for k, v in self.lost_at_load.items() if v), None)
        if first is not None:
            out["first_dropped"] = first
        return out

    @property
    def time(self) -> float:
        return float(libsumo.simulation.getTime())

    def done(self) -> bool:
        return self.time >= self.options.end - 1e-9

    def advance(self, until: float) -> int:
        """SUMO alone up to ``until`` on the scenario's clock (a traffic-only warm-up): no vehicle is read, the
        5-minute statistics and the gridlock watch start after it; the demand's counters (loaded, departed,
        collisions, teleports) keep counting. The next :meth:`step` sees every vehicle as new (entered).
        Returns the steps simulated."""
        sim = libsumo.simulation
        n = 0
        while float(sim.getTime()) < until - 1e-9 and not self.done():
            libsumo.simulationStep()
            starting = sim.getStartingTeleportIDList()
            self.teleports += len(starting)
            self._teleporting.update(starting)  # still jumping when the frames start: left out as in step()
            self._teleporting.difference_update(sim.getEndingTeleportIDList())
            self.loaded += sim.getLoadedNumber()
            self.departed += sim.getDepartedNumber()
            self.collisions += sim.getCollidingVehiclesNumber()
            n += 1
        self.jam = jam.JamWatch(float(sim.getTime()))
        return n

    def step(self) -> VehicleStates:
        sim, veh = libsumo.simulation, libsumo.vehicle
        libsumo.simulationStep()
        t = float(sim.getTime())
        dt = self.options.step_length
        starting = sim.getStartingTeleportIDList()
        ending = sim.getEndingTeleportIDList()
        self.teleports += len(starting)
        self._teleporting.update(starting)
        self._teleporting.difference_update(ending)
        self._back_from_teleport.update(ending)

        ids_all = veh.getIDList()
        ids = [v for v in ids_all if v not in self._teleporting] if self._teleporting else list(ids_all)
        n = len(ids)
        # libsumo has no batch getter: three plain getters per vehicle are the SUMO floor
        # (measured faster than subscriptions, docs/architecture.md "SUMO notes"), called on the
        # SWIG functions themselves (the libsumo.vehicle methods only forward to them: 1/4 of the
        # getters' time; same values).
        get_position, get_speed, get_angle = _GETTERS or (veh.getPosition, veh.getSpeed, veh.getAngle)
        xy = np.array([get_position(v, False) for v in ids], dtype=float).reshape(n, 2)
        speed = np.array([get_speed(v) for v in ids], dtype=float)
        angle = np.array([get_angle(v) for v in ids], dtype=float)
        ids_arr = np.array(ids, dtype=object)
        # Navigational angle (0 = north, clockwise) -> heading from +x, counter-clockwise.
        heading = np.radians(90.0 - angle)
        direction = np.empty((n, 2))
        direction[:, 0] = np.cos(heading)  # numpy's cos / sin of the contiguous headings (copied into place)
        direction[:, 1] = np.sin(heading)
        velocity = speed[:, None] * direction

        idx = match_ids(self._prev_ids, ids_arr)
        half = None
        if self.reference_point == "centre":
            half = self._half_lengths(ids, idx)
            xy = centre_from_front(xy, direction, half)
        back = np.zeros(n, dtype=bool)
        if self._back_from_teleport:
            back = np.array([v in self._back_from_teleport for v in ids], dtype=bool)
            self._back_from_teleport.difference_update(ids)
        # Entered (new, back from a teleport, or a jump) and the mean acceleration over (t - Ts, t] of the
        # others: what a two-axis IMU integrates, turning included (_continuity_reference in numpy).
        entered, accel = _continuity(idx, back, xy, self._prev_xy, velocity, self._prev_vel, dt, self.JUMP_SPEED * dt)

        arrived = sim.getArrivedNumber()
        halting = int(np.count_nonzero(speed < HALT_SPEED))
        self.stats.add(t, n, halting, arrived, float(speed.sum() * dt), len(starting))
        self.loaded += sim.getLoadedNumber()
        self.departed += sim.getDepartedNumber()
        self.collisions += sim.getCollidingVehiclesNumber()
        self._steps += 1
        if self._steps % self._every == 0:
            self.jam.check(t, halting, n, len(sim.getPendingVehicles()), self.departed)
        self._prev_ids, self._prev_xy, self._prev_vel = ids_arr, xy, velocity
        if half is not None:
            self._prev_half_length = half
        return VehicleStates(t=t, ids=ids_arr, xy=xy, velocity=velocity, heading=heading, accel=accel, entered=entered,
                             direction=direction, prev_row=idx, front_offset=half)

    def _half_lengths(self, ids: list, idx: np.ndarray) -> np.ndarray:
        """(N,) half of each vehicle's SUMO length (vehicle.getLength, asked once per vehicle: it does not
        change; the others carried from the previous step's rows ``idx``)."""
        half = np.empty(len(ids))
        seen = idx >= 0
        half[seen] = self._prev_half_length[idx[seen]]
        get_length = libsumo.vehicle.getLength
        for i in np.flatnonzero(~seen).tolist():  # new vehicles only
            half[i] = 0.5 * get_length(ids[i])
        return half


@njit(cache=True)
def _continuity(idx, back, xy, prev_xy, velocity, prev_vel, dt, max_jump):
    """(entered (N,), accel (N, 2)): a vehicle enters when it is new (idx < 0), back from a teleport, or
    moved more than ``max_jump`` (``np.hypot``'s libm hypot) since its previous row; the others get
    (v - v_prev) / dt, the entered zero."""
    n = idx.size
    entered = np.empty(n, dtype=np.bool_)
    accel = np.zeros((n, 2))
    for i in range(n):
        r = idx[i]
        entered[i] = r < 0 or back[i]
        if r >= 0 and math.hypot(xy[i, 0] - prev_xy[r, 0], xy[i, 1] - prev_xy[r, 1]) > max_jump:
            entered[i] = True
        if not entered[i]:
            accel[i, 0] = (velocity[i, 0] - prev_vel[r, 0]) / dt
            accel[i, 1] = (velocity[i, 1] - prev_vel[r, 1]) / dt
    return entered, accel


def _continuity_reference(idx, back, xy, prev_xy, velocity, prev_vel, dt, max_jump):
    """:func:`_continuity` in numpy."""
    seen = idx >= 0
    entered = ~seen | back
    jump = np.zeros(idx.size, dtype=bool)
    jump[seen] = np.hypot(*(xy[seen] - prev_xy[idx[seen]]).T) > max_jump
    entered |= jump
    accel = np.zeros((idx.size, 2))
    cont = ~entered
    accel[cont] = (velocity[cont] - prev_vel[idx[cont]]) / dt
    return entered, accel


def sumo_version() -> str:
    if libsumo is None:
        return "not installed"
    return str(libsumo.getVersion()[1])
