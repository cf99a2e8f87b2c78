"""The gridlock rule of `coloc net import`'s trials, which a run applies too (its run line flags a jammed run).

Gridlock signs, checked every CHECK_S simulated seconds (measured on a Berlin extract, see
:func:`couplers.net.importer.demand.gridlock_trial`): teleports (vehicles stuck for SUMO's 300 s) of
more than TELEPORTS of the vehicles due (at least TELEPORTS_MIN: a few happen at odd junctions of real
nets at any demand); more than HALTING_SHARE of the vehicles in the net halting over the last WINDOW
checks after the first WARMUP_S; an insertion backlog above BACKLOG of the vehicles departed (at least
BACKLOG_MIN: entries blocked).
"""

from __future__ import annotations

CHECK_S = 30.0
WARMUP_S = 300.0
WINDOW = 4  # checks averaged for the halting share
HALTING_SHARE = 0.5
BACKLOG = 0.05
BACKLOG_MIN = 20
TELEPORTS = 0.01
TELEPORTS_MIN = 3


def rule_text() -> str:
    return (f"teleports at most {TELEPORTS:.0%} of the vehicles (min {TELEPORTS_MIN}), at most {HALTING_SHARE:.0%} "
            f"of vehicles halting over {WINDOW} checks {CHECK_S:g} s apart after {WARMUP_S:g} s, insertion backlog "
            f"at most {BACKLOG:.0%} of departures (min {BACKLOG_MIN})")


class JamWatch:
    """The rule over a run: ``check`` every CHECK_S simulated seconds, ``verdict`` at the end (the first sign
    of gridlock, "" if none). Unlike a trial, a run does not stop at the first sign."""

    def __init__(self, begin: float = 0.0):
        self.begin = begin
        self.window: list[tuple[int, int]] = []
        self.worst_share = 0.0
        self.worst_backlog = 0
        self.first_sign = ""

    def check(self, t: float, halting: int, vehicles: int, backlog: int, departed: int) -> None:
        self.window.append((halting, vehicles))
        del self.window[:-WINDOW]
        share = sum(h for h, _ in self.window) / max(1, sum(n for _, n in self.window))
        late = t - self.begin >= WARMUP_S
        if late:
            self.worst_share = max(self.worst_share, share)
        self.worst_backlog = max(self.worst_backlog, backlog)
        if self.first_sign:
            return
        if late and share > HALTING_SHARE:
            self.first_sign = (f"{share:.0%} of {vehicles} vehicles halting over the {WINDOW * CHECK_S / 60:g} min "
                               f"to t = {t:.0f} s")
        elif backlog > max(BACKLOG_MIN, BACKLOG * departed):
            self.first_sign = f"{backlog} vehicles waiting to enter at t = {t:.0f} s"

    def verdict(self, teleports: int, vehicles: int) -> str:
        """The first sign of gridlock ("" if none); teleports are judged over the whole run."""
        if teleports > max(TELEPORTS_MIN, TELEPORTS * vehicles):
            return f"{teleports} teleports of {vehicles} vehicles" + (f"; {self.first_sign}" if self.first_sign else "")
        return self.first_sign
