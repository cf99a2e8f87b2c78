#!/usr/bin/env python3
"""Statistical equivalence of the fast ICP-DA-PF pair sums (``[pf] kernel = "fast"``) to the exact tree.

Paired by seed: each case runs ``icp_da_pf`` twice on the same frames, once with the exact k-d tree
(the reference, 1e-6 per sum) and once with the fast kernel (1e-3 per sum, ``coloc.kernels.pf_fast``),
and compares what a user sees:

* ``single_road``: Brambilla et al. Fig. 7 settings (``experiments/sweeps/fig7_single_road_pf.toml``:
  ``experiments/single_road.toml``, eta_TH = 1, Jv = Jf = 5000, kernel density messages) at
  df = 0.5 m and 3 m. Per run the window MSE of the vehicle positions (t = 10-19 s and 20-30 s, as
  ``tools/paired_windows.py``); per df and window the paired difference fast - exact over the seeds,
  its standard error, and the acceptance: |mean| within two standard errors of zero and below
  0.05 m^2. Also the seconds per step with V2F rows (mean and worst) of each kernel.
* ``arterial`` (``--arterial-seeds``): the first ``--arterial-duration`` s (300) of TLR
  (``experiments/arterial_tlr.toml``, J = 1000): vehicle RMSE and p95 of the position error over all
  vehicle-steps, the association shares (correct / wrong / discarded of the V2F rows, as
  ``coloc run``'s summary); acceptance: RMSE and p95 within 2 % of the exact PF, shares within 0.5
  points.

Every finished run is appended to ``<out>/runs.jsonl`` (so an interrupted or extended study resumes
where it stopped: rerun with more ``--seeds``); the table is printed from that file.

    python tools/pf_equivalence.py --seeds 50                   # the full study (about 2 x 100 runs)
    python tools/pf_equivalence.py --seeds 10 --arterial-seeds 1
    python tools/pf_equivalence.py --table-only                 # print the table of what is recorded
    python tools/pf_equivalence.py --seeds 10 --null-seeds 10   # and the Monte Carlo floor of the pairing
    python tools/pf_equivalence.py --seeds 0 --arterial-seeds 3 --variants fast_component   # fast kernel and
                                                                # BPA-L stopped per component ([pf] bpa_stop)
    python tools/pf_equivalence.py --seeds 0 --arterial-null-seeds 3   # the arterial's Monte Carlo floor

Each record also holds the CPU seconds per step (with ``NUMBA_NUM_THREADS=1`` what one quiet core would
take), the rows per step and the process's resident memory (every 80 steps and the run's peak).

Two PF runs on the same frames part ways at the first resampling draw that a weight differing in its
last bits moves, and from there on differ by the filter's own Monte Carlo error; ``--null-seeds``
measures that floor directly (the exact tree against itself with other particle generators), so the
fast kernel's paired differences can be read against it.

Run it alone on the machine: the PF kernels use every core, and the per-step times are measured.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

WINDOWS = ((10.0, 19.0), (20.0, 30.0))
SPACINGS = (0.5, 3.0)
KERNELS = ("tree", "fast")  # the reference and the default approximation (the records' "kernel" field)
# Each approximation the tool can pair against the exact tree ("tree"), by its [pf] overrides.
VARIANTS = {"tree": {"pf.kernel": "tree"}, "fast": {"pf.kernel": "fast"},
            "fast_component": {"pf.kernel": "fast", "pf.bpa_stop": "component"}}
NULL = "tree_reseeded"  # the exact tree with other particle generators: the Monte Carlo floor of the pairing
NULL_OFFSET = 1000
SINGLE_ROAD = {"lc.eta_threshold": 1.0, "pf.vehicle_particles": 5000, "pf.feature_particles": 5000,
               "pf.message_bandwidth": "prior"}
MSE_LIMIT = 0.05  # m^2
REL_LIMIT = 0.02  # arterial RMSE and p95
SHARE_LIMIT = 0.5  # percentage points


def _rss_mb(field: str = "VmRSS") -> float:
    """This process's resident memory (VmRSS) or its peak since the last :func:`_reset_peak` (VmHWM), MB;
    nan where /proc does not tell."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(field + ":"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return float("nan")


