"""``[analysis] warmup_start``: what runs during the warm-up (docs/protocol.md "Warm-up").

"sensed": sensing and estimation from the begin, the warm-up's rows written and not scored; "traffic": SUMO
alone drives the warm-up (:meth:`couplers.traffic.sumo.SumoTraffic.advance`), sensing and estimation start
at begin + warmup_s with every vehicle on the road entering then."""
from __future__ import annotations

from couplers.errors import InputError

WARMUP_STARTS = ("sensed", "traffic")


def validate_warmup_start(cfg) -> None:
    """A known value; "traffic" on a SUMO scenario with a window left to sense."""
    a = cfg.analysis
    if a is None:
        return
    if a.warmup_start not in WARMUP_STARTS:
        raise InputError(cfg.path, "analysis.warmup_start",
                         f"unknown value {a.warmup_start!r} (available: {', '.join(WARMUP_STARTS)})")
    if a.warmup_start != "traffic":
        return
    if cfg.scenario.kind != "sumo":
        raise InputError(cfg.path, "analysis.warmup_start", "\"traffic\" needs a SUMO scenario (the controlled "
                                                            "scenarios have no traffic to run alone)")
    if not a.warmup_s < cfg.run.duration_s:
        raise InputError(cfg.path, "analysis.warmup_s", f"{a.warmup_s:g} s leaves nothing to sense with "
                                                        f"warmup_start = \"traffic\" (run.duration_s = "
                                                        f"{cfg.run.duration_s:g} s)")
