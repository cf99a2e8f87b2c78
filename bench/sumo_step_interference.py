"""Why SUMO's own step is slower inside the realistic frames' run than inside the idealised one.

Times libsumo's ``simulationStep`` (process CPU, per step) and the coupler's getters and bookkeeping
(``SumoTraffic.step`` less the step) on the same traffic (TLR arterial, seed 1) under several things done
between two SUMO steps, the variants alternated round by round in one process:

- ``idealised``: the idealised frames, nothing else;
- ``realistic``: the realistic preset's frames (the work itself);
- ``touch:B``: the idealised frames, then B MiB of one preallocated array read and written before each step
  (the realistic code's memory traffic without its work or its allocations);
- ``alloc:B``: the idealised frames, then B MiB in fresh 8 KiB arrays allocated, written and freed before each
  step (the heap churn as well);
- ``spin:T``: the idealised frames, then T ms of CPU spent on almost no memory (a Python loop reading the
  process clock, a system call each time);
- ``compute:T``: the idealised frames, then T ms of a numba loop on registers (no memory, no system call);
- ``none``: the paired mode's null (nothing done, the same bookkeeping);
- ``sleep:T``: the idealised frames, then T ms asleep (the core left to other processes).

    python bench/sumo_step_interference.py [--duration 300] [--rounds 3] [--variants idealised,realistic,...]
    python bench/sumo_step_interference.py --paired --variants none,realistic,compute:1,touch:16,sleep:4
    python bench/sumo_step_interference.py --measure   # the realistic synthesis' CPU and transient bytes a step

Without --paired: one run per variant and round; prints per variant the median over rounds of each run's
per-step median and mean (steps after the first 60 s), in microseconds, and every round's value. Between separate
runs the machine's state moves SUMO's step by up to 2x on a shared machine, so these cannot resolve a 10 % effect.
With --paired (the decisive form): one idealised run per variant and round, the work done before a seeded random
half of its steps only (``realistic``: the realistic preset's synthesis on that run's latest states, by a second
coupler fed them), and SUMO's step after the work against without it, in the same run. Measured 2026-11-28 at
load 7-15 (docs/performance.md, "SUMO's step beside the realistic sensing"): the realistic synthesis +0.13 to
+0.23 ms (+7 to +10 %, five batches; the same with --no-gc), a register-only loop of 1 ms +0.03 to +0.18 ms,
16 MiB streamed +0.25 ms, nothing -0.04 to +0.02 ms.
Not a test: it asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import os
import sys
import time
from pathlib import Path

import numpy as np
from numba import njit

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from couplers.net.folder import load_net_folder  # noqa: E402
from couplers.sumo_coupler import SumoCoupler  # noqa: E402
from couplers.traffic import sumo as sumo_mod  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import sumo_scenario  # noqa: E402

WARM_S = 60.0
_REAL_STEP = sumo_mod.libsumo.simulationStep
_REAL_TRAFFIC_STEP = sumo_mod.SumoTraffic.step


class Probe:
    """Wraps libsumo.simulationStep and SumoTraffic.step; ``before`` runs just before each SUMO step."""

    def __init__(self, before=None, mask=None):
        self.before = before
        self.mask = mask  # bool per step: the interference before that step (None: every step)
        self.sumo: list[float] = []
        self.traffic: list[float] = []
        self.extra: list[float] = []  # the interference's own CPU, left out of the getters

    def __enter__(self):
        probe = self

        def step(*a, **k):
            c0 = time.process_time()
            if probe.before is not None and (probe.mask is None or probe.mask[len(probe.sumo) % probe.mask.size]):
                probe.before()
            c1 = time.process_time()
            probe.extra.append(c1 - c0)
            c0 = c1
            out = _REAL_STEP(*a, **k)
            probe.sumo.append(time.process_time() - c0)
            return out

        def traffic_step(self_):
            c0 = time.process_time()
            out = _REAL_TRAFFIC_STEP(self_)
            probe.traffic.append(time.process_time() - c0)
            return out

        sumo_mod.libsumo.simulationStep = step
        sumo_mod.SumoTraffic.step = traffic_step
        return self

    def __exit__(self, *exc):
        sumo_mod.libsumo.simulationStep = _REAL_STEP
        sumo_mod.SumoTraffic.step = _REAL_TRAFFIC_STEP


@njit(cache=True)
def _chain(n):
    x = 1.0
    for _ in range(n):
        x = x * 1.0000001 + 1e-9
    return x


def _calibrate(seconds: float) -> int:
    _chain(10)
    c0 = time.process_time()
    _chain(10_000_000)
    return int(10_000_000 * seconds / max(time.process_time() - c0, 1e-6))


def interference(kind: str, arg: float):
    if kind in ("idealised", "realistic"):
        return None
    if kind == "touch":
        buf = np.zeros(int(arg * 2**20) // 8)

        def touch():
            np.add(buf, 1.0, out=buf)
        return touch
    if kind == "alloc":
        n = max(1, int(arg * 2**20) // 8192)

        def alloc():
            keep = [np.full(1024, 1.0) for _ in range(n)]
            del keep
        return alloc
    if kind == "spin":
        def spin():
            end = time.process_time() + arg * 1e-3
            while time.process_time() < end:
                pass
        return spin
    if kind == "compute":  # no memory, no system call: a dependent chain of multiplies in registers
        n = _calibrate(arg * 1e-3)
        return lambda: _chain(n)
    if kind == "none":  # the method's null: the same bookkeeping, nothing done
        return lambda: None
    if kind == "sleep":
        return lambda: time.sleep(arg * 1e-3)
    raise SystemExit(f"unknown variant {kind!r}")


class _Feed:
    """A realistic coupler's traffic: the states the idealised run's SUMO produced last (vehicle rows matched by
    id, since the realistic sensing does not see every step)."""

    def __init__(self):
        self.states = None

    def step(self):
        return dataclasses.replace(self.states, prev_row=None)

    def done(self) -> bool:
        return False


def paired(variant: str, ideal, real, skip: int, seed: int) -> tuple:
    """One idealised run with the interference before a seeded random half of the steps: (median SUMO step
    after it, median without it, mean after, mean without, the getters' median after and without), microseconds
    (the same machine state for both).
    ``realistic``: the realistic preset's frame synthesis on the idealised run's latest states."""
    kind, _, arg = variant.partition(":")
    scenario = sumo_scenario(ideal, load_net_folder(ideal.net_dir))
    mask = np.random.default_rng(seed).random(4096) < 0.5
    before = interference(kind, float(arg or 0))
    feed = None
    if kind == "realistic":
        feed = _Feed()
        rc = SumoCoupler(sumo_scenario(real, load_net_folder(real.net_dir)), real.sensors)
        rc.traffic = feed
        gen = rc.frames()

        def before():
            if feed.states is not None:
                next(gen)
    with Probe(before, mask) as probe, SumoCoupler(scenario, ideal.sensors) as coupler:
        if feed is not None:
            traffic_step = sumo_mod.SumoTraffic.step

            def step_and_feed(self_):
                feed.states = traffic_step(self_)
                return feed.states
            sumo_mod.SumoTraffic.step = step_and_feed
        for _ in coupler.frames():
            pass
    s = np.array(probe.sumo) * 1e6
    g = (np.array(probe.traffic) - np.array(probe.sumo) - np.array(probe.extra)) * 1e6
    on = mask[: s.size].copy()
    on[:skip] = False
    off = ~mask[: s.size]
    off[:skip] = False
    return (float(np.median(s[on])), float(np.median(s[off])), float(s[on].mean()), float(s[off].mean()),
            float(np.median(g[on])), float(np.median(g[off])))


def run(variant: str, ideal, real, skip: int) -> tuple[float, float, float, float, float]:
    kind, _, arg = variant.partition(":")
    cfg = real if kind == "realistic" else ideal
    scenario = sumo_scenario(cfg, load_net_folder(cfg.net_dir))
    c0 = time.process_time()
    with Probe(interference(kind, float(arg or 0))) as probe, SumoCoupler(scenario, cfg.sensors) as coupler:
        for _ in coupler.frames():
            pass
    total = time.process_time() - c0
    s = np.array(probe.sumo[skip:]) * 1e6
    g = (np.array(probe.traffic[skip:]) - np.array(probe.sumo[skip:]) - np.array(probe.extra[skip:])) * 1e6
    return float(np.median(s)), float(s.mean()), float(np.median(g)), float(g.mean()), total


def measure(real, skip: int) -> None:
    """The realistic synthesis' CPU a step and its transient heap (tracemalloc's peak above the start)."""
    import tracemalloc

    scenario = sumo_scenario(real, load_net_folder(real.net_dir))
    cpu, peak = [], []
    with SumoCoupler(scenario, real.sensors) as coupler:
        it = coupler.frames()
        while True:
            c0 = time.process_time()
            try:
                next(it)
            except StopIteration:
                break
            cpu.append(time.process_time() - c0)
    with Probe() as probe, SumoCoupler(scenario, real.sensors) as coupler:
        tracemalloc.start()
        for _ in coupler.frames():
            cur, pk = tracemalloc.get_traced_memory()
            peak.append(pk - cur)
            tracemalloc.reset_peak()
        tracemalloc.stop()
    print(f"realistic frame CPU a step: median {1e3 * np.median(cpu[skip:]):.2f} ms; transient heap peak a step "
          f"(tracemalloc): median {np.median(peak[skip:]) / 2**20:.2f} MiB, max {np.max(peak[skip:]) / 2**20:.2f} MiB")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--variants", default="idealised,realistic,touch:4,alloc:4,spin:4,sleep:4")
    ap.add_argument("--measure", action="store_true")
    ap.add_argument("--no-gc", action="store_true", help="Python's cyclic garbage collector off for the timed runs")
    ap.add_argument("--paired", action="store_true",
                    help="each interference before a seeded random half of one idealised run's steps: SUMO's step "
                         "after it against without it, in the same run")
    args = ap.parse_args()
    over = {"run.duration_s": args.duration, "run.seed": 1}
    ideal = load_config(ROOT / "experiments" / "arterial_tlr.toml", over)
    real = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml", over)
    skip = int(round(WARM_S / ideal.scenario.step_s))  # steps of the warm-up, left out
    if args.measure:
        measure(real, skip)
        return
    variants = args.variants.split(",")
    if args.no_gc:
        gc.disable()
    warm = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml", {**over, "run.duration_s": 60.0})
    run("realistic", ideal, warm, 0)  # numba caches loaded, not timed
    if args.paired:
        res = {v: [] for v in variants}
        for r in range(args.rounds):
            for v in variants:
                res[v].append(paired(v, ideal, real, skip, 100 + r))
                x = res[v][-1]
                print(f"round {r} {v:<12} SUMO step after it: median {x[0]:7.1f} us (mean {x[2]:7.1f}), without: "
                      f"{x[1]:7.1f} (mean {x[3]:7.1f}) | getters {x[4]:6.1f} / {x[5]:6.1f} | load "
                      f"{os.getloadavg()[0]:.1f}", flush=True)
        print("variant      SUMO step after it - without (us), median over rounds of the runs' median differences "
              "[rounds]; ratio after / without; the getters' difference")
        for v, rows in res.items():
            a = np.array(rows)
            d = a[:, 0] - a[:, 1]
            dg = a[:, 4] - a[:, 5]
            print(f"{v:<12} {np.median(d):+7.1f}  [{' '.join(f'{x:+.0f}' for x in d)}]  "
                  f"{np.median(a[:, 0] / a[:, 1]):.3f}   getters {np.median(dg):+6.1f} "
                  f"[{' '.join(f'{x:+.0f}' for x in dg)}]")
        return
    res = {v: [] for v in variants}
    for r in range(args.rounds):
        for v in variants:
            res[v].append(run(v, ideal, real, skip))
            print(f"round {r} {v:<12} step median {res[v][-1][0]:7.1f} us mean {res[v][-1][1]:7.1f} | getters "
                  f"median {res[v][-1][2]:6.1f} mean {res[v][-1][3]:6.1f} | run CPU {res[v][-1][4]:.2f} s "
                  f"| load {os.getloadavg()[0]:.1f}", flush=True)
    print("variant        SUMO step median / mean (us), getters median / mean (us): median over rounds [rounds]")
    for v, rows in res.items():
        a = np.array(rows)
        print(f"{v:<12} {np.median(a[:, 0]):7.1f} / {np.median(a[:, 1]):7.1f}   {np.median(a[:, 2]):6.1f} / "
              f"{np.median(a[:, 3]):6.1f}   [{' '.join(f'{x:.0f}' for x in a[:, 0])}]")


if __name__ == "__main__":
    main()
