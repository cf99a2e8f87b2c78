"""How much of a frame step the world's numba kernels take, idealised against realistic sensing, on the hour.

Runs the arterial's frames (no estimator) with the idealised sensing of ``experiments/arterial_<control>.toml``
and with the realistic preset's sensing on the same traffic, alternating, each in its own process. In each run,
every numba kernel that ``couplers`` and ``coloc`` call from Python, and libsumo's ``simulationStep``, is wrapped
by a process-time timer; from ``--from`` seconds on (the net full) it prints per step: the whole frame step's CPU,
SUMO's step, the kernels' sum and the largest kernels. The wrappers add about a microsecond a call; kernels called
from inside other kernels are counted in their caller.

    python bench/frame_kernel_share.py --duration 3600 --from 1800 --repeat 3

What it answers: whether the kernels that do the realistic world's work (line of sight, reflections, sight lines,
the receiver's fixes, ...) fit, on their own, in the budget a ratio target of the realistic frames to the
idealised ones leaves (docs/performance.md, "The realistic frames' kernels against the idealised frames").
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def one(control: str, sensing: str, duration: float, start: float, top: int) -> None:
    import libsumo
    from numba.core.registry import CPUDispatcher

    import coloc
    import couplers
    from couplers.net.folder import load_net_folder
    from couplers.sumo_coupler import SumoCoupler
    from experiments.config import load_config
    from experiments.runner import sumo_scenario

    over = {"run.duration_s": duration}
    cfg = load_config(ROOT / "experiments" / f"arterial_{control}.toml", over)
    sensors = cfg.sensors if sensing == "idealised" else \
        load_config(ROOT / "experiments" / f"arterial_{control}_realistic.toml", over).sensors
    scenario = sumo_scenario(cfg, load_net_folder(cfg.net_dir))
    acc: dict[str, list] = {}
    clock = time.process_time

    def timed(name, f):
        def call(*a, **k):
            t = clock()
            out = f(*a, **k)
            cell = acc.setdefault(name, [0.0, 0])
            cell[0] += clock() - t
            cell[1] += 1
            return out
        return call

    wrapped = {}
    for pkg in (couplers, coloc):
        for info in pkgutil.walk_packages(pkg.__path__, pkg.__name__ + "."):
            try:
                mod = importlib.import_module(info.name)
            except Exception:  # a module that needs what this run does not have (e.g. gtsam)
                continue
            for key, value in list(vars(mod).items()):
                if isinstance(value, CPUDispatcher):
                    name = f"{value.py_func.__module__}.{value.py_func.__name__}"
                    wrapped.setdefault(id(value), timed(name, value))
                    setattr(mod, key, wrapped[id(value)])
    libsumo.simulationStep = timed("SUMO", libsumo.simulationStep)
    steps, c0 = 0, None
    with SumoCoupler(scenario, sensors) as coupler:
        for _frame in coupler.frames():
            steps += 1
            if c0 is None and steps * cfg.scenario.step_s >= start:
                acc.clear()
                c0, s0 = clock(), steps
    n = steps - s0
    total = (clock() - c0) / n * 1e3
    sumo = acc.pop("SUMO", [0.0, 0])[0] / n * 1e3
    kernels = sorted(((t / n * 1e3, name) for name, (t, _c) in acc.items()), reverse=True)
    kernel_sum = sum(k for k, _ in kernels)
    print(f"{sensing:>9}: frame step {total:6.3f} ms, SUMO's step {sumo:6.3f} ms, kernels {kernel_sum:6.3f} ms"
          + "".join(f"\n           {t:6.3f} ms  {name}" for t, name in kernels[:top]), flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--control", default="tlr", choices=("tlr", "vsr"))
    ap.add_argument("--duration", type=float, default=3600.0)
    ap.add_argument("--from", dest="start", type=float, default=1800.0, help="count steps from this simulated time")
    ap.add_argument("--repeat", type=int, default=3, help="alternating (idealised, realistic) pairs")
    ap.add_argument("--top", type=int, default=8, help="kernels listed per run")
    ap.add_argument("--one", choices=("idealised", "realistic"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.one:
        one(args.control, args.one, args.duration, args.start, args.top)
        return 0
    for _ in range(args.repeat):
        for sensing in ("idealised", "realistic"):
            subprocess.run([sys.executable, __file__, "--one", sensing, "--control", args.control, "--duration",
                            str(args.duration), "--from", str(args.start), "--top", str(args.top)], check=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
