"""Ablations of ``joint_oracle`` on recorded frames (docs/validation/oracle.md, "Ablations").

Records the frames of a config once per world variant (realism components switched off one by one) and
runs the oracle, or a variant of it, on them, scored against the frames' truth:

    OPENBLAS_NUM_THREADS=1 python tools/oracle_ablation.py record experiments/arterial_tlr_realistic.toml \
        --variant full --seed 1 --duration 300 --out /tmp/frames
    OPENBLAS_NUM_THREADS=1 python tools/oracle_ablation.py score /tmp/frames/full_s1.pkl --from 120 \
        --methods joint_oracle,icp_known_da [--oracle key=value ...]

World variants (edits of the config's tables before it is validated):
``full``; ``net_xy`` (``[perception] detections = "net_xy"``); ``no_imu`` (no ``[inertial]``); ``no_nlos``
(NLOS rates 0); ``per_vehicle`` (``[gnss_error] model = "per_vehicle"``, no common / field part);
``no_field`` (field: common only, ``field_share`` 0); ``no_users`` (no road users, no persistent clutter);
``ideal_sensing`` (net_xy and no IMU). Combine with ``+``, e.g. ``net_xy+no_imu``.

Scores: RMSE and p95 of the 2-D position error, mean / median position NEES and the share inside the 95 %
ellipse (NEES <= 5.991), overall and by GNSS zone, from ``--from`` seconds on. A diagnostic, not a run:
nothing here is written under results/.
"""

from __future__ import annotations

import argparse
import dataclasses
import pickle
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

# this checkout's packages, not an installed copy (a script's own folder is first on sys.path)
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from coloc.methods.registry import JOINT_ORACLE  # noqa: E402

CHI2_2_95 = 5.991464547107979


def _edit(data: dict, variant: str) -> dict:
    for v in variant.split("+"):
        if v == "full":
            continue
        if v in ("net_xy", "ideal_sensing"):
            data.setdefault("perception", {})["detections"] = "net_xy"
        if v in ("no_imu", "ideal_sensing"):
            data.pop("inertial", None)
        if v == "no_nlos":
            data["gnss_error"]["nlos_rate_per_min"] = [0.0 for _ in data["gnss_error"]["nlos_rate_per_min"]]
            data["gnss_error"]["nlos_bias_mean_m"] = 0.0
        if v == "per_vehicle":
            ge = data["gnss_error"]
            ge["model"] = "per_vehicle"
            for k in ("common_share", "common_tau_s", "field_share", "field_corr_length_m", "field_tau_s",
                      "local_corr_length_m", "nlos_cell_m"):
                ge.pop(k, None)
        if v == "no_field":
            data["gnss_error"]["field_share"] = 0.0
        if v == "no_users":
            data["perception"]["road_users"] = False
            data["perception"]["persistent_clutter_per_km"] = 0.0
        if v not in ("full", "net_xy", "ideal_sensing", "no_imu", "no_nlos", "per_vehicle", "no_field", "no_users"):
            raise SystemExit(f"unknown variant {v!r}")
    return data


def load_variant(path: str, variant: str, seed: int, duration: float, methods: str, warmup: float = 0.0):
    from experiments.config import config_from_dict
    from experiments.config_extends import resolve_extends

    p = Path(path).resolve()
    data = tomllib.loads(p.read_text())
    data = resolve_extends(data, p) if "extends" in data else data
    data = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    data = _edit(data, variant)
    data["run"] = {**data["run"], "seed": seed, "duration_s": duration, "methods": methods.split(",")}
    if warmup > 0:
        # the protocol's warm-up: SUMO alone fills the net, sensing and estimation start at begin + warmup
        data["analysis"] = {**data.get("analysis", {}), "warmup_s": warmup, "warmup_start": "traffic"}
    return config_from_dict(data, p)


def record(args) -> None:
    from experiments.runner import frame_source

    cfg = load_variant(args.config, args.variant, args.seed, args.duration, "gnss,icp_known_da,joint_oracle",
                       args.warmup)
    frames = []
    t0 = time.process_time()
    with frame_source(cfg) as src:
        for f in src.frames():
            frames.append(f)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    dest = out / f"{args.variant}_s{args.seed}{'_w%g' % args.warmup if args.warmup else ''}.pkl"
    with open(dest, "wb") as fh:
        pickle.dump({"config": args.config, "variant": args.variant, "seed": args.seed, "warmup": args.warmup,
                     "frames": frames}, fh)
    print(f"{dest}: {len(frames)} frames, {time.process_time() - t0:.0f} s CPU", file=sys.stderr)


