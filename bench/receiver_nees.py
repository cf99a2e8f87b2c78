"""The simulated receivers' fixes against the covariance they report, by GNSS zone: frames only, no estimator.

    python bench/receiver_nees.py experiments/arterial_tlr_realistic.toml --seed 101 --duration 300 \
        --set gnss_error.model=satellites --set gnss_error.nlos=reflect --set gnss_error.velocity=doppler \
        [--set gnss_error.reported_covariance=residual]

For every vehicle-step (from ``--from`` s on): the 2-D position NEES of ``gnss_z - x_true`` against the
reported ``gnss_R`` block, likewise the velocity, and the share inside the 95 % ellipse (chi2(2) 5.99); RMS of
the errors. Scored from truth: the world's side, never an estimator's input. Not a test: prints numbers.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from couplers.net.folder import load_net_folder  # noqa: E402
from couplers.sumo_coupler import SumoCoupler  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import sumo_scenario  # noqa: E402

GATE = 5.991464547107979  # chi2(2) 95 %


def _value(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("config")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--duration", type=float, default=300.0)
    ap.add_argument("--from", dest="t_from", type=float, default=0.0, help="score from this run time (s)")
    ap.add_argument("--set", action="append", default=[], help="KEY=VALUE config override, e.g. gnss_error.nlos=reflect")
    args = ap.parse_args()
    over = {"run.duration_s": args.duration, "run.seed": args.seed}
    for kv in args.set:
        k, v = kv.split("=", 1)
        over[k] = _value(v)
    cfg = load_config(args.config, over)
    scenario = sumo_scenario(cfg, load_net_folder(cfg.net_dir))
    acc: dict[str, dict[str, list]] = {}
    with SumoCoupler(scenario, cfg.sensors) as coupler:
        for frame in coupler.frames():
            if frame.t < args.t_from or not frame.n_vehicles:
                continue
            x = np.asarray(frame.truth.x_true, dtype=float)
            zone = np.asarray(frame.truth.zone, dtype=object).reshape(-1).astype(str)
            for name, sl in (("pos", slice(0, 2)), ("vel", slice(2, 4))):
                e = np.asarray(frame.gnss_z, dtype=float)[:, sl] - x[:, sl]
                c = np.asarray(frame.gnss_R, dtype=float)[:, sl, sl]
                nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(c), e)
                for z in np.unique(zone):
                    m = zone == z
                    for key in (z, "all"):
                        d = acc.setdefault(f"{name} {key}", {"nees": [], "sq": []})
                        d["nees"].append(nees[m])
                        d["sq"].append((e[m] ** 2).sum(-1))
    out = {}
    for key, d in sorted(acc.items()):
        nees, sq = np.concatenate(d["nees"]), np.concatenate(d["sq"])
        out[key] = {"n": int(nees.size), "rms_2d": float(np.sqrt(sq.mean())), "nees_mean": float(nees.mean()),
                    "nees_median": float(np.median(nees)), "inside_95": float((nees <= GATE).mean())}
    for key, v in out.items():
        print(f"{key:>10}: n {v['n']:7d}  RMS {v['rms_2d']:8.3f}  NEES mean {v['nees_mean']:9.2f} "
              f"median {v['nees_median']:6.2f}  inside 95 % {100 * v['inside_95']:5.1f} %")
    print(json.dumps({"config": args.config, "seed": args.seed, "duration": args.duration, "from": args.t_from,
                      "set": args.set, "by": out}))


if __name__ == "__main__":
    main()
