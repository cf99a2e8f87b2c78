"""Choose ``[gnss_model]`` values for ``gnss`` cheaply: record a config's frames once per seed, then replay the
``gnss`` tracker with variants of its ``[gnss_model]`` on them.

    python tools/gnss_model_replay.py record CONFIG --seeds 101,102,103 --dir DIR
    python tools/gnss_model_replay.py run CONFIG --seeds 101,102,103 --dir DIR [--set key=value ...] [--detail]

``record`` runs the coupled simulation of CONFIG with the tuning protocol (900 s, ``analysis.warmup_s = 600``,
``warmup_start = "traffic"``) and pickles every frame with its truth (about 170 MB per seed on the arterial).
``run`` steps ``gnss`` (CONFIG's ``[motion]`` and ``[gnss_model]``, with ``--set`` overriding keys of
``[gnss_model]``) through the frames and prints one table row: per zone A, B, C and all, RMSE / p95 (m) of the
2-D position error pooled over the seeds, the mean over seeds of each run's mean 2-D NEES (with the cross term),
and the share of samples inside the 95 % ellipse. Every frame after the traffic-only warm-up is scored, as
``coloc run`` scores these runs (same numbers as the sweep of ``experiments/sweeps/realistic_tuning_gnss_tau.toml``
for the preset's values: RMSE, NEES and inside shares equal, p95 within 0.1 m). ``--detail``: per seed, zone C's
share inside by time since switch-on.
Tuning seeds only (docs/protocol.md). Not a test.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.gnss_bias import GnssBiasTracker  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import frame_source  # noqa: E402
from tools.frame_recording import read_frames as frames, write_frames  # noqa: E402

INSIDE_95 = 5.991464547107979  # chi-square quantile, 2 dof, 0.95
TIME_BINS = (0.0, 15.0, 60.0, 120.0, np.inf)


def protocol_config(base: Path, seed: int, folder: Path):
    cfg = folder / f"cfg_{seed}.toml"
    cfg.write_text(f'extends = "{base.resolve()}"\n[run]\nseed = {seed}\nduration_s = 900.0\nmethods = ["gnss"]\n'
                   '[analysis]\nwarmup_s = 600.0\nwarmup_start = "traffic"\n')
    return load_config(cfg)


def record(cfg, path: Path) -> None:
    with frame_source(cfg) as src:
        write_frames(src.frames(), path)


def replay(path: Path, model, motion):
    """(error (M,), NEES (M,), zone (M,), seconds since the first frame (M,)) of every vehicle-step."""
    est = GnssBiasTracker(motion=motion, model=model)
    err, nees, zone, since = [], [], [], []
    t0 = None
    for fr in frames(path):
        t0 = fr.t if t0 is None else t0
        out = est.step(fr)
        e = out.mean[:, :2] - fr.truth.x_true[:, :2]
        nees.append(np.einsum("ni,ni->n", e, np.linalg.solve(out.cov[:, :2, :2], e[..., None])[..., 0]))
        err.append(np.hypot(e[:, 0], e[:, 1]))
        zone.append(np.asarray(fr.truth.zone))
        since.append(np.full(len(fr.vehicle_ids), fr.t - t0))
    return tuple(np.concatenate(a) for a in (err, nees, zone, since))


def parse_value(v: str):
    if v in ("true", "false"):
        return v == "true"
    for kind in (int, float):
        try:
            return kind(v)
        except ValueError:
            pass
    return v


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cmd", choices=("record", "run"))
    ap.add_argument("config", type=Path)
    ap.add_argument("--seeds", default="101,102,103")
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--set", action="append", default=[], help="[gnss_model] key=value")
    ap.add_argument("--detail", action="store_true")
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    args.dir.mkdir(parents=True, exist_ok=True)
    if args.cmd == "record":
        for s in seeds:
            record(protocol_config(args.config, s, args.dir), args.dir / f"frames_{s}.pkl")
        return
    cfg = protocol_config(args.config, seeds[0], args.dir)
    kw = dict(kv.split("=", 1) for kv in args.set)
    model = dataclasses.replace(cfg.gnss_model, **{k: parse_value(v) for k, v in kw.items()})
    res = [replay(args.dir / f"frames_{s}.pkl", model, cfg.motion) for s in seeds]
    if args.detail:
        for s, (_e, nees, zone, since) in zip(seeds, res):
            c = zone == "C"
            shares = [100 * np.mean(nees[c & (since >= lo) & (since < hi)] < INSIDE_95)
                      for lo, hi in zip(TIME_BINS, TIME_BINS[1:])]
            print(f"seed {s}: zone C inside {100 * np.mean(nees[c] < INSIDE_95):.1f} %, by time since switch-on "
                  + " / ".join(f"{x:.1f}" for x in shares))
    cells = []
    for z in ("A", "B", "C", "all"):
        sel = [np.ones(len(zone), bool) if z == "all" else zone == z for _e, _n, zone, _t in res]
        e = np.concatenate([r[0][m] for r, m in zip(res, sel)])
        n = np.concatenate([r[1][m] for r, m in zip(res, sel)])
        anees = np.mean([r[1][m].mean() for r, m in zip(res, sel)])
        cells.append(f"{np.sqrt(np.mean(e ** 2)):.2f} / {np.percentile(e, 95):.1f}, {anees:.2f}, "
                     f"{100 * np.mean(n < INSIDE_95):.1f}")
    print(f"| {' '.join(args.set) or 'as configured'} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
