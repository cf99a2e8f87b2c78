"""The ``coloc`` command line: run, sweep, report (net comes with its issue).

Bad input prints one line naming the file and field and exits with status 2;
no traceback, nothing half-written.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from couplers.errors import InputError

EXIT_INPUT = 2


def _methods(text: str) -> list[str]:
    return [m.strip() for m in text.split(",") if m.strip()]


def cmd_run(args: argparse.Namespace) -> int:
    from couplers.errors import read_toml
    from experiments.config import load_config
    from experiments.runner import run_experiment
    from experiments.studies import is_study, run_study

    data = read_toml(args.config, "config file")
    if is_study(data):  # a study of another source paper (experiments/studies)
        summary = run_study(data, Path(args.config), Path(args.out), args.seed, progress=not args.quiet)
        for line in summary.get("lines", []):
            print(line)
        print(f"wrote {args.out}/report.html")
        return 0
    overrides = {}
    if args.seed is not None:
        overrides["run.seed"] = args.seed
    if args.duration is not None:
        overrides["run.duration_s"] = args.duration
    if args.methods is not None:
        overrides["run.methods"] = _methods(args.methods)
    cfg = load_config(args.config, overrides)
    summary = run_experiment(cfg, Path(args.out), progress=None if not args.quiet else False)
    for method, block in summary["methods"].items():
        print(
            f"{method:>14}: RMSE {block['rmse_pos_m']:.2f} m, p50 {block['p50_pos_m']:.2f} m, "
            f"p95 {block['p95_pos_m']:.2f} m, velocity RMSE {block['rmse_vel_mps']:.3f} m/s"
        )
    for method, block in summary.get("association", {}).items():
        if block.get("correct_pct") is not None:
            print(
                f"{method:>14}: association {block['correct_pct']:.1f} % correct, {block['wrong_pct']:.1f} % wrong, "
                f"{block['discarded_pct']:.1f} % discarded of {block['correct'] + block['wrong'] + block['discarded']} "
                "V2F measurements"
            )
    tr = summary["traffic"]
    if tr is not None:  # None for the controlled scenarios (no SUMO traffic)
        print(
            f"{'traffic':>14}: {tr['mean_vehicles']:.0f} vehicles in net, exit flow {tr['exit_flow_vph']:.0f} veh/h, "
            f"mean queue {tr['mean_queue']:.1f}, stop time {tr['stop_time_s_per_km']:.1f} s/km, "
            f"teleports {tr['teleports']}"
        )
    print(f"wrote {args.out}/report.html")
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    from experiments.sweep import SweepFailed, run_sweep

    if args.workers is not None and args.workers < 1:
        raise InputError(None, "--workers", "must be >= 1")
    try:
        res = run_sweep(args.sweep, Path(args.out), scheduler=args.scheduler, workers=args.workers,
                        progress=not args.quiet, dry_run=args.dry_run)
    except SweepFailed as exc:
        print(f"coloc: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("coloc: interrupted; completed runs are kept: rerun the same command to resume", file=sys.stderr)
        return 130
    if res.dry_run:
        print(f"{args.sweep}: valid, {res.n_runs} runs (nothing was run)")
        return 0
    where = (f"scheduler {args.scheduler}" if args.scheduler else f"{res.workers} local workers"
             if res.computed else "this process (nothing to compute)")
    print(f"{res.n_runs} runs ({res.computed} computed, {res.present} already present) in {res.seconds:.1f} s on {where}")
    print(f"wrote {res.out}/sweep.parquet, {res.out}/curves.parquet, {res.out}/report.html")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from experiments.report import write_comparison_report, write_run_report

    dirs = [Path(d) for d in args.dirs]
    if len(dirs) == 1 and args.out is None and (dirs[0] / "sweep.toml").is_file():
        from experiments.sweep_report import write_sweep_report

        for name in ("sweep.parquet", "curves.parquet"):
            if not (dirs[0] / name).is_file():
                raise InputError(dirs[0] / name, None, "not found: has this sweep finished?")
        print(f"wrote {write_sweep_report(dirs[0])}")
        return 0
    for d in dirs:
        for name in ("summary.json", "estimates.parquet", "traffic.parquet", "config.toml"):
            if not (d / name).is_file():
                raise InputError(d / name, None, "not found: is this a `coloc run` output folder?")
    if len(dirs) == 1 and args.out is None:
        path = write_run_report(dirs[0])
    else:
        out = Path(args.out) if args.out else dirs[0].parent / "compare"
        path = write_comparison_report(dirs, out)
    print(f"wrote {path}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="coloc", description="Traffic-coupled evaluation of cooperative vehicle localization.")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="one run of an experiment config")
    r.add_argument("config", help="experiment TOML, e.g. experiments/arterial_tlr.toml")
    r.add_argument("--out", required=True, help="output folder (replaced atomically when the run finishes)")
    r.add_argument("--seed", type=int, help="override [run] seed")
    r.add_argument("--duration", type=float, help="override [run] duration_s (simulated seconds)")
    r.add_argument("--methods", help="override [run] methods, comma separated (e.g. gnss)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.set_defaults(func=cmd_run)

    sw = sub.add_parser("sweep", help="Monte Carlo / parameter sweep on Dask (resumable)")
    sw.add_argument("sweep", help="sweep TOML, e.g. experiments/sweeps/fig7_single_road.toml")
    sw.add_argument("--out", required=True, help="sweep folder (runs/, sweep.parquet, curves.parquet, report.html)")
    sw.add_argument("--scheduler", help="address of a running Dask scheduler (default: a local cluster)")
    sw.add_argument("--workers", type=int, help="local worker processes (default: min(CPUs, 4))")
    sw.add_argument("--dry-run", action="store_true", help="validate the sweep and every config; run nothing")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.set_defaults(func=cmd_sweep)

    rep = sub.add_parser("report", help="rebuild a run's or a sweep's report, or compare several runs")
    rep.add_argument("dirs", nargs="+", help="run output folders (or one sweep folder)")
    rep.add_argument("--out", help="comparison output folder (default: <first>/../compare)")
    rep.set_defaults(func=cmd_report)
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except InputError as exc:
        print(f"coloc: error: {exc.describe()}", file=sys.stderr)
        return EXIT_INPUT
    except KeyboardInterrupt:
        print("coloc: interrupted; nothing was written", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
