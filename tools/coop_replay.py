"""Diagnose and tune the cooperative methods cheaply: record a config's frames once per seed, then replay ``gnss``,
``icp_known_da`` and ``icp_da_lc`` with variants of their config on them.

    python tools/coop_replay.py CONFIG --seeds 101,102,103 --dir DIR [--record] [--warmup-start traffic|sensed]
        [--methods icp_da_lc] [--set lc.key=value ...] [--from SECONDS] [--per-seed] [--cohorts] [--dump OUT.npz]

``--record`` first records the frames that are missing in DIR (``frames_<seed>.pkl``, with their truth, as
``tools/gnss_model_replay.py record`` does; about 170 MB per seed for the 300 sensed seconds of the arterial) with
the tuning protocol: 900 s, ``[analysis] warmup_s = 600`` and ``warmup_start`` ``traffic`` (SUMO alone for 600 s,
then every vehicle switches on at once, the presets' tuning protocol) or ``sensed`` (sensing and estimation from the
begin, so the scored window starts with the map the vehicles built while entering). Each method is built as
``coloc run`` builds it (experiments.runner.build_estimators) from CONFIG and the ``--set`` overrides (dotted
config keys, e.g. ``lc.own_consistency_gate=0.9``) and stepped through the frames without their truth (known
association is given the rows' true features, its definition). The vehicle-steps from ``--from`` seconds after
the first frame are scored (600 with ``sensed`` scores what the sweep of the tuning protocol scores). One table
row per method: per zone A, B, C and all, RMSE / p95 (m) of the 2-D position error pooled over the seeds, the mean
over seeds of each run's mean 2-D NEES (with the cross term), the share of samples inside the 95 % ellipse; for
``icp_da_lc`` also its landmark rows on the track most of that landmark's rows went to, on another track or
discarded, and the share of clutter and persistent-clutter rows it used (diagnostics from the truth, after the
step). ``--cohorts``: the same cells for the vehicles on the road at the first frame (a traffic-only warm-up
switches them all on together, with no map) and for those that entered later. ``--report-scale K`` (a what-if,
not an estimator setting): every estimator is given the receiver's reported covariance times K. ``--dump``: every
scored vehicle-step (seed, t, vehicle, zone, error, NEES and the whitened error wx, wy per method) for
row-by-row comparisons and the shared part of the errors (experiments/sweep/consistency.py).
Tuning seeds only (docs/protocol.md). Not a test.
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_KNOWN_DA  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.sweep.consistency import whitened_errors  # noqa: E402
from experiments.runner import build_estimators  # noqa: E402
from tools.gnss_model_replay import INSIDE_95, frames, parse_value, record  # noqa: E402

ZONES = ("A", "B", "C", "all")


def protocol_config(base: Path, seed: int, folder: Path, warmup_start: str) -> Path:
    cfg = folder / f"cfg_{seed}.toml"
    cfg.write_text(f'extends = "{base.resolve()}"\n[run]\nseed = {seed}\nduration_s = 900.0\nmethods = ["gnss"]\n'
                   f'[analysis]\nwarmup_s = 600.0\nwarmup_start = "{warmup_start}"\n')
    return cfg


def replay(cfg, path: Path, scored_from: float, report_scale: float) -> dict:
    """Per method: error, NEES, zone, t, vehicle, on-at-start of every scored vehicle-step; for icp_da_lc the
    fate of its rows."""
    ests = build_estimators(cfg)
    names = list(cfg.run.methods)
    out = {m: {"err": [], "nees": [], "zone": [], "t": [], "veh": [], "on": [], "wx": [], "wy": []} for m in names}
    rows = {"kind": [], "feat": [], "track": [], "zone": []}
    t0, at_start = None, set()
    for fr in frames(path):
        if t0 is None:
            t0, at_start = fr.t, set(np.asarray(fr.vehicle_ids).tolist())
        blind = fr.without_truth()
        if report_scale != 1.0:
            blind = replace(blind, gnss_R=blind.gnss_R * report_scale, prior_R=blind.prior_R * report_scale)
        scored = fr.t >= t0 + scored_from
        zone = np.asarray(fr.truth.zone).astype(str)
        ids = np.asarray(fr.vehicle_ids).astype(str)
        for m, est in zip(names, ests):
            e = (est.step_with_association(blind, fr.truth.v2f_feature) if hasattr(est, "step_with_association")
                 else est.step(blind))
            if not scored:
                continue
            d = e.mean[:, :2] - fr.truth.x_true[:, :2]
            o = out[m]
            o["nees"].append(np.einsum("ni,ni->n", d, np.linalg.solve(e.cov[:, :2, :2], d[..., None])[..., 0]))
            o["err"].append(np.hypot(d[:, 0], d[:, 1]))
            w = whitened_errors(d[:, 0], d[:, 1], e.cov[:, 0, 0], e.cov[:, 1, 1], e.cov[:, 0, 1])
            o["wx"].append(w[0])
            o["wy"].append(w[1])
            o["zone"].append(zone)
            o["t"].append(np.full(zone.size, fr.t))
            o["veh"].append(ids)
            o["on"].append(np.array([v in at_start for v in np.asarray(fr.vehicle_ids).tolist()], dtype=bool))
            if m == ICP_DA_LC.name and fr.v2f_owner.size:
                kind = (np.asarray(fr.truth.v2f_kind, dtype=np.int64) if fr.truth.v2f_kind is not None
                        else np.where(np.asarray(fr.truth.v2f_feature) >= 0, 0, 1))
                rows["kind"].append(kind)
                rows["feat"].append(np.asarray(fr.truth.v2f_feature, dtype=np.int64))
                rows["track"].append(np.asarray(e.v2f_assignment, dtype=np.int64))
                rows["zone"].append(zone[np.asarray(fr.v2f_owner, dtype=np.int64)])
    res = {m: {k: np.concatenate(v) for k, v in o.items()} for m, o in out.items()}
    if rows["kind"]:
        res["rows"] = {k: np.concatenate(v) for k, v in rows.items()}
    return res


def row_fate(rows: dict) -> dict:
    """Landmark rows: on the track most of that landmark's used rows went to / on another track / discarded;
    clutter and persistent clutter rows: the share used (a persistent source is static: a track on it
    localizes like a landmark)."""
    kind, feat, track = rows["kind"], rows["feat"], rows["track"]
    used = track >= 0
    lm = (kind == 0) & (feat >= 0)
    best = np.zeros(lm.size, dtype=bool)
    if (lm & used).any():
        f, t = feat[lm & used], track[lm & used]
        pairs, counts = np.unique(np.stack([f, t], 1), axis=0, return_counts=True)
        order = np.lexsort((-counts, pairs[:, 0]))
        first = np.ones(order.size, dtype=bool)
        first[1:] = pairs[order][1:, 0] != pairs[order][:-1, 0]
        top = pairs[order][first]  # (feature, its majority track), sorted by feature
        pos = np.searchsorted(top[:, 0], f)
        best[lm & used] = top[pos, 1] == t
    n_lm = max(int(lm.sum()), 1)
    out = {"landmark rows": int(lm.sum()), "on majority track %": 100 * best.sum() / n_lm,
           "on other track %": 100 * (lm & used & ~best).sum() / n_lm, "discarded %": 100 * (lm & ~used).sum() / n_lm}
    for k, name in ((1, "clutter"), (2, "persistent")):
        sel = kind == k
        out[f"{name} rows"] = int(sel.sum())
        out[f"{name} used %"] = 100 * (sel & used).sum() / max(int(sel.sum()), 1)
    return out


def table_row(label: str, runs: list[dict], subset=None) -> str:
    cells = []
    for z in ZONES:
        sel = [(np.ones(r["zone"].size, bool) if z == "all" else r["zone"] == z) & (True if subset is None else
                                                                                   subset(r)) for r in runs]
        if not any(m.any() for m in sel):
            cells.append("-")
            continue
        e = np.concatenate([r["err"][m] for r, m in zip(runs, sel)])
        n = np.concatenate([r["nees"][m] for r, m in zip(runs, sel)])
        anees = np.mean([r["nees"][m].mean() for r, m in zip(runs, sel) if m.any()])
        cells.append(f"{np.sqrt(np.mean(e ** 2)):.2f} / {np.percentile(e, 95):.2f}, {anees:.2f}, "
                     f"{100 * np.mean(n < INSIDE_95):.1f}")
    return f"| {label} | " + " | ".join(cells) + " |"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", type=Path)
    ap.add_argument("--seeds", default="101,102,103")
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--record", action="store_true", help="record the missing frames first")
    ap.add_argument("--warmup-start", choices=("traffic", "sensed"), default="traffic")
    ap.add_argument("--methods", default=",".join(m.name for m in (GNSS, ICP_KNOWN_DA, ICP_DA_LC)))
    ap.add_argument("--set", action="append", default=[], help="dotted config key=value")
    ap.add_argument("--from", dest="scored_from", type=float, default=0.0,
                    help="score from this many seconds after the first frame")
    ap.add_argument("--report-scale", type=float, default=1.0, help="what-if: the receiver's covariance times this")
    ap.add_argument("--per-seed", action="store_true", help="a row per seed as well")
    ap.add_argument("--cohorts", action="store_true", help="rows for the vehicles on at the start / entered later")
    ap.add_argument("--dump", type=Path)
    args = ap.parse_args()
    seeds = [int(s) for s in args.seeds.split(",")]
    args.dir.mkdir(parents=True, exist_ok=True)
    over = {k: parse_value(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    over["run.methods"] = args.methods.split(",")
    res = []
    for s in seeds:
        cfg = protocol_config(args.config, s, args.dir, args.warmup_start)
        path = args.dir / f"frames_{s}.pkl"
        if args.record and not path.exists():
            record(load_config(cfg), path)
        res.append(replay(load_config(cfg, over), path, args.scored_from, args.report_scale))
    tag = " ".join(args.set) or "as configured"
    for m in over["run.methods"]:
        print(table_row(f"{m}, {tag}", [r[m] for r in res]))
        if args.per_seed:
            for s, r in zip(seeds, res):
                print(table_row(f"{m}, seed {s}", [r[m]]))
        if args.cohorts:
            print(table_row(f"{m}, on at the start", [r[m] for r in res], lambda r: r["on"]))
            print(table_row(f"{m}, entered later", [r[m] for r in res], lambda r: ~r["on"]))
    for s, r in zip(seeds, res):
        if "rows" in r:
            print(f"seed {s} icp_da_lc rows: " + ", ".join(
                f"{k} {v:.1f}" if isinstance(v, float) else f"{k} {v}" for k, v in row_fate(r["rows"]).items()))
    if args.dump:
        flat = {f"{s}/{m}/{k}": v for s, r in zip(seeds, res) for m in over["run.methods"] for k, v in r[m].items()}
        np.savez_compressed(args.dump, **flat)


if __name__ == "__main__":
    main()
