"""Replay ``joint_oracle`` in the satellite world on recorded frames: the frames of a run without the oracle (e.g.
``tools/coop_replay.py --record``) get the oracle's channel (``Frame.oracle_gnss``) by stepping a second satellite
receiver process of the same seed over their truth (checked: its fixes equal the recorded ones to the byte, else
the tool stops), then ``gnss``, ``icp_known_da``, ``icp_da_lc`` and ``joint_oracle`` are stepped as ``coloc run``
builds them and scored by zone from ``--from`` seconds after the first frame to ``--to``.

    python tools/oracle_sat_replay.py CONFIG FRAMES.pkl --from 600 --to 660 [--methods ...] [--set key=value]
        [--oracle-start SECONDS] [--nlos-stats] [--out OUT.json] [--seed-json OUT.json] [--estimates OUT.parquet]

``--fix-oracle`` adds the fix-level oracle (``[oracle] gnss_channel = "fix"``: the fixes and their reports only,
the world's fix-level error structure; docs/validation/oracle.md, "Seventh round") as the column
``joint_oracle_fix``; ``--set-fix key=value`` overrides its OracleWorld keys. Without ``joint_oracle`` among
``--methods`` the frames are replayed as recorded (no second receiver process: the fix-level oracle does not need
the channel). ``--set`` overrides an OracleWorld key (e.g. ``multipath_state=false``, ``nlos_d_std_m=20``). ``--nlos-stats``:
the distribution of D = extra path / (2 cos el) and of the path rate / (2 cos el |v|) over the reflected signals
of the fixes (what :data:`experiments.oracle_world.NLOS_D_MEAN_M` is measured from). Tuning seeds only.
``--oracle-start S`` (a cost saving, opt-in): ``joint_oracle`` sees the frames from S seconds after the first one
only, and takes every vehicle on the road then as entering (prior: its fix of that step with the reported
covariance, as ``[scenario] start = "gnss_fix"``); the other methods see every frame. ``--seed-json``: per method
and zone rmse, p95, nees_mean, inside, n (the protocol's pairing format). ``--estimates``: the oracle's scored
estimates (method, t, vehicle, x, y, cov_xx, cov_xy, cov_yy) as parquet. Not a test.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from couplers.net.folder import load_net_folder  # noqa: E402
from couplers.sensing import gnss_satellites as gs  # noqa: E402
from coloc.methods.registry import GNSS, ICP_DA_LC, ICP_KNOWN_DA, JOINT_ORACLE  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import build_estimators  # noqa: E402
from tools.frame_recording import read_frames  # noqa: E402
from tools.gnss_model_replay import INSIDE_95, parse_value  # noqa: E402

ZONES = ("A", "B", "C", "all")
FIX_ORACLE = f"{JOINT_ORACLE.name}_fix"  # the fix-level oracle's column


def channel_frames(cfg, path: Path, stats: dict | None = None, channel: bool = True):
    """The recorded frames with ``oracle_gnss`` from a second receiver process over their truth."""
    ge = replace(cfg.sensors.gnss_error, oracle_channel=True)
    net = load_net_folder(cfg.net_dir)
    proc = gs.SatelliteErrorProcess(ge, cfg.run.seed, cfg.scenario.step_s,
                                    net.buildings, net_path=net.net)
    if stats is not None:  # the extra paths and rates of the reflections found (the reflect kernel's output)
        inner = gs.reflect_kernel

        def spy(xy, b, *a):
            found, ex, g = inner(xy, b, *a)
            stats["last"] = (found, ex, g)
            return found, ex, g

        gs.reflect_kernel = spy
    if not channel:  # the frames as recorded
        for fr in read_frames(path):
            yield fr, None
        return
    for fr in read_frames(path):
        tr = fr.truth
        err = proc.step(fr.t, fr.vehicle_ids, fr.entered, None, None, None, tr.x_true[:, :2])
        if not np.array_equal(tr.x_true[:, :2] + err, fr.gnss_z[:, :2]):
            raise SystemExit(f"t={fr.t}: the second receiver process does not reproduce the recorded fixes")
        if proc.doppler:
            proc.velocity_error(tr.x_true[:, 2:4])
        ch = proc.oracle_frame()
        if stats is not None:
            for key in ("ex", "found", "cols"):
                stats.pop(key, None)
        if stats is not None and "last" in stats and len(fr.vehicle_ids):
            found, ex, g = stats.pop("last")
            el = proc._geom[1]
            cols = np.flatnonzero(el >= proc.mask)
            stats.update(ex=ex, found=found, cols=cols)
            used = ch.reflected[:, cols]
            c2 = 2.0 * np.cos(el[cols])[None, :]
            stats.setdefault("D", []).append((ex / c2)[used])
            v = np.hypot(*tr.x_true[:, 2:4].T)
            rr = (g[..., 0] * tr.x_true[:, None, 2] + g[..., 1] * tr.x_true[:, None, 3]) / (c2 * np.maximum(v, 0.5)[:, None])
            stats.setdefault("rate", []).append(rr[used & (v[:, None] > 2.0)])
            stats.setdefault("zone", []).append(np.broadcast_to(np.asarray(tr.zone)[:, None], used.shape)[used])
        nlos_part = None
        if stats is not None:  # the fix's part from the reflected signals' extra paths (a diagnostic; truth)
            full = np.zeros(ch.used.shape)
            if "ex" in stats:
                full[:, stats["cols"]] = stats["ex"]  # as the world adds it (gnss_satellites._assemble)
            nlos_part = np.einsum("nis,ns->ni", ch.gain, full * ch.reflected)
        yield replace(fr, oracle_gnss=ch), nlos_part


def late_start_frame(fr):
    """The frame as the first one of a filter started now: every vehicle entering, its prior the step's fix with
    the reported covariance and said to be that fix (``prior_has_fix``, so it is not applied twice)."""
    n = fr.n_vehicles
    return replace(fr, entered=np.ones(n, dtype=bool), prior_z=np.array(fr.gnss_z, dtype=float, copy=True),
                   prior_R=np.array(fr.gnss_R, dtype=float, copy=True), prior_has_fix=np.ones(n, dtype=bool))


def seed_table(res: dict) -> dict:
    """``report``'s table as {method: {zone: {rmse, p95, nees_mean, inside, n}}}."""
    out: dict = {}
    for key, row in res["table"].items():
        m, z = key.split("/")
        out.setdefault(m, {})[z] = dict(rmse=row["rmse"], p95=row["p95"], nees_mean=row["nees"],
                                         inside=row["inside"], n=row["n"])
    return out


