"""The ``coloc`` command line: run, sweep, report, net import / net check.

Bad input prints one line naming the file and field and exits with status 2;
no traceback, nothing half-written.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

from couplers.errors import InputError

EXIT_INPUT = 2
EXIT_FAILED = 1  # the command failed for another reason than its input (an estimator worker's error)
EXIT_INTERRUPTED = 130  # 128 + SIGINT
EXIT_TERMINATED = 143  # 128 + SIGTERM


class Terminated(BaseException):
    """SIGTERM, raised where the command is, so the same clean-up as for Ctrl-C runs."""


_MAIN_PID: int | None = None  # the process whose SIGTERM becomes Terminated


def _on_sigterm(signum, frame):
    if os.getpid() != _MAIN_PID:
        # A forked worker (the import's gridlock trials, a study's process pool) inherited the handler:
        # a pool ends its workers with SIGTERM, which must end them quietly, as it would by default.
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        os.kill(os.getpid(), signal.SIGTERM)
        return
    raise Terminated()


def _methods(text: str) -> list[str]:
    return [m.strip() for m in text.split(",") if m.strip()]


def cmd_run(args: argparse.Namespace) -> int:
    from couplers.errors import read_toml
    from couplers.publish import check_target
    from experiments.config import load_config
    from experiments.runner import run_experiment
    from experiments.studies import is_study, run_study

    if args.workers < 0:
        raise InputError(None, "--workers", "must be >= 0")
    check_target(Path(args.out), ("run",), force=args.force)  # before anything is read or simulated
    data = read_toml(args.config, "config file")
    if is_study(data):  # a study of another source paper (experiments/studies)
        summary = run_study(data, Path(args.config), Path(args.out), args.seed, progress=not args.quiet,
                            force=args.force)
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
    if not args.quiet:
        from experiments.warm import cold_cache_note

        note = cold_cache_note()
        if note is not None:
            print(note + "...", file=sys.stderr, flush=True)
    summary = run_experiment(cfg, Path(args.out), progress=None if not args.quiet else False, force=args.force,
                             workers=args.workers)
    for method, block in summary["methods"].items():
        if block["rmse_pos_m"] is None:  # nothing scored, e.g. a run no longer than its [analysis] warm-up
            warmup = cfg.analysis.warmup_s if cfg.analysis is not None else 0.0
            print(f"{method:>14}: no estimate scored" + (f" (none after the warm-up, analysis.warmup_s = {warmup:g} "
                                                          "s: run longer)" if warmup else ""))
            continue
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
    cov = summary.get("within_rsu_coverage")
    if cov:  # infrastructure mode: the same covered vehicle-steps for every method
        for method, block in cov["methods"].items():
            if block.get("rmse_pos_m") is not None:
                print(f"{method:>14}: within RSU coverage RMSE {block['rmse_pos_m']:.2f} m, "
                      f"p95 {block['p95_pos_m']:.2f} m, n {block['n']}")
    tr = summary["traffic"]
    if tr is not None:  # None for the controlled scenarios (no SUMO traffic)
        print(
            f"{'traffic':>14}: {tr['mean_vehicles']:.0f} vehicles in net, exit flow {tr['exit_flow_vph']:.0f} veh/h, "
            f"mean queue {tr['mean_queue']:.1f}, stop time {tr['stop_time_s_per_km']:.1f} s/km, "
            f"teleports {tr['teleports']}"
        )
        if "inserted" in tr:
            print(f"{'vehicles':>14}: {traffic_losses_line(tr)}")
    print(f"wrote {args.out}/report.html")
    return 0


def traffic_losses_line(tr: dict) -> str:
    """The run line of the demand's vehicles: inserted, never inserted, dropped by SUMO at load, teleported,
    in collisions, and JAMMED by the import's gridlock rule (couplers.net.gridlock)."""
    text = (f"{tr['inserted']} inserted, {tr['never_inserted']} never inserted (still waiting at the end), "
            f"{tr['dropped_at_load']} dropped by SUMO at load, {tr['teleports']} teleports, "
            f"{tr['collisions']} in collisions")
    if tr["dropped_at_load"]:
        why = []
        if tr.get("dropped_unsorted"):
            why.append(f"{tr['dropped_unsorted']} because a route file is not sorted by departure")
        if tr.get("dropped_no_route"):
            why.append(f"{tr['dropped_no_route']} without a route")
        text += f" [{'; '.join(why)}; first: {tr.get('first_dropped', '?')}]"
    if tr.get("jammed"):
        text += f"; JAMMED by the gridlock rule: {tr['jam_verdict']}"
    return text