def _score(err: np.ndarray, nees: np.ndarray) -> str:
    e = np.hypot(err[:, 0], err[:, 1])
    return (f"RMSE {np.sqrt(np.mean(e ** 2)):7.2f}  p95 {np.quantile(e, 0.95):7.2f}  NEES {nees.mean():9.2f} "
            f"(med {np.median(nees):7.2f})  in95 {100 * np.mean(nees <= CHI2_2_95):5.1f} %  n {e.size}")


class _Diagnostics:
    """Truth-reading diagnostics of the oracle's heading (never part of a method: they patch the oracle's
    module for this process only). ``heading_stats``: the heading the rows are converted with against the
    true heading, normalized by its claimed variance, by speed; ``true_heading``: rows converted with the true
    heading at variance 0 (the rows' information then carries no heading term); ``true_imu_heading``: the IMU
    input rotated by the true heading of t-1."""

    def __init__(self, which):
        import coloc.core.detections as cd
        import coloc.methods.joint_oracle as jo

        self.which = set(which)
        self.truth = None
        self.frame = None
        self.stats = []  # (speed, error, var)
        self._prev = {}
        if not self.which:
            return
        orig = jo.vehicle_headings

        def patched(frame, mean, cov, idx, memory, min_speed):
            psi, var, mem = orig(frame, mean, cov, idx, memory, min_speed)
            tr = self.truth
            if tr is not None and tr.heading is not None:
                th = np.asarray(tr.heading, dtype=float)
                sp = np.hypot(tr.x_true[:, 2], tr.x_true[:, 3])
                err = (psi - th + np.pi) % (2 * np.pi) - np.pi
                self.stats.append(np.stack([sp, err, var, np.hypot(mean[:, 2], mean[:, 3])], axis=1))
                if "true_heading" in self.which:
                    psi, var = th.copy(), np.full_like(var, 1e-12)
            return psi, var, mem

        jo.vehicle_headings = patched
        if "true_imu_heading" in self.which:
            orig_h = cd.heading_from_velocity

            orig_imu = jo.JointOracle._imu_input
            self._in_imu = False

            def patched_h(v, p):
                psi, var = orig_h(v, p)
                f = self.frame
                if self._in_imu and f is not None and psi.shape[0] == f.n_vehicles:
                    prev = np.array([self._prev.get(i, np.nan) for i in f.vehicle_ids])
                    ok = np.isfinite(prev)
                    psi = np.where(ok, prev, psi)
                    var = np.where(ok, 1e-12, var)
                return psi, var

            def patched_imu(est, *a):
                self._in_imu = True
                try:
                    return orig_imu(est, *a)
                finally:
                    self._in_imu = False

            cd.heading_from_velocity = patched_h
            jo.JointOracle._imu_input = patched_imu

    def oracle_state(self, est, f, scored: bool) -> None:
        """``state``: the oracle's joint state against the frame's truth (never part of a method): the error of
        the vehicles' mean position (the part every vehicle shares: common GNSS error, the map's offset) with its
        claimed covariance, each vehicle's error less that mean, the landmarks' positions and, with the heading
        state, the heading by true speed."""
        if "state" not in self.which or not scored or est.state.mean is None or f.n_vehicles < 2:
            return
        st, w = est.state, est.world
        n, vd = st.vehicle_ids.shape[0], w.vehicle_dim
        pi = vd * np.arange(n)[:, None] + np.arange(2)
        e = st.mean[pi] - f.truth.x_true[:, :2]
        pp = st.cov[pi.reshape(-1)[:, None], pi.reshape(-1)[None, :]].reshape(n, 2, n, 2)
        colsum = pp.sum(axis=2) / n  # (n, 2, 2): (1/n) sum_j P_ij
        pbar = colsum.sum(axis=0) / n
        ebar = e.mean(axis=0)
        rel = e - ebar
        prel = pp[np.arange(n), :, np.arange(n), :] - colsum - np.swapaxes(colsum, 1, 2) + pbar
        st_ = self.__dict__.setdefault("_state", {"mean": [], "rel": [], "feat": [], "head": []})
        st_["mean"].append((ebar @ np.linalg.solve(pbar, ebar), float(np.hypot(*ebar)), float(np.sqrt(np.trace(pbar)))))
        st_["rel"].append(np.einsum("ni,ni->n", rel, np.linalg.solve(prel, rel[..., None])[..., 0]))
        k = st.feature_ids.size
        if k:
            fi = vd * n + 4 * np.arange(k)[:, None] + np.arange(2)
            ef = st.mean[fi] - np.asarray(f.truth.features_true, dtype=float)[st.feature_ids, :2]
            pf = st.cov[fi[:, :, None], fi[:, None, :]]
            st_["feat"].append(np.stack([np.hypot(ef[:, 0], ef[:, 1]),
                                         np.einsum("ni,ni->n", ef, np.linalg.solve(pf, ef[..., None])[..., 0])], 1))
        if w.heading_dim and f.truth.heading is not None:
            ho = w.heading_offset
            eh = (st.mean[vd * np.arange(n) + ho] - f.truth.heading + np.pi) % (2 * np.pi) - np.pi
            vh = st.cov[vd * np.arange(n) + ho, vd * np.arange(n) + ho]
            sp = np.hypot(f.truth.x_true[:, 2], f.truth.x_true[:, 3])
            st_["head"].append(np.stack([sp, eh, vh], 1))

    def report_state(self) -> None:
        st_ = self.__dict__.pop("_state", None)
        if not st_:
            return
        m = np.array(st_["mean"])
        print(f"   mean over vehicles: error {np.sqrt(np.mean(m[:, 1] ** 2)):.2f} m RMS, claimed {np.sqrt(np.mean(m[:, 2] ** 2)):.2f} m, "
              f"NEES {m[:, 0].mean():.2f} (med {np.median(m[:, 0]):.2f}), in95 {100 * np.mean(m[:, 0] <= CHI2_2_95):.1f} %")
        r = np.concatenate(st_["rel"])
        print(f"   vehicle less the mean: NEES {r.mean():.2f} (med {np.median(r):.2f}), in95 {100 * np.mean(r <= CHI2_2_95):.1f} %")
        if st_["feat"]:
            fe = np.concatenate(st_["feat"])
            print(f"   landmarks: RMSE {np.sqrt(np.mean(fe[:, 0] ** 2)):.2f} m, NEES {fe[:, 1].mean():.2f} "
                  f"(med {np.median(fe[:, 1]):.2f}), in95 {100 * np.mean(fe[:, 1] <= CHI2_2_95):.1f} %")
        if st_["head"]:
            h = np.concatenate(st_["head"])
            for lo, hi in zip([0.0, 1.0, 4.0, 8.0], [1.0, 4.0, 8.0, 1e9]):
                k = (h[:, 0] >= lo) & (h[:, 0] < hi)
                if k.any():
                    e, v = h[k, 1], h[k, 2]
                    print(f"   heading state, true speed {lo:3.0f}-{min(hi, 99):3.0f}: RMS {np.degrees(np.sqrt(np.mean(e ** 2))):6.3f} deg, "
                          f"claimed {np.degrees(np.sqrt(np.mean(v))):6.3f} deg, mean e^2/var {np.mean(e ** 2 / np.maximum(v, 1e-30)):7.2f}, n {k.sum()}")

    def after_step(self):
        f = self.frame
        if f is not None and f.truth.heading is not None:
            self._prev = dict(zip(f.vehicle_ids, f.truth.heading))

    def report(self):
        if not self.stats:
            return
        s = np.concatenate(self.stats)
        self.stats = []
        edges = [1.0, 2.0, 4.0, 8.0, 1e9]
        for lo, hi in zip(edges[:-1], edges[1:]):
            m = (s[:, 3] >= lo) & (s[:, 3] < hi)
            if m.any():
                e, v = s[m, 1], s[m, 2]
                print(f"   heading, est. speed {lo:3.0f}-{min(hi, 99):3.0f}: RMS {np.degrees(np.sqrt(np.mean(e ** 2))):6.2f} deg, "
                      f"claimed {np.degrees(np.sqrt(np.mean(v))):6.2f} deg, mean e^2/var {np.mean(e ** 2 / np.maximum(v, 1e-30)):8.1f}, "
                      f"n {m.sum()}")