def _reset_peak() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")  # Linux: VmHWM := VmRSS
    except OSError:
        pass


def run_one(config: Path, overrides: dict, pf_seed_offset: int = 0) -> dict:
    """One icp_da_pf run in this process: per-step position errors, association counts, step times,
    resident memory (every 80 steps, and the run's peak). ``pf_seed_offset``: the particle generators
    seeded apart from the scenario (the null comparison)."""
    import dataclasses

    from coloc.methods.registry import ICP_DA_PF
    from experiments.config import load_config
    from experiments.runner import build_estimators, frame_source
    from experiments.scoring import score_association

    cfg = load_config(config, {**overrides, "run.methods": [ICP_DA_PF.name]})
    (est,) = build_estimators(cfg)
    if pf_seed_offset:
        est.pf = dataclasses.replace(est.pf, seed=est.pf.seed + pf_seed_offset)
    t, err, step_s, step_cpu, step_rows, assoc, rss = [], [], [], [], [], [], []
    _reset_peak()
    with frame_source(cfg) as source:
        for k, frame in enumerate(source.frames()):
            if k % 80 == 0:
                rss.append([float(frame.t), _rss_mb()])
            blind = frame.without_truth()
            t0, c0 = time.perf_counter(), time.process_time()
            out = est.step(blind)
            dt, dc = time.perf_counter() - t0, time.process_time() - c0
            if blind.v2f_owner.size:
                step_s.append(dt)
                step_cpu.append(dc)
                step_rows.append(int(blind.v2f_owner.size))
            e = out.mean[:, :2] - frame.truth.x_true[:, :2]
            t.append(np.full(frame.n_vehicles, frame.t))
            err.append(np.hypot(e[:, 0], e[:, 1]))
            assoc.append((np.asarray(out.v2f_assignment, np.int64), np.asarray(frame.truth.v2f_feature, np.int64)))
    t, err = np.concatenate(t), np.concatenate(err)
    counts, _ = score_association(assoc)
    c = counts.sum(axis=0)
    total = max(int(c.sum()), 1)
    return {
        "window_mse": [float(np.mean(err[(t >= lo) & (t <= hi)] ** 2)) for lo, hi in WINDOWS],
        "rmse": float(np.sqrt(np.mean(err**2))), "p95": float(np.quantile(err, 0.95)),
        "shares": [100.0 * float(v) / total for v in c], "v2f_rows": int(c.sum()),
        "step_s_mean": float(np.mean(step_s)) if step_s else 0.0, "step_s_max": float(np.max(step_s, initial=0.0)),
        "steps_with_v2f": len(step_s), "wall_s": float(np.sum(step_s)),
        "rss_mb": rss, "peak_rss_mb": _rss_mb("VmHWM"),
        # CPU seconds of the process per step: with NUMBA_NUM_THREADS=1 what a quiet core would take
        "step_cpu_mean": float(np.mean(step_cpu)) if step_cpu else 0.0,
        "step_cpu_max": float(np.max(step_cpu, initial=0.0)),
        # per step with V2F rows: rows and CPU seconds (cost against rows, for projections to longer runs)
        "step_rows": step_rows, "step_cpu": [round(c, 4) for c in step_cpu],
    }


def load_records(path: Path) -> dict:
    recs = {}
    if path.exists():
        for line in path.read_text().splitlines():
            r = json.loads(line)
            recs[(r["case"], r["seed"], r["kernel"])] = r
    return recs