def _sweep_or_stop(run):
    """``run()`` (a sweep or a tuning pass) and None, or None and the exit code of a failed or stopped pass
    (its completed runs are kept for a resume)."""
    from experiments.sweep.run import SweepFailed

    try:
        return run(), 0
    except SweepFailed as exc:
        print(f"coloc: error: {exc}", file=sys.stderr)
        return None, 1
    except (KeyboardInterrupt, Terminated) as exc:
        print(f"coloc: {_stopped(exc)}; completed runs are kept: rerun the same command to resume", file=sys.stderr)
        return None, _stop_code(exc)
    except SystemError as exc:  # the signal's exception raised inside a C callback (_stop_in_chain)
        stop = _stop_in_chain(exc)
        if stop is None:
            raise
        print(f"coloc: {_stopped(stop)}; completed runs are kept: rerun the same command to resume", file=sys.stderr)
        return None, _stop_code(stop)


def cmd_sweep(args: argparse.Namespace) -> int:
    from experiments.sweep.run import run_sweep

    if args.workers is not None and args.workers < 1:
        raise InputError(None, "--workers", "must be >= 1")
    res, code = _sweep_or_stop(lambda: run_sweep(args.sweep, Path(args.out), scheduler=args.scheduler,
                                                 workers=args.workers, progress=not args.quiet,
                                                 dry_run=args.dry_run, force=args.force))
    if res is None:
        return code
    if res.dry_run:
        print(f"{args.sweep}: valid, {res.n_runs} runs (nothing was run)")
        return 0
    where = (f"scheduler {args.scheduler}" if args.scheduler else f"{res.workers} local workers"
             if res.computed else "this process (nothing to compute)")
    if res.workers_asked is not None and res.computed and not args.scheduler:
        where += f" (--workers {res.workers_asked} capped: at most the runs to compute and the usable cores)"
    again = f", {res.recomputed} of them again after their inputs changed" if res.recomputed else ""
    print(f"{res.n_runs} runs ({res.computed} computed{again}, {res.present} already present) in {res.seconds:.1f} s "
          f"on {where}")
    print(f"wrote {res.out}/sweep.parquet, {res.out}/curves.parquet, {res.out}/report.html")
    return 0


def cmd_tune(args: argparse.Namespace) -> int:
    from experiments.sweep.run import run_sweep
    from experiments.sweep.tune import tuning_spec, write_tuning

    if args.workers is not None and args.workers < 1:
        raise InputError(None, "--workers", "must be >= 1")
    spec = tuning_spec(args.sweep)
    res, code = _sweep_or_stop(lambda: run_sweep(args.sweep, Path(args.out), workers=args.workers,
                                                 progress=not args.quiet, dry_run=args.dry_run, force=args.force,
                                                 write_report=False, spec=spec))
    if res is None:
        return code
    if res.dry_run:
        print(f"{args.sweep}: valid, {res.n_runs} tuning runs on seeds {list(spec.seeds)} (nothing was run)")
        return 0
    table, tuned = write_tuning(spec, res.out, spec.path)
    best = table[table["rank"] == 1].iloc[0]
    chosen = ", ".join(f"{k} = {best[k]}" for k in spec.grid_keys)
    print(f"{res.n_runs} tuning runs in {res.seconds:.1f} s; chosen {chosen} "
          f"({spec.objective[0]} {spec.objective[1]} {best['objective_mean']:.4f} m over {int(best['seeds'])} seeds)")
    print(f"wrote {tuned}, {res.out}/tuned.resolved.toml, {res.out}/tuning.parquet")
    return 0


RUN_FILES = ("summary.json", "estimates.parquet", "traffic.parquet", "config.toml")