def score(args) -> None:
    from coloc.methods.registry import GNSS, build_method
    from experiments.runner import method_params

    with open(args.frames, "rb") as fh:
        rec = pickle.load(fh)
    w = rec.get("warmup", 0.0)
    cfg = load_variant(rec["config"], rec["variant"], rec["seed"], w + 1.0, args.methods, w)
    params = method_params(cfg)
    if args.oracle and params.oracle_world is not None:
        kw = {}
        for item in args.oracle:
            k, v = item.split("=")
            old = getattr(params.oracle_world, k)
            if v == "none":
                kw[k] = None
            else:
                kw[k] = type(old)(v) if not isinstance(old, bool) else v.lower() in ("1", "true", "yes")
        params = dataclasses.replace(params, oracle_world=dataclasses.replace(params.oracle_world, **kw))
    if args.motion:
        kw = {k: float(v) for k, v in (item.split("=") for item in args.motion)}
        icp = params.icp
        params = dataclasses.replace(params, icp=dataclasses.replace(icp, motion=dataclasses.replace(icp.motion, **kw)))
        if getattr(params, "motion", None) is not None:
            params = dataclasses.replace(params, motion=dataclasses.replace(params.motion, **kw))
    if args.icp:
        kw = {}
        for item in args.icp:
            k, v = item.split("=")
            kw[k] = None if v == "none" else float(v)
        params = dataclasses.replace(params, icp=dataclasses.replace(params.icp, **kw))
    frames = [f for f in rec["frames"] if f.t <= args.until + 1e-9]
    diag = _Diagnostics(args.diag or ())
    for name in args.methods.split(","):
        est = build_method(name, params)
        errs, nees, zones, ts, excl, speeds = [], [], [], [], [], []
        cpu = time.process_time()
        for f in frames:
            diag.truth = f.truth
            diag.frame = f
            clean = f.without_truth()
            if getattr(est, "step_with_association", None) is not None and name != GNSS.name:
                out = est.step_with_association(clean, f.truth.v2f_feature)
            else:
                out = est.step(clean)
            diag.after_step()
            if name != GNSS.name and hasattr(est, "world"):
                diag.oracle_state(est, f, f.t + 1e-9 >= args.t_from)
            if getattr(est, "last_excluded", None) is not None:
                excl.append(float(np.mean(est.last_excluded)) if est.last_excluded.size else 0.0)
            if args.verbose and excl and len(excl) % 40 == 0:
                print(f"  t {f.t:.0f} cpu {time.process_time() - cpu:.0f} s excluded {np.mean(excl[-40:]):.3f}",
                      file=sys.stderr, flush=True)
            if f.t + 1e-9 < args.t_from or f.n_vehicles == 0:
                continue
            e = out.mean[:, :2] - f.truth.x_true[:, :2]
            pc = out.cov[:, :2, :2]
            nees.append(np.einsum("ni,ni->n", e, np.linalg.solve(pc, e[..., None])[..., 0]))
            errs.append(e)
            speeds.append(np.hypot(f.truth.x_true[:, 2], f.truth.x_true[:, 3]))
            zones.append(np.asarray(f.truth.zone))
            ts.append(np.full(e.shape[0], f.t))
        cpu = time.process_time() - cpu
        err, nee, zone = np.concatenate(errs), np.concatenate(nees), np.concatenate(zones)
        if excl:
            print(f"   share of fixes excluded by the NLOS gate: {np.mean(excl):.3f}")
        print(f"{name:14s} {_score(err, nee)}  cpu {cpu:.0f} s ({1e3 * cpu / len(frames):.0f} ms/step)")
        for z in np.unique(zone):
            m = zone == z
            print(f"   zone {z}       {_score(err[m], nee[m])}")
        if args.by_speed:
            sp = np.concatenate(speeds)
            edges = [0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 1e9]
            for lo, hi in zip(edges[:-1], edges[1:]):
                m = (sp >= lo) & (sp < hi)
                if m.any():
                    print(f"   speed {lo:3.1f}-{min(hi, 99):4.1f} {_score(err[m], nee[m])}")
        diag.report()
        diag.report_state()
        if args.over_time:
            t = np.concatenate(ts)
            for lo in np.arange(args.t_from, args.until, args.over_time):
                m = (t >= lo) & (t < lo + args.over_time)
                if m.any():
                    print(f"   t {lo:5.0f}        {_score(err[m], nee[m])}")
        sys.stdout.flush()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("record")
    r.add_argument("config")
    r.add_argument("--variant", default="full")
    r.add_argument("--seed", type=int, default=1)
    r.add_argument("--duration", type=float, default=300.0)
    r.add_argument("--out", required=True)
    r.add_argument("--warmup", type=float, default=0.0,
                   help="seconds of SUMO alone before sensing starts ([analysis] warmup_start = \"traffic\"); "
                        "--duration counts them")
    s = sub.add_parser("score")
    s.add_argument("frames")
    s.add_argument("--methods", default=JOINT_ORACLE.name)
    s.add_argument("--from", dest="t_from", type=float, default=120.0)
    s.add_argument("--until", type=float, default=1e9)
    s.add_argument("--over-time", type=float, default=0.0)
    s.add_argument("--verbose", action="store_true")
    s.add_argument("--oracle", nargs="*", help="OracleWorld overrides key=value")
    s.add_argument("--motion", nargs="*", help="[motion] overrides key=value (e.g. heading_min_speed=3)")
    s.add_argument("--icp", nargs="*", help="[icp] overrides key=value (e.g. feature_velocity_prior_sigma=1e-4)")
    s.add_argument("--by-speed", action="store_true", help="scores by the vehicle's true speed")
    s.add_argument("--diag", nargs="*", help="diagnostics that read truth (never a method): heading_stats, "
                   "true_heading (rows converted with the true heading, no heading error), true_imu_heading, "
                   "state (the oracle's joint state: shared and relative error, landmarks, heading state)")
    args = ap.parse_args(argv)
    record(args) if args.cmd == "record" else score(args)


if __name__ == "__main__":
    main()