def _cpu(rs: list[dict]) -> str:
    """CPU seconds per step of the runs that recorded them (the load-independent measure)."""
    rs = [r for r in rs if "step_cpu_mean" in r]
    if not rs:
        return ""
    return (f"; CPU {np.mean([r['step_cpu_mean'] for r in rs]):.3f} s, worst {max(r['step_cpu_max'] for r in rs):.3f} s"
            f" ({len(rs)} runs), peak RSS {max(r['peak_rss_mb'] for r in rs):.0f} MB")


def paired_table(recs: dict) -> tuple[list[str], bool]:
    """The tables of every approximation recorded (``VARIANTS`` other than the tree) against the tree."""
    lines, ok_all = [], True
    found = [v for v in VARIANTS if v != "tree" and any(k == v for (_, _, k) in recs)] or ["fast"]
    for i, variant in enumerate(found):
        part, ok = _variant_table(recs, variant, nulls=i == 0)
        lines.extend((["", f"=== {variant} ({', '.join(f'{a} = {b}' for a, b in VARIANTS[variant].items())})"]
                      if len(found) > 1 else []) + part)
        ok_all &= ok
    return lines, ok_all


def _variant_table(recs: dict, variant: str, nulls: bool = True) -> tuple[list[str], bool]:
    fast = variant
    lines, ok_all, null_lines = [], True, []
    lines.append(f"single road, Fig. 7 settings, J = 5000: window MSE, {fast} - exact, paired by seed")
    lines.append(f"{'df':>5} {'window':>8} {'seeds':>5} {'MSE exact':>10} {'MSE fast':>9} {'diff':>9} "
                 f"{'SE':>7} {'|d|/SE':>6} {'pass':>5}")
    for df in SPACINGS:
        case = f"single_road_df{df}"
        seeds = sorted(s for (c, s, k) in recs if c == case and k == "tree" and (c, s, fast) in recs)
        for w, (lo, hi) in enumerate(WINDOWS):
            null = sorted(s for (c, s, k) in recs if c == case and k == NULL and (c, s, "tree") in recs)
            if nulls and len(null) > 1:
                d = np.array([recs[(case, s, NULL)]["window_mse"][w] - recs[(case, s, "tree")]["window_mse"][w]
                              for s in null])
                null_lines.append(f"{df:5.1f} {f'{lo:.0f}-{hi:.0f} s':>8} {d.size:5d} {d.mean():+9.4f} "
                             f"{d.std(ddof=1) / np.sqrt(d.size):7.4f} {np.sqrt(np.mean(d**2)):9.4f}")
            if not seeds:
                continue
            a = np.array([recs[(case, s, fast)]["window_mse"][w] for s in seeds])
            b = np.array([recs[(case, s, "tree")]["window_mse"][w] for s in seeds])
            d = a - b
            se = float(d.std(ddof=1) / np.sqrt(d.size)) if d.size > 1 else float("nan")
            ok = bool(abs(d.mean()) <= 2 * se and abs(d.mean()) < MSE_LIMIT) if d.size > 1 else False
            ok_all &= ok
            lines.append(f"{df:5.1f} {f'{lo:.0f}-{hi:.0f} s':>8} {d.size:5d} {b.mean():10.3f} {a.mean():9.3f} "
                         f"{d.mean():+9.4f} {se:7.4f} {abs(d.mean()) / se if se > 0 else float('nan'):6.2f} "
                         f"{'yes' if ok else 'NO':>5}")
    if null_lines:
        lines.append("")
        lines.append("Monte Carlo floor: exact tree with other particle generators - exact tree, same scenario seeds")
        lines.append(f"{'df':>5} {'window':>8} {'seeds':>5} {'diff':>9} {'SE':>7} {'rms diff':>9}")
        lines.extend(null_lines)
    fast_rms = []
    for df in SPACINGS:
        case = f"single_road_df{df}"
        for w in range(len(WINDOWS)):
            d = [recs[(case, s, fast)]["window_mse"][w] - recs[(case, s, "tree")]["window_mse"][w]
                 for (c, s, k) in recs if c == case and k == "tree" and (c, s, fast) in recs]
            if d:
                fast_rms.append(f"df {df} w{w}: {np.sqrt(np.mean(np.square(d))):.4f}")
    if fast_rms:
        lines.append(f"rms of the paired difference {fast} - exact (compare with the floor): " + ", ".join(fast_rms))
    lines.append("")
    lines.append("seconds per step with V2F rows (mean over runs of the run's mean; worst single step)")
    for df in SPACINGS:
        case = f"single_road_df{df}"
        for k in ("tree", fast):
            rs = [r for (c, s, kk), r in recs.items() if c == case and kk == k]
            if rs:
                lines.append(f"  df = {df} m, {k:>4s}: mean {np.mean([r['step_s_mean'] for r in rs]):.3f} s, "
                             f"worst {max(r['step_s_max'] for r in rs):.3f} s ({len(rs)} runs)" + _cpu(rs))
    art_null = sorted(s for (c, s, k) in recs if c == "arterial" and k == NULL and ("arterial", s, "tree") in recs)
    if nulls and art_null:
        lines.append("")
        lines.append("arterial TLR, J = 1000, Monte Carlo floor: exact tree with other particle generators against "
                     "the exact tree (what the 2 % / 0.5-point criterion compares with)")
        lines.append(f"{'seed':>4} {'RMSE exact':>10} {'RMSE other':>10} {'rel':>7} {'p95 exact':>9} "
                     f"{'p95 other':>9} {'rel':>7} {'max share diff':>14}")
        for s in art_null:
            e, f = recs[("arterial", s, "tree")], recs[("arterial", s, NULL)]
            dsh = max(abs(x - y) for x, y in zip(f["shares"], e["shares"]))
            lines.append(f"{s:4d} {e['rmse']:10.3f} {f['rmse']:10.3f} {f['rmse'] / e['rmse'] - 1:+7.2%} "
                         f"{e['p95']:9.3f} {f['p95']:9.3f} {f['p95'] / e['p95'] - 1:+7.2%} {dsh:14.2f}")
    art = sorted(s for (c, s, k) in recs if c == "arterial" and k == "tree" and ("arterial", s, fast) in recs)
    if art:
        lines.append("")
        lines.append(f"arterial TLR, J = 1000: {fast} against exact")
        lines.append(f"{'seed':>4} {'RMSE exact':>10} {'RMSE fast':>9} {'rel':>7} {'p95 exact':>9} {'p95 fast':>8} "
                     f"{'rel':>7} {'correct/wrong/discarded exact':>30} {'fast':>22} {'s/step exact':>12} "
                     f"{'fast':>6} {'pass':>5}")
        for s in art:
            e, f = recs[("arterial", s, "tree")], recs[("arterial", s, fast)]
            r1, r2 = f["rmse"] / e["rmse"] - 1, f["p95"] / e["p95"] - 1
            dsh = max(abs(x - y) for x, y in zip(f["shares"], e["shares"]))
            ok = abs(r1) <= REL_LIMIT and abs(r2) <= REL_LIMIT and dsh <= SHARE_LIMIT
            ok_all &= ok
            sh = lambda r: "/".join(f"{v:.2f}" for v in r["shares"])  # noqa: E731
            lines.append(f"{s:4d} {e['rmse']:10.3f} {f['rmse']:9.3f} {r1:+7.2%} {e['p95']:9.3f} {f['p95']:8.3f} "
                         f"{r2:+7.2%} {sh(e):>30} {sh(f):>22} {e['step_s_mean']:12.3f} {f['step_s_mean']:6.3f} "
                         f"{'yes' if ok else 'NO':>5}")
        for k in ("tree", fast):
            rs = [recs[("arterial", s, k)] for s in art]
            if c := _cpu(rs):
                lines.append(f"  {k}: per step with V2F rows{c[1:]}")
    return lines, ok_all


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50, help="single-road seeds per df (1..N)")
    ap.add_argument("--arterial-seeds", type=int, default=0, help="arterial TLR seeds (1..N); the study uses 3")
    ap.add_argument("--arterial-duration", type=float, default=300.0)
    ap.add_argument("--null-seeds", type=int, default=0,
                    help="single-road seeds (1..N) also run by the exact tree with other particle generators "
                         "(pf seed + 1000): how far two exact runs differ by Monte Carlo alone")
    ap.add_argument("--arterial-null-seeds", type=int, default=0,
                    help="arterial TLR seeds (1..N) of the Monte Carlo floor: the exact tree against itself with "
                         "other particle generators (the 2 %% criterion's own noise)")
    ap.add_argument("--variants", default="fast",
                    help=f"approximations run against the exact tree, comma-separated (of {', '.join(VARIANTS)})")
    ap.add_argument("--arterial-first", action="store_true", help="run the arterial seeds before the single road")
    ap.add_argument("--out", type=Path, default=ROOT / "results" / "pf_equivalence")
    ap.add_argument("--table-only", action="store_true", help="print the table of the recorded runs")
    args = ap.parse_args(argv)
    variants = ["tree"] + [v for v in args.variants.split(",") if v]
    if unknown := [v for v in variants if v not in VARIANTS]:
        ap.error(f"unknown variant {unknown[0]!r} (available: {', '.join(VARIANTS)})")
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "runs.jsonl"
    recs = load_records(path)
    todo = []
    if not args.table_only:
        for seed in range(1, args.seeds + 1):
            for df in SPACINGS:
                for k in variants:
                    todo.append((f"single_road_df{df}", seed, k, ROOT / "experiments" / "single_road.toml",
                                 {**SINGLE_ROAD, "single_road.feature_spacing_m": df, "run.seed": seed,
                                  **VARIANTS[k]}))
        for seed in range(1, args.null_seeds + 1):
            for df in SPACINGS:
                todo.append((f"single_road_df{df}", seed, NULL, ROOT / "experiments" / "single_road.toml",
                             {**SINGLE_ROAD, "single_road.feature_spacing_m": df, "run.seed": seed,
                              "pf.kernel": "tree"}))
        arterial = [("arterial", seed, k, ROOT / "experiments" / "arterial_tlr.toml",
                     {"run.seed": seed, "run.duration_s": args.arterial_duration, **VARIANTS[k]})
                    for seed in range(1, args.arterial_seeds + 1) for k in variants]
        arterial += [("arterial", seed, k, ROOT / "experiments" / "arterial_tlr.toml",
                      {"run.seed": seed, "run.duration_s": args.arterial_duration, "pf.kernel": "tree"})
                     for seed in range(1, args.arterial_null_seeds + 1) for k in ("tree", NULL)]
        todo = arterial + todo if args.arterial_first else todo + arterial
    for case, seed, kernel, config, over in todo:
        if (case, seed, kernel) in recs:
            continue
        t0 = time.perf_counter()
        rec = {"case": case, "seed": seed, "kernel": kernel,
               **run_one(config, over, NULL_OFFSET if kernel == NULL else 0)}
        rec["run_s"] = time.perf_counter() - t0
        recs[(case, seed, kernel)] = rec
        with path.open("a") as fh:
            fh.write(json.dumps(rec) + "\n")
        print(f"{case} seed {seed} {kernel}: {rec['run_s']:.0f} s, step {rec['step_s_mean']:.3f} s, "
              f"CPU {rec['step_cpu_mean']:.3f} s, peak RSS {rec['peak_rss_mb']:.0f} MB", flush=True)
    lines, ok = paired_table(recs)
    print("\n".join(lines))
    print(f"\nequivalence {'PASSED' if ok else 'NOT SHOWN'} (fast within the limits on every row)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