def _check_run_folder(d: Path) -> None:
    """A folder ``coloc report`` can read as a run: say what it is instead when it is not one."""
    from couplers.publish import output_kind

    if not d.exists():
        raise InputError(d, None, "no such folder")
    if not d.is_dir():
        raise InputError(d, None, "is a file, not a run output folder")
    missing = [name for name in RUN_FILES if not (d / name).is_file()]
    if not missing:
        return
    kind = output_kind(d)
    if kind not in (None, "run"):
        raise InputError(d, None, f"holds a coloc {kind} output, not a run output"
                                  + (" (give a sweep folder alone, without --out)" if kind == "sweep" else ""))
    if len(missing) == len(RUN_FILES):
        inside = sorted(p.name for p in d.iterdir() if p.is_dir() and (p / "summary.json").is_file())
        if inside:  # e.g. a sweep's runs/ folder
            raise InputError(d, None, f"holds no run output itself but {len(inside)} run folder(s) in it "
                                      f"(e.g. {inside[0]}): give those")
        raise InputError(d, None, f"holds no coloc run output (none of {', '.join(RUN_FILES)}): "
                                  "give the --out folder of a `coloc run`")
    raise InputError(d / missing[0], None, "missing: the run folder is incomplete"
                                           + (f" (also missing: {', '.join(missing[1:])})" if len(missing) > 1 else ""))


def cmd_report(args: argparse.Namespace) -> int:
    from experiments.report import write_comparison_report, write_run_report
    from experiments.report.parallel import available_workers

    dirs = [Path(d) for d in args.dirs]
    if len(dirs) == 1 and args.out is None and (dirs[0] / "sweep.toml").is_file():
        from experiments.sweep.report import write_sweep_report

        for name in ("sweep.parquet", "curves.parquet"):
            if not (dirs[0] / name).is_file():
                raise InputError(dirs[0] / name, None, "not found: has this sweep finished?")
        print(f"wrote {write_sweep_report(dirs[0], force=args.force)}")
        return 0
    for d in dirs:
        _check_run_folder(d)
    if len(dirs) == 1 and args.out is None:
        path = write_run_report(dirs[0], workers=available_workers(), force=args.force)
    else:
        out = Path(args.out) if args.out else dirs[0].parent / "compare"
        path = write_comparison_report(dirs, out, force=args.force, workers=available_workers())
    print(f"wrote {path}")
    return 0


def _kinds(text: str) -> tuple[str, ...]:
    return tuple(k.strip() for k in text.split(",") if k.strip())


def cmd_net_import(args: argparse.Namespace) -> int:
    from couplers.net.importer import ImportOptions, import_net
    from experiments.netconfigs import config_names, net_configs, realistic_values

    out = Path(args.out) if args.out else Path("sumo_nets") / args.name
    experiments_dir = Path(args.experiments_dir)
    routes = _route_paths(args.routes)
    if routes or args.sumocfg:  # the options that shape the generated demand: refused, not recorded unused
        given = "--sumocfg" if args.sumocfg else "--routes"
        for flag, val in (("--demand", args.demand), ("--duration", args.duration)):
            if val is not None:
                raise InputError(None, flag, f"not with {given}: it shapes the generated demand, and the demand is "
                                             f"{'the scenario' if args.sumocfg else 'your route file'}'s"
                                             + (" (its begin/end come from the configuration)" if args.sumocfg else ""))
    demand = args.demand if args.demand is not None else (2800.0, 1800.0)
    opts = ImportOptions(
        name=args.name, out=out, net=_path(args.net), osm=_path(args.osm), seed=args.seed,
        feature_count=args.features, feature_kinds=_kinds(args.feature_kinds), guess_signals=args.guess_signals,
        zones=_path(args.zones), areas=_path(args.areas), routes=(routes[0] if len(routes) == 1 else routes) or None,
        additional=_path(args.additional), demand_start_vph=demand[0], demand_end_vph=demand[1],
        demand_scale=args.demand_scale, fringe_factor=args.fringe_factor,
        duration_s=args.duration if args.duration is not None else 3600.0, sumocfg=_path(args.sumocfg),
        zone_cell_m=args.zone_cell, calibrate=not args.no_calibrate, calibration_s=args.calibration_s,
        max_density_scale=args.max_density_scale,
        signals="rebuild" if args.rebuild_signals else "keep" if args.keep_signals else "check",
        sort_routes=args.sort_routes, force=args.force,
    )
    source = (opts.sumocfg or opts.osm or opts.net).name if (opts.sumocfg or opts.osm or opts.net) else "?"
    if not args.force:  # refuse before the (possibly long) import, not after it
        for cfg_name in config_names(args.name):
            cfg = experiments_dir / cfg_name
            if cfg.exists():
                raise InputError(cfg, None, "already exists (pass --force to replace it)")

    def configs(result):
        return net_configs(args.name, out, experiments_dir, result.track_area, source,
                           clock=result.summary["derived"].get("sumocfg"),
                           realistic=realistic_values(result.staged, result.track_area, args.seed, args.occlusion_s,
                                                      print))

    res = import_net(opts, finalize=configs)
    for line in res.lines:
        print(line)
    written = ", ".join(f"{experiments_dir}/{n}" for n in config_names(args.name))
    print(f"wrote {out} in {res.seconds:.1f} s, and {written}")
    print(f"next: coloc net check {out}; coloc run {experiments_dir}/{args.name}_tlr.toml --out results/{args.name}_tlr")
    return 0