def report(args, names, out, cpu, steps, nveh) -> dict:
    """The table by method and zone of the vehicle-steps scored so far (printed)."""
    res = {"steps": steps, "vehicles_mean": float(np.mean(nveh)) if nveh else 0.0,
           "cpu_ms_per_step": {m: 1e3 * cpu[m] / max(steps, 1) for m in names}, "table": {}}
    print(f"{args.frames} {args.t_from:.0f}-{args.to:.0f} s: {steps} steps, {res['vehicles_mean']:.0f} vehicles")
    print("method zone   n   RMSE   p95   meanNEES  inside95 | CPU ms/step")
    for m in names:
        err, nees, zone = (np.concatenate(out[m][k]) if out[m][k] else np.empty(0) for k in ("err", "nees", "zone"))
        for z in ZONES:
            sel = np.ones(err.size, bool) if z == "all" else zone == z
            if not sel.any():
                continue
            row = dict(n=int(sel.sum()), rmse=float(np.sqrt(np.mean(err[sel] ** 2))),
                       p95=float(np.percentile(err[sel], 95)), nees=float(nees[sel].mean()),
                       median_nees=float(np.median(nees[sel])), inside=float(np.mean(nees[sel] <= INSIDE_95)))
            res["table"][f"{m}/{z}"] = row
            print(f"{m:13s} {z:3s} {row['n']:6d} {row['rmse']:6.2f} {row['p95']:6.2f} {row['nees']:9.2f} "
                  f"{100 * row['inside']:6.1f} % | {res['cpu_ms_per_step'][m]:.0f}")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", type=Path)
    ap.add_argument("frames", type=Path)
    ap.add_argument("--from", dest="t_from", type=float, default=600.0)
    ap.add_argument("--to", type=float, default=660.0)
    ap.add_argument("--methods", default=",".join(m.name for m in (GNSS, ICP_KNOWN_DA, ICP_DA_LC, JOINT_ORACLE)))
    ap.add_argument("--set", action="append", default=[])
    ap.add_argument("--fix-oracle", action="store_true", help="add the fix-level oracle (column joint_oracle_fix)")
    ap.add_argument("--set-fix", action="append", default=[], help="an OracleWorld key of the fix-level oracle")
    ap.add_argument("--nlos-stats", action="store_true")
    ap.add_argument("--nlos-known", action="store_true",
                    help="diagnostic (reads truth): the oracle's fixes less their reflected signals' true extra "
                         "paths through the gain, and its extra-path mean and std set to 0")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--oracle-start", type=float, default=0.0,
                    help="joint_oracle starts at this many seconds after the first frame (vehicles then entering)")
    ap.add_argument("--seed-json", type=Path)
    ap.add_argument("--estimates", type=Path, help="the oracle's scored estimates as parquet")
    args = ap.parse_args()
    cfg = load_config(args.config)
    cfg = replace(cfg, run=replace(cfg.run, methods=tuple(args.methods.split(",")) if args.methods else ()))
    names = list(cfg.run.methods)
    ests = build_estimators(cfg) if names else []
    if args.fix_oracle:  # the fix-level oracle, built as `coloc run` builds it with [oracle] gnss_channel = "fix"
        from experiments.oracle_world import OracleSection

        fix_cfg = replace(cfg, run=replace(cfg.run, methods=(JOINT_ORACLE.name,)),
                          oracle=OracleSection(gnss_channel="fix"))
        fix_est = build_estimators(fix_cfg)[0]
        for kv in args.set_fix:
            k, v = kv.split("=", 1)
            fix_est.world = replace(fix_est.world, **{k: parse_value(v)})
        print("fix-level oracle:", fix_est.world)
        names.append(FIX_ORACLE)
        ests.append(fix_est)
    for kv in args.set:
        k, v = kv.split("=", 1)
        for m, e in zip(names, ests):
            if m == JOINT_ORACLE.name:
                e.world = replace(e.world, **{k: parse_value(v)})
    if args.nlos_known:
        args.nlos_stats = True
        for m, e in zip(names, ests):
            if m == JOINT_ORACLE.name:
                e.world = replace(e.world, nlos_d_mean_m=0.0, nlos_d_std_m=0.0)
    stats = {} if args.nlos_stats else None
    out = {m: {"err": [], "nees": [], "zone": []} for m in names}
    cpu = {m: 0.0 for m in names}
    steps, t0, nveh = 0, None, []
    oracle_on = False
    rows = {k: [] for k in ("method", "t", "vehicle", "x", "y", "cov_xx", "cov_xy", "cov_yy")}
    for fr, nlos_part in channel_frames(cfg, args.frames, stats, channel=JOINT_ORACLE.name in cfg.run.methods):
        t0 = fr.t if t0 is None else t0
        if fr.t - t0 > args.to:
            break
        blind = fr.without_truth()
        scored = fr.t - t0 >= args.t_from
        oracle_now = fr.t - t0 >= args.oracle_start - 1e-9
        for m, est in zip(names, ests):
            if m == JOINT_ORACLE.name and not oracle_now:
                continue
            c = time.process_time()
            seen = blind
            if m == JOINT_ORACLE.name and not oracle_on and args.oracle_start > 0:
                seen = late_start_frame(seen)
            if args.nlos_known and m == JOINT_ORACLE.name:  # diagnostic: the extra paths' realisation taken out
                gz = blind.gnss_z.copy()
                gz[:, :2] -= nlos_part
                seen = replace(blind, gnss_z=gz)
            e = (est.step_with_association(seen, fr.truth.v2f_feature) if hasattr(est, "step_with_association")
                 else est.step(seen))
            if scored:
                cpu[m] += time.process_time() - c
            if m == JOINT_ORACLE.name:
                oracle_on = True
            if not scored:
                continue
            if m in (JOINT_ORACLE.name, FIX_ORACLE) and args.estimates:
                rows["method"].append(np.full(fr.n_vehicles, m))
                rows["t"].append(np.full(fr.n_vehicles, fr.t))
                rows["vehicle"].append(np.asarray(fr.vehicle_ids).astype(str))
                rows["x"].append(e.mean[:, 0])
                rows["y"].append(e.mean[:, 1])
                for k, (i, j) in (("cov_xx", (0, 0)), ("cov_xy", (0, 1)), ("cov_yy", (1, 1))):
                    rows[k].append(e.cov[:, i, j])
            d = e.mean[:, :2] - fr.truth.x_true[:, :2]
            out[m]["nees"].append(np.einsum("ni,ni->n", d, np.linalg.solve(e.cov[:, :2, :2], d[..., None])[..., 0]))
            out[m]["err"].append(np.hypot(d[:, 0], d[:, 1]))
            out[m]["zone"].append(np.asarray(fr.truth.zone).astype(str))
        if scored:
            steps += 1
            nveh.append(fr.n_vehicles)
            if steps % 20 == 0:  # partial tables: a long replay on a shared machine
                report(args, names, out, cpu, steps, nveh)
                sys.stdout.flush()
    res = report(args, names, out, cpu, steps, nveh)
    if stats is not None and stats.get("D"):
        dd, rr = np.concatenate(stats["D"]), np.concatenate(stats["rate"])
        res["nlos"] = dict(n=int(dd.size), d_mean=float(dd.mean()), d_std=float(dd.std()),
                           d_p50=float(np.median(dd)), d_p95=float(np.percentile(dd, 95)),
                           rate_mean=float(rr.mean()) if rr.size else 0.0, rate_rms=float(np.sqrt(np.mean(rr ** 2)))
                           if rr.size else 0.0)
        print("nlos", res["nlos"])
    if args.out:
        args.out.write_text(json.dumps(res, indent=1))
    if args.seed_json:
        args.seed_json.write_text(json.dumps(seed_table(res), indent=1))
    if args.estimates and rows["t"]:
        import pandas as pd

        pd.DataFrame({k: np.concatenate(v) for k, v in rows.items()}).to_parquet(args.estimates, index=False)


if __name__ == "__main__":
    main()
