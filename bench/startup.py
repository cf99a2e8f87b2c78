"""Benchmark: how long `coloc run` takes to reach its first simulation step, and `coloc report` to write.

Prints, each the best (minimum) and median wall time of ``--repeat`` fresh processes and their median
CPU time (user + system; on a busy machine wall times stretch, CPU times much less):
  1. ``import experiments.cli`` (what every ``coloc`` command pays before it parses its arguments);
  2. the imports of ``coloc run`` (``experiments.config``, ``experiments.runner``, ``experiments.studies``);
  3. ``coloc run CONFIG --duration 60`` from process start to its first frame and to the end of the
     estimators' first step (the runner's ``COLOC_TIMING=1`` line), and the whole short run;
  4. with ``--report RUN_DIR`` (a finished run, e.g. the TLR hour): ``coloc report`` on a copy of it
     (the CPU time includes the report's figure worker process: it is waited for), and with
     ``--compare RUN_DIR2`` as well (e.g. the VSR hour): ``coloc report RUN_DIR RUN_DIR2 --out ...``,
     the comparison ``make run`` writes (on copies that already have their run reports);
and which of the heavy optional libraries (gtsam, dask, matplotlib, ...) the run path imported.
Start-up targets: first step within 2 s of process start on a warm numba cache; the hour's
report within 3 s. Run once before, to warm the numba cache (``coloc run`` of any config).

    python bench/startup.py [--config experiments/arterial_tlr.toml] [--repeat 5] [--report /tmp/tlr_hour
                            [--compare /tmp/vsr_hour]] [--skip-run]

Not a test: it asserts nothing and prints numbers.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PY = sys.executable
COLOC = str(Path(sys.executable).parent / "coloc")
RUN_IMPORTS = ("import experiments.config, experiments.runner, experiments.studies")
HEAVY = ("gtsam", "dask", "distributed", "matplotlib", "pandas", "pyarrow", "scipy.stats", "scipy.optimize",
         "numba", "libsumo", "sumolib", "shapely", "pyproj", "tqdm")
TIMING = re.compile(r"coloc timing: (.+?) at ([0-9.]+) s after process start, ([0-9.]+) s of CPU")


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _wall(cmd: list[str], cpu: list[float] | None = None, **kw) -> tuple[float, subprocess.CompletedProcess]:
    """Wall seconds of ``cmd``; its CPU seconds (user + system) appended to ``cpu``."""
    c0, t0 = _children_cpu(), time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, **kw)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{proc.stderr}")
    if cpu is not None:
        cpu.append(_children_cpu() - c0)
    return time.perf_counter() - t0, proc


def _line(what: str, values: list[float], cpu: list[float] | None = None) -> None:
    """Best and median wall seconds, and the median CPU seconds (less sensitive to a busy machine)."""
    tail = f"   CPU median {statistics.median(cpu):6.2f} s" if cpu else ""
    print(f"  {what:<48} best {min(values):6.2f} s   median {statistics.median(values):6.2f} s{tail}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "experiments" / "arterial_tlr.toml"))
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--report", help="a finished run folder (e.g. the TLR hour) to time `coloc report` on")
    ap.add_argument("--compare", help="with --report: a second run folder (e.g. the VSR hour) to time the "
                                      "comparison report of the two on")
    ap.add_argument("--skip-run", action="store_true", help="time only the reports (no start-up measurements)")
    args = ap.parse_args()
    if not args.skip_run:
        _startup(args)
    if args.report:
        _reports(args)


def _startup(args: argparse.Namespace) -> None:
    print(f"start-up of `coloc run {Path(args.config).name} --duration {args.duration:g}`, {args.repeat} processes each")
    cpu: list[float] = []
    cli = [_wall([PY, "-c", "import experiments.cli"], cpu)[0] for _ in range(args.repeat)]
    _line("python -c 'import experiments.cli'", cli, cpu)
    cpu = []
    imp = [_wall([PY, "-c", RUN_IMPORTS], cpu)[0] for _ in range(args.repeat)]
    _line("python -c 'import <coloc run's modules>'", imp, cpu)
    _, proc = _wall([PY, "-c", RUN_IMPORTS + "; import sys; print(' '.join(m for m in "
                     f"{HEAVY!r} if m in sys.modules))"])
    print(f"  loaded by coloc run's imports: {proc.stdout.strip() or 'none of ' + ', '.join(HEAVY)}")

    first: dict[str, list[float]] = {}
    first_cpu: dict[str, list[float]] = {}
    whole: list[float] = []
    cpu = []
    with tempfile.TemporaryDirectory() as tmp:
        env = dict(os.environ, COLOC_TIMING="1")
        for _ in range(args.repeat):
            sec, proc = _wall([COLOC, "run", args.config, "--duration", f"{args.duration:g}", "--out",
                               str(Path(tmp) / "run"), "--force", "--quiet"], cpu, env=env)
            whole.append(sec)
            for what, s, c in TIMING.findall(proc.stderr):
                first.setdefault(what, []).append(float(s))
                first_cpu.setdefault(what, []).append(float(c))
    for what, values in first.items():
        _line(f"run: {what}", values, first_cpu[what])
    _line(f"coloc run --duration {args.duration:g}, whole", whole, cpu)


def _reports(args: argparse.Namespace) -> None:
    srcs = [Path(args.report)] + ([Path(args.compare)] if args.compare else [])
    with tempfile.TemporaryDirectory() as tmp:
        copies = []
        for src in srcs:
            copies.append(Path(tmp) / f"{len(copies)}" / src.name)
            shutil.copytree(src, copies[-1], ignore=shutil.ignore_patterns("figures", "report.html"))
        cpu: list[float] = []
        rep = [_wall([COLOC, "report", str(copies[0])], cpu)[0] for _ in range(args.repeat)]
        _line(f"coloc report {srcs[0]}", rep, cpu)
        if args.compare:
            _wall([COLOC, "report", str(copies[1])])  # its run report, so the comparison only compares
            cpu = []
            cmp = [_wall([COLOC, "report", *map(str, copies), "--out", str(Path(tmp) / "compare")], cpu)[0]
                   for _ in range(args.repeat)]
            _line(f"coloc report {srcs[0].name} {srcs[1].name} --out ...", cmp, cpu)


if __name__ == "__main__":
    main()