def _path(text: str | None) -> Path | None:
    return None if text is None else Path(text)


def _route_paths(values: list[str] | None) -> tuple[Path, ...]:
    """``--routes`` given once or more, each one file or a comma-separated list."""
    return tuple(Path(x.strip()) for v in values or () for x in v.split(",") if x.strip())


def cmd_net_check(args: argparse.Namespace) -> int:
    from couplers.net.check import check_net_folder

    problems, info = check_net_folder(Path(args.dir), max_feature_distance_m=args.max_feature_distance)
    for p in problems:
        print(p)
    if problems:
        print(f"{args.dir}: {len(problems)} problem(s)", file=sys.stderr)
        return 1
    print(f"{args.dir}: ok ({info})")
    return 0


class _VersionAction(argparse.Action):
    """``coloc --version``: coloc, SUMO (the libsumo in use) and Python; looked up only when asked."""

    def __init__(self, option_strings, dest=argparse.SUPPRESS, default=argparse.SUPPRESS, help=None):
        super().__init__(option_strings, dest=dest, default=default, nargs=0, help=help)

    def __call__(self, parser, namespace, values, option_string=None):
        import importlib.metadata
        import platform

        from couplers.traffic.sumo import sumo_version

        try:
            coloc = importlib.metadata.version("coloc")
        except importlib.metadata.PackageNotFoundError:  # run from a source tree that is not installed
            coloc = "unknown (not installed)"
        sumo = sumo_version()  # libsumo's own string, e.g. "SUMO 1.28.0"
        print(f"coloc {coloc}, {sumo if sumo.startswith('SUMO') else 'SUMO ' + sumo}, "
              f"Python {platform.python_version()}")
        parser.exit()


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="coloc", description="Traffic-coupled evaluation of cooperative vehicle localization.")
    p.add_argument("--version", action=_VersionAction, help="print the coloc, SUMO and Python versions and exit")
    sub = p.add_subparsers(dest="command", required=True)

    r = sub.add_parser("run", help="one run of an experiment config")
    r.add_argument("config", help="experiment TOML, e.g. experiments/arterial_tlr.toml")
    r.add_argument("--out", required=True, help="output folder: absent, empty or an earlier run's (coloc's files "
                                                "replaced when the run finishes; other files kept)")
    r.add_argument("--force", action="store_true", help="write into --out even if coloc did not write it, or "
                                                        "through a symbolic link (nothing is deleted: files in the "
                                                        "way are kept as NAME.before-coloc; never a file)")
    r.add_argument("--seed", type=int, help="override [run] seed")
    r.add_argument("--duration", type=float, help="override [run] duration_s (simulated seconds)")
    r.add_argument("--methods", help="override [run] methods, comma separated (e.g. gnss)")
    r.add_argument("--quiet", action="store_true", help="no progress bar")
    r.add_argument("--workers", type=int, default=0,
                   help="spread the estimators over this process and this many worker processes, by the "
                        "registry's cost of each (default 0: all in this process; 1 is the fastest on 2 cores); "
                        "the same files, byte for byte")
    r.set_defaults(func=cmd_run)

    sw = sub.add_parser("sweep", help="Monte Carlo / parameter sweep on Dask (resumable)")
    sw.add_argument("sweep", help="sweep TOML, e.g. experiments/sweeps/fig7_single_road.toml")
    sw.add_argument("--out", required=True, help="sweep folder (runs/, sweep.parquet, curves.parquet, report.html): "
                                                 "absent, empty or this sweep's")
    sw.add_argument("--force", action="store_true", help="write into --out even if coloc did not write it")
    sw.add_argument("--scheduler", help="address of a running Dask scheduler (default: a local cluster)")
    sw.add_argument("--workers", type=int, help="local worker processes (default: min(CPUs, 4)); at most the runs "
                                                "still to compute and the usable cores")
    sw.add_argument("--dry-run", action="store_true", help="validate the sweep and every config; run nothing")
    sw.add_argument("--quiet", action="store_true", help="no progress bar")
    sw.set_defaults(func=cmd_sweep)

    tu = sub.add_parser("tune", help="choose [sweep.grid] values on the sweep's tune_seeds only (objective: "
                                     "[sweep] objective); writes an extends overlay, tuned.toml")
    tu.add_argument("sweep", help="sweep TOML with tune_seeds, eval_seeds, objective and a grid of candidates")
    tu.add_argument("--out", required=True, help="tuning folder (a sweep folder of the tuning runs, tuned.toml)")
    tu.add_argument("--force", action="store_true", help="write into --out even if coloc did not write it")
    tu.add_argument("--workers", type=int, help="local worker processes (default: min(CPUs, 4))")
    tu.add_argument("--dry-run", action="store_true", help="validate; run nothing")
    tu.add_argument("--quiet", action="store_true", help="no progress bar")
    tu.set_defaults(func=cmd_tune)

    rep = sub.add_parser("report", help="rebuild a run's or a sweep's report, or compare several runs")
    rep.add_argument("dirs", nargs="+", help="run output folders (or one sweep folder)")
    rep.add_argument("--out", help="comparison output folder (default: <first>/../compare): absent, empty or "
                                   "an earlier comparison's")
    rep.add_argument("--force", action="store_true", help="write into --out (or a run folder) even if coloc did not "
                                                          "write it; files in the way are kept as NAME.before-coloc")
    rep.set_defaults(func=cmd_report)

    net = sub.add_parser("net", help="plug-in nets: import a SUMO net or an OSM extract, check a net folder")
    nsub = net.add_subparsers(dest="net_command", required=True)
    ni = nsub.add_parser("import", help="build a net folder and TLR/VSR configs from a .net.xml, .osm[.gz] or "
                                        ".sumocfg")
    src = ni.add_mutually_exclusive_group(required=True)
    src.add_argument("--net", help="a SUMO net (FILE.net.xml)")
    src.add_argument("--osm", help="an OpenStreetMap extract (FILE.osm or FILE.osm.gz)")
    src.add_argument("--sumocfg", help="a SUMO scenario (FILE.sumocfg): its net, route files, additional files and "
                                       "its clock (begin/end/step-length), kept by the runs")
    ni.add_argument("--name", required=True, help="name of the net folder and of the configs")
    ni.add_argument("--out", help="net folder to write (default: sumo_nets/NAME)")
    ni.add_argument("--experiments-dir", default="experiments",
                    help="where NAME_tlr.toml, NAME_vsr.toml and their _realistic variants go "
                         "(default: experiments)")
    ni.add_argument("--seed", type=int, default=1, help="seed of trips, route choice and feature choice (default 1)")
    ni.add_argument("--features", type=int, default=64, help="number of features (default 64, the paper's)")
    ni.add_argument("--feature-kinds", default="traffic_light,bus_stop,parking,sign",
                    help="comma-separated kinds to place (default: all four)")
    ni.add_argument("--guess-signals", action="store_true",
                    help="let netconvert place traffic lights at major junctions (needed when the net has none)")
    sig = ni.add_mutually_exclusive_group()
    sig.add_argument("--rebuild-signals", action="store_true",
                     help="let netconvert rebuild every signal program (--tls.rebuild: static, 90 s cycle), e.g. "
                          "when the import reports implausible programs (a cycle over 300 s, approaches never green)")
    sig.add_argument("--keep-signals", action="store_true",
                     help="import implausible signal programs as they are (default: refuse and name them)")
    ni.add_argument("--zones", help="GNSS zones GeoJSON, WGS84 lon/lat (RFC 7946; converted with the net's "
                                    "projection) or net x/y (crs urn:coloc:sumo-net-xy); "
                                    "default: from building density, else a default layout")
    ni.add_argument("--areas", help="analysis areas GeoJSON, WGS84 lon/lat or net x/y (as --zones); "
                                    "default: a 3 x 2 grid")
    ni.add_argument("--routes", action="append",
                    help="your own SUMO route file(s) instead of the generated demand (plain or .gz; repeat the "
                         "option or separate files by commas)")
    ni.add_argument("--sort-routes", action="store_true",
                    help="sort the vehicles of your route files by departure in the folder's copy (default: a file "
                         "not sorted by departure is refused, SUMO would drop the vehicles out of order)")
    ni.add_argument("--additional", help="busStop / parkingArea additionals for a --net input (feature places)")
    ni.add_argument("--demand", type=float, nargs=2, metavar=("START", "END"),
                    help="falling profile on the arterial, veh/h at the start and end of the hour (default 2800 1800; "
                         "generated demand only)")
    ni.add_argument("--demand-scale", type=float, default=1.0,
                    help="multiplies the demand after scaling it to the net's size (default 1)")
    ni.add_argument("--fringe-factor", type=float, default=10.0,
                    help="randomTrips --fringe-factor: weight of trips entering/leaving at the net's edge (default 10)")
    ni.add_argument("--duration", type=float, help="generated demand's duration, s (default 3600)")
    ni.add_argument("--max-density-scale", type=float, default=4.0,
                    help="cap of the density match, as a multiple of the arterial's demand (default 4)")
    ni.add_argument("--no-calibrate", action="store_true",
                    help="keep the density-matched demand (default: scale it down by 0.6 until it runs "
                         "without gridlock under VSR and TLR); with --routes/--sumocfg, skip the gridlock trial "
                         "of your demand (which is reported, never rescaled)")
    ni.add_argument("--calibration-s", type=float,
                    help="simulated seconds of each gridlock trial (default: the whole demand, --duration)")
    ni.add_argument("--zone-cell", type=float, default=200.0, help="cell size of building-density zones, m")
    ni.add_argument("--occlusion-s", type=float, default=600.0,
                    help="simulated seconds (from the begin, per control) of the occlusion measurement that sets "
                         "[lc] visibility in the realistic configs (default 600; 0: keep the arterial's)")
    ni.add_argument("--force", action="store_true", help="replace an existing folder and configs")
    ni.set_defaults(func=cmd_net_import)
    nc = nsub.add_parser("check", help="validate a net folder: one line per problem, non-zero exit if any")
    nc.add_argument("dir", help="net folder, e.g. sumo_nets/arterial")
    nc.add_argument("--max-feature-distance", type=float, default=30.0,
                    help="features farther than this from a drivable lane are a problem (default 30 m)")
    nc.set_defaults(func=cmd_net_check)
    return p


