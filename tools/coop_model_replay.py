"""The receiver model of ``[gnss_model]`` in every method that takes it, on recorded frames: replay ``gnss``,
``icp_known_da`` and ``icp_da_lc`` (or ``--methods``) with the config's ``[gnss_model]`` and keys overridden by
``--set``, and print per method one table row by zone.

    python tools/gnss_model_replay.py record CONFIG --seeds 101,102,103 --dir DIR    (the frames, once)
    python tools/coop_model_replay.py CONFIG --seeds 101,102,103 --dir DIR [--set key=value ...] [--methods ...]
        [--save FILE.npz]

The frames are those of :mod:`tools.gnss_model_replay` (tuning protocol: 900 s, 600 s traffic-only warm-up,
every frame after it scored). Each method steps as ``coloc run`` steps it (``icp_known_da`` told the frame's
true association by the replay, never from the frame it is given). Cells: RMSE / p95 of the 2-D position
error (m) pooled over the seeds, the mean over seeds of each run's mean 2-D NEES (with the cross term), the
share of samples inside the 95 % ellipse. ``--save``: the per-sample arrays (error, NEES, zone, seed) per
method, to compare two variants without replaying. Tuning seeds only (docs/protocol.md). Not a test.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tools"))

from gnss_model_replay import INSIDE_95, frames, parse_value  # noqa: E402

from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_KNOWN_DA, METHODS  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.pipeline import step_result  # noqa: E402
from experiments.runner import build_estimators  # noqa: E402

DEFAULT_METHODS = (GNSS.name, ICP_KNOWN_DA.name, ICP_DA_LC.name)
ZONES = ("A", "B", "C", "all")


def replay(cfg, path: Path) -> dict:
    """Per method: (error (M,), NEES (M,), zone (M,)) of every vehicle-step, and its CPU seconds."""
    ests = build_estimators(cfg)
    known = [METHODS[e.name].known_association for e in ests]
    out = {e.name: ([], [], []) for e in ests}
    cpu = {e.name: 0.0 for e in ests}
    for fr in frames(path):
        blind = fr.without_truth()
        for est, told in zip(ests, known):
            t0 = time.process_time()
            res = step_result(est, told, blind, fr.truth.v2f_feature if told else None).estimate
            cpu[est.name] += time.process_time() - t0
            e = res.mean[:, :2] - fr.truth.x_true[:, :2]
            nees = np.einsum("ni,ni->n", e, np.linalg.solve(res.cov[:, :2, :2], e[..., None])[..., 0])
            acc = out[est.name]
            acc[0].append(np.hypot(e[:, 0], e[:, 1]))
            acc[1].append(nees)
            acc[2].append(np.asarray(fr.truth.zone))
    return {k: (tuple(np.concatenate(a) for a in v), cpu[k]) for k, v in out.items()}


def cells(res: list) -> list[str]:
    out = []
    for z in ZONES:
        sel = [np.ones(len(zone), bool) if z == "all" else zone == z for _e, _n, zone in res]
        e = np.concatenate([r[0][m] for r, m in zip(res, sel)])
        n = np.concatenate([r[1][m] for r, m in zip(res, sel)])
        anees = np.mean([r[1][m].mean() for r, m in zip(res, sel)])
        out.append(f"{np.sqrt(np.mean(e ** 2)):.2f} / {np.percentile(e, 95):.1f}, {anees:.2f}, "
                   f"{100 * np.mean(n < INSIDE_95):.1f}")
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", type=Path)
    ap.add_argument("--seeds", default="101,102,103")
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--set", action="append", default=[], help="[gnss_model] key=value")
    ap.add_argument("--methods", default=",".join(DEFAULT_METHODS))
    ap.add_argument("--save", type=Path)
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    over = {"run.methods": args.methods.split(","), "run.duration_s": 900.0, "analysis.warmup_s": 600.0,
            "analysis.warmup_start": "traffic"}
    over.update({f"gnss_model.{k}": parse_value(v) for k, v in (kv.split("=", 1) for kv in args.set)})
    per_seed = []
    for s in seeds:
        cfg = load_config(args.config, {**over, "run.seed": s})
        per_seed.append(replay(cfg, args.dir / f"frames_{s}.pkl"))
    label = " ".join(args.set) or "as configured"
    saved = {}
    for m in per_seed[0]:
        res = [ps[m][0] for ps in per_seed]
        cpu = sum(ps[m][1] for ps in per_seed)
        steps = sum(len(r[0]) for r in res)
        print(f"| {m} | {label} | " + " | ".join(cells(res)) + f" | {1e6 * cpu / steps:.0f} us |")
        for s, r in zip(seeds, res):
            saved[f"{m}/{s}/err"], saved[f"{m}/{s}/nees"], saved[f"{m}/{s}/zone"] = r
    if args.save:
        np.savez_compressed(args.save, **saved)


if __name__ == "__main__":
    main()
