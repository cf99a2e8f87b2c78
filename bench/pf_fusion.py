"""Benchmark: ICP-DA-PF with ``[fusion]`` (split CI with the receiver model, coloc/methods/pf_fusion.py) beside
``gnss`` and ``icp_da_lc`` (and, on request, the paper's ICP-DA-PF without ``[fusion]``) on the same frames.

    python bench/pf_fusion.py [--config experiments/arterial_tlr_realistic.toml] [--seeds 1] [--duration 300]
                              [--warmup 60] [--particles 1000] [--frames DIR] [--paper]

The frames are the runner's (experiments.runner.frame_source: the config's sensing, GNSS world and entry
protocol), or with ``--frames DIR`` the recorded ``DIR/frames_<seed>.pkl`` of ``tools/coop_replay.py --record``
(the tuning protocol: 900 s, ``warmup_start`` as recorded; the estimators are then built from CONFIG with that
protocol's ``[run]`` and ``[analysis]``, as ``tools/coop_replay.py`` builds them), cut at ``--duration`` seconds
after the first frame. Each method is built as ``coloc run`` builds it (the config's ``[fusion]``,
``[gnss_model]`` with its report calibration, ``[lc]``, ``[pf]``); ``icp_da_pf+fusion`` takes the config's
``[fusion]`` or the default one, ``icp_da_pf`` (``--paper``) none. Scored: every vehicle-step from ``--warmup``
seconds after the first frame. Prints per seed and then over the seeds, per method and zone (A, B, C, all):
position RMSE and p95 (m), the mean over seeds of each run's mean 2-D position NEES, the median NEES, the share
of samples inside the 95 % ellipse (NEES <= 5.991), and the CPU seconds (time.process_time) of the method's
steps per scored vehicle-step (the warm-up steps are stepped, not timed). Over the seeds the errors and NEES are
pooled (RMSE, p95, median, share; as tools/coop_replay.py). ``--particles``: Jv = Jf (default the config's).
The estimators read the truth-free frame; the score reads the truth. Not a test: it asserts nothing.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.coop_fusion import FusionParams  # noqa: E402
from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_DA_PF  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import build_estimators, frame_source  # noqa: E402
from tools.frame_recording import read_frames  # noqa: E402

INSIDE_95 = 5.991464547107979  # chi-square quantile, 2 dof, 0.95
ZONES = ("A", "B", "C", "all")
FUSED = ICP_DA_PF.name + "+fusion"


def build_arms(cfg, paper: bool) -> dict:
    """The estimators by label: gnss and icp_da_lc as configured, the PF with [fusion] (and without, ``paper``)."""
    gnss, lc = build_estimators(dataclasses.replace(cfg, run=dataclasses.replace(
        cfg.run, methods=[GNSS.name, ICP_DA_LC.name])))
    pf_cfg = dataclasses.replace(cfg, run=dataclasses.replace(cfg.run, methods=[ICP_DA_PF.name]))
    arms = {GNSS.name: gnss, ICP_DA_LC.name: lc}
    if paper:
        arms[ICP_DA_PF.name] = build_estimators(dataclasses.replace(pf_cfg, fusion=None))[0]
    arms[FUSED] = build_estimators(dataclasses.replace(pf_cfg, fusion=cfg.fusion or FusionParams()))[0]
    return arms


def run_seed(cfg, frames, warmup: float, duration: float, paper: bool) -> tuple[dict, int]:
    """Per label: the scored samples' error, NEES and zone and the CPU seconds of the scored steps; and the
    number of scored vehicle-steps. Progress (simulated time, CPU seconds) on stderr every 100 s."""
    arms = build_arms(cfg, paper)
    out = {k: {"err": [], "nees": [], "zone": [], "cpu": 0.0} for k in arms}
    vehicle_steps, t0, shown = 0, None, 0.0
    for frame in frames:
        t0 = frame.t if t0 is None else t0
        if frame.t - t0 > duration:
            break
        if frame.t - t0 >= shown + 100.0:
            shown += 100.0
            print(f"  {frame.t - t0:.0f} s, {frame.n_vehicles} vehicles, {time.process_time():.0f} s CPU",
                  file=sys.stderr, flush=True)
        blind = frame.without_truth()
        timed = frame.t - t0 >= warmup
        zone = np.asarray(frame.truth.zone).astype(str)
        for key, est in arms.items():
            c0 = time.process_time()
            est_out = est.step(blind)
            if not timed:
                continue
            o = out[key]
            o["cpu"] += time.process_time() - c0
            e = frame.truth.x_true[:, :2] - est_out.mean[:, :2]
            o["err"].append(np.sqrt((e * e).sum(axis=1)))
            o["nees"].append(np.einsum("ni,ni->n", e, np.linalg.solve(est_out.cov[:, :2, :2], e[..., None])[..., 0]))
            o["zone"].append(zone)
        if timed:
            vehicle_steps += frame.n_vehicles
    for o in out.values():
        for k in ("err", "nees", "zone"):
            o[k] = np.concatenate(o[k]) if o[k] else np.empty(0)
    return out, vehicle_steps


def cells(runs: list[dict]) -> list[str]:
    """Per zone: RMSE / p95, ANEES (mean over runs of the run's mean), median NEES, inside 95 % (pooled)."""
    res = []
    for z in ZONES:
        sel = [np.ones(r["zone"].size, bool) if z == "all" else r["zone"] == z for r in runs]
        if not any(m.any() for m in sel):
            res.append("-")
            continue
        e = np.concatenate([r["err"][m] for r, m in zip(runs, sel)])
        q = np.concatenate([r["nees"][m] for r, m in zip(runs, sel)])
        anees = np.mean([r["nees"][m].mean() for r, m in zip(runs, sel) if m.any()])
        res.append(f"{np.sqrt(np.mean(e ** 2)):.2f} / {np.percentile(e, 95):.2f}, {anees:.2f}, {np.median(q):.2f}, "
                   f"{100 * np.mean(q <= INSIDE_95):.1f}")
    return res


def protocol_config(base: Path, seed: int, folder: Path) -> Path:
    """The recorded frames' protocol (tools/coop_replay.py): 900 s, [analysis] warmup 600 s, sensed start."""
    cfg = folder / f"cfg_{seed}.toml"
    cfg.write_text(f'extends = "{base.resolve()}"\n[run]\nseed = {seed}\nduration_s = 900.0\nmethods = ["gnss"]\n'
                   '[analysis]\nwarmup_s = 600.0\nwarmup_start = "sensed"\n')
    return cfg


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "experiments" / "arterial_tlr_realistic.toml"))
    ap.add_argument("--seeds", default="1")
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--warmup", type=float, default=60.0)
    ap.add_argument("--particles", type=int, default=0)
    ap.add_argument("--frames", type=Path, help="replay DIR/frames_<seed>.pkl (tools/coop_replay.py --record)")
    ap.add_argument("--paper", action="store_true", help="also the paper's icp_da_pf (no [fusion])")
    ap.add_argument("--dump", type=Path, help="write each seed's scored samples to DUMP/pf_fusion_<seed>.npz")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    over = {}
    if args.particles:
        over.update({"pf.vehicle_particles": args.particles, "pf.feature_particles": args.particles})
    runs, steps, jv = [], [], 0
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            if args.frames is not None:
                cfg = load_config(protocol_config(Path(args.config), seed, Path(tmp)), over)
                res = run_seed(cfg, read_frames(args.frames / f"frames_{seed}.pkl"), args.warmup, args.duration,
                               args.paper)
            else:
                cfg = load_config(Path(args.config), {**over, "run.duration_s": args.duration, "run.seed": seed})
                with frame_source(cfg) as source:
                    res = run_seed(cfg, source.frames(), args.warmup, args.duration, args.paper)
            runs.append(res[0])
            steps.append(res[1])
            jv = cfg.pf.vehicle_particles
            print(f"seed {seed} done: {res[1]} scored vehicle-steps", flush=True)
            for key, r in res[0].items():
                print(f"| {key} | {seed} | " + " | ".join(cells([r])) + f" | {1e3 * r['cpu'] / res[1]:.2f} |",
                      flush=True)
            if args.dump is not None:
                args.dump.mkdir(parents=True, exist_ok=True)
                np.savez_compressed(args.dump / f"pf_fusion_{seed}.npz", steps=res[1], **{
                    f"{key}/{k}": v for key, r in res[0].items() for k, v in r.items()})
    src = f"frames {args.frames}" if args.frames is not None else "live frames"
    print(f"{args.config}, {src}, seeds {args.seeds}: to {args.duration:.0f} s, scored from {args.warmup:.0f} s "
          f"after the first frame, J = {jv}; {sum(steps)} scored vehicle-steps ({', '.join(map(str, steps))})")
    print("Cells: RMSE / p95 (m), mean NEES, median NEES, inside 95 % (%)")
    print("| method | seed | A | B | C | all | CPU ms / vehicle-step |")
    print("|---|---|---|---|---|---|---|")
    for key in runs[0]:
        for seed, r, n in zip(seeds, runs, steps):
            print(f"| {key} | {seed} | " + " | ".join(cells([r[key]])) + f" | {1e3 * r[key]['cpu'] / n:.2f} |")
        if len(seeds) > 1:
            cpu = sum(r[key]["cpu"] for r in runs) / sum(steps)
            print(f"| {key} | all | " + " | ".join(cells([r[key] for r in runs])) + f" | {1e3 * cpu:.2f} |")


if __name__ == "__main__":
    main()