def _stop_in_chain(exc: BaseException) -> BaseException | None:
    """The Terminated or KeyboardInterrupt that ``exc`` was raised from, if any: a signal handler's exception
    raised while a C callback runs (numba's ``_numba_unpickle`` when a cached kernel is first called) reaches
    Python as a SystemError whose cause is that exception."""
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, (KeyboardInterrupt, Terminated)):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


def _stopped(exc: BaseException) -> str:
    return "terminated" if isinstance(exc, Terminated) else "interrupted"


def _stop_code(exc: BaseException) -> int:
    return EXIT_TERMINATED if isinstance(exc, Terminated) else EXIT_INTERRUPTED


def _from_a_worker(exc: Exception) -> bool:
    """An estimator worker's failure (``run --workers``); any other exception keeps its traceback."""
    pipeline = sys.modules.get("experiments.pipeline")  # not imported: no worker ran
    return pipeline is not None and isinstance(exc, pipeline.EstimatorWorkerError)


def _worker_failed(exc: Exception) -> int:
    """One line for an estimator worker's failure; its traceback only with ``COLOC_DEBUG`` set (not 0)."""
    print(f"coloc: error: {exc}", file=sys.stderr)
    if os.environ.get("COLOC_DEBUG", "") not in ("", "0") and exc.worker_traceback:
        print(exc.worker_traceback.rstrip(), file=sys.stderr)
    return EXIT_FAILED


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    global _MAIN_PID
    _MAIN_PID = os.getpid()
    try:
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    except ValueError:  # not the main thread (an embedding program): leave SIGTERM as it is
        previous = None
    try:
        from experiments.ranges import check_options

        check_options(args.func.__name__, args)  # numeric options in their ranges (experiments/ranges.py)
        return args.func(args)
    except InputError as exc:
        print(f"coloc: error: {exc.describe()}", file=sys.stderr)
        return EXIT_INPUT
    except OSError as exc:  # the file system refused (read-only folder, disk full, ...): not a bug
        where = exc.filename if exc.filename is not None else "output"
        print(f"coloc: error: {where}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_INPUT
    except (KeyboardInterrupt, Terminated) as exc:
        print(f"coloc: {_stopped(exc)}; nothing was written", file=sys.stderr)
        return _stop_code(exc)
    except Exception as exc:
        stop = _stop_in_chain(exc)
        if stop is not None:
            print(f"coloc: {_stopped(stop)}; nothing was written", file=sys.stderr)
            return _stop_code(stop)
        if not _from_a_worker(exc):
            raise
        return _worker_failed(exc)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
