"""The satellite world's error at fix level, measured on recorded frames (reads truth; tuning seeds only): what
``joint_oracle`` with ``[joint_oracle] gnss_channel = "fix"`` is told (experiments/oracle_world.py, ``FIX_*``).

    python tools/fix_error_stats.py FRAMES.pkl [FRAMES.pkl ...] [--from 600] [--to 900] [--out OUT.json]

Definitions (docs/validation/oracle.md, "Seventh round"):

* the common error c_t: per step, the mean raw fix error (per axis) over the zone-A vehicles of the step (at least
  three); its per-axis RMS and its autocorrelation at lags of 60, 150, 300 s;
* the local error of a fix: its error less c_t; per bin of the reported per-axis std sqrt(trace(R_pos) / 2) the
  fixes' count, the reported RMS, the local and the raw per-axis RMS, local / reported;
* the local error's correlation between two fixes of one vehicle k steps apart (sum a.b / sqrt(sum a.a sum b.b)
  over the pairs, both axes), binned by the distance the vehicle travelled in between (truth);
* the velocity's error (fix less truth) per axis against the reported velocity std, per bin of the reported position
  std, and its correlation at lags of 1, 4, 16 steps for moving vehicles (above 2 m/s).
Not a test.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tools.frame_recording import read_frames  # noqa: E402

STD_BINS = (0.0, 1.0, 1.2, 1.5, 2.0, 3.0, 4.0, 6.0, 10.0, np.inf)
DIST_BINS = (0.0, 0.5, 2.0, 5.0, 10.0, 20.0, 50.0, np.inf)
LAGS = (1, 2, 4, 8, 16, 40, 80)


def collect(path: Path, t_from: float, t_to: float) -> dict:
    """Per scored vehicle-step: seed-local step index, vehicle, zone, error, reported blocks, distance travelled."""
    rows = {k: [] for k in ("k", "veh", "zone", "err", "rp", "verr", "rv", "dist", "speed")}
    t0, dist, last = None, {}, {}
    for k, fr in enumerate(read_frames(path)):
        t0 = fr.t if t0 is None else t0
        if fr.t - t0 > t_to:
            break
        ids = np.asarray(fr.vehicle_ids).astype(str)
        xy = fr.truth.x_true[:, :2]
        d = np.empty(len(ids))
        for i, v in enumerate(ids):
            if v in last:
                dist[v] += float(np.hypot(*(xy[i] - last[v])))
            else:
                dist[v] = 0.0
            last[v] = xy[i].copy()
            d[i] = dist[v]
        if fr.t - t0 < t_from:
            continue
        z, r = np.asarray(fr.gnss_z, dtype=float), np.asarray(fr.gnss_R, dtype=float)
        rows["k"].append(np.full(len(ids), k))
        rows["veh"].append(ids)
        rows["zone"].append(np.asarray(fr.truth.zone).astype(str))
        rows["err"].append(z[:, :2] - fr.truth.x_true[:, :2])
        rows["rp"].append(r[:, :2, :2])
        rows["verr"].append(z[:, 2:] - fr.truth.x_true[:, 2:4])
        rows["rv"].append(r[:, 2:, 2:])
        rows["dist"].append(d)
        rows["speed"].append(np.hypot(*fr.truth.x_true[:, 2:4].T))
    return {k: np.concatenate(v) for k, v in rows.items()}


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    den = np.sqrt(np.sum(a * a) * np.sum(b * b))
    return float(np.sum(a * b) / den) if den > 0 else float("nan")


def analyse(r: dict, dt: float) -> dict:
    out: dict = {}
    steps = np.unique(r["k"])
    a = r["zone"] == "A"
    common = np.full((steps.max() + 1, 2), np.nan)
    for k in steps:
        sel = a & (r["k"] == k)
        if sel.sum() >= 3:
            common[k] = r["err"][sel].mean(axis=0)
    c = common[steps]
    ok = np.all(np.isfinite(c), axis=1)
    out["common_rms_per_axis"] = float(np.sqrt(np.nanmean(c[ok] ** 2)))
    out["common_mean"] = np.nanmean(c[ok], axis=0).tolist()
    cz = c[ok] - 0.0
    out["common_autocorr"] = {f"{lag}s": _corr(cz[:-int(round(lag / dt))], cz[int(round(lag / dt)):])
                              for lag in (60, 150, 300) if int(round(lag / dt)) < len(cz)}
    has = np.all(np.isfinite(common[r["k"]]), axis=1)
    loc = r["err"] - np.where(has[:, None], common[r["k"]], 0.0)
    std = np.sqrt(0.5 * (r["rp"][:, 0, 0] + r["rp"][:, 1, 1]))
    vstd = np.sqrt(0.5 * (r["rv"][:, 0, 0] + r["rv"][:, 1, 1]))
    out["report_bins"] = []
    for lo, hi in zip(STD_BINS[:-1], STD_BINS[1:]):
        sel = has & (std > lo) & (std <= hi)
        if not sel.any():
            continue
        zones = {z: float(np.mean(r["zone"][sel] == z)) for z in ("A", "B", "C")}
        out["report_bins"].append(dict(
            bin=f"{lo:g}-{hi:g}", n=int(sel.sum()), zones=zones, reported=float(np.sqrt(np.mean(std[sel] ** 2))),
            local=float(np.sqrt(np.mean(loc[sel] ** 2))), raw=float(np.sqrt(np.mean(r["err"][sel] ** 2))),
            local_over_reported=float(np.sqrt(np.mean(loc[sel] ** 2)) / np.sqrt(np.mean(std[sel] ** 2))),
            vel_reported=float(np.sqrt(np.mean(vstd[sel] ** 2))), vel=float(np.sqrt(np.mean(r["verr"][sel] ** 2))),
            vel_nees=float(np.mean(np.einsum("ni,ni->n", r["verr"][sel], np.linalg.solve(
                r["rv"][sel], r["verr"][sel][..., None])[..., 0]))),
            local_nees=float(np.mean(np.einsum("ni,ni->n", loc[sel], np.linalg.solve(
                r["rp"][sel], loc[sel][..., None])[..., 0])))))
    # per vehicle, in step order: the lagged pairs
    order = np.lexsort((r["k"], r["veh"]))
    veh, kk = r["veh"][order], r["k"][order]
    lo_, dd, ve, sp, zn = loc[order], r["dist"][order], r["verr"][order], r["speed"][order], r["zone"][order]
    hh = has[order]
    pairs = {b: ([], []) for b in range(len(DIST_BINS) - 1)}
    lag_time = {lag: ([], []) for lag in LAGS}
    vel = {(z, lag): ([], []) for z in ("A", "B", "C") for lag in (1, 4, 16)}
    for lag in LAGS:
        same = (veh[lag:] == veh[:-lag]) & (kk[lag:] - kk[:-lag] == lag) & hh[lag:] & hh[:-lag]
        i0 = np.flatnonzero(same)
        i1 = i0 + lag
        moved = dd[i1] - dd[i0]
        b = np.digitize(moved, DIST_BINS[1:-1])
        for j in range(len(DIST_BINS) - 1):
            s = b == j
            pairs[j][0].append(lo_[i0[s]])
            pairs[j][1].append(lo_[i1[s]])
        still = moved < 0.5
        lag_time[lag][0].append(lo_[i0[still]])
        lag_time[lag][1].append(lo_[i1[still]])
        if lag in (1, 4, 16):
            for z in ("A", "B", "C"):
                s = (zn[i0] == z) & (sp[i0] > 2.0) & (sp[i1] > 2.0)
                vel[(z, lag)][0].append(ve[i0[s]])
                vel[(z, lag)][1].append(ve[i1[s]])
    out["local_corr_by_distance"] = []
    for j, (p0, p1) in pairs.items():
        x0, x1 = np.concatenate(p0), np.concatenate(p1)
        out["local_corr_by_distance"].append(dict(bin=f"{DIST_BINS[j]:g}-{DIST_BINS[j + 1]:g} m", n=len(x0),
                                                  corr=_corr(x0, x1)))
    out["local_corr_standing"] = [dict(lag_s=lag * dt, n=len(np.concatenate(p0)),
                                       corr=_corr(np.concatenate(p0), np.concatenate(p1)))
                                  for lag, (p0, p1) in lag_time.items()]
    out["velocity_corr_moving"] = [dict(zone=z, lag_s=lag * dt, n=len(np.concatenate(p0)),
                                        corr=_corr(np.concatenate(p0), np.concatenate(p1)))
                                   for (z, lag), (p0, p1) in vel.items()]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("frames", type=Path, nargs="+")
    ap.add_argument("--from", dest="t_from", type=float, default=600.0)
    ap.add_argument("--to", type=float, default=900.0)
    ap.add_argument("--dt", type=float, default=0.75)
    ap.add_argument("--out", type=Path)
    args = ap.parse_args()
    res = {str(p): analyse(collect(p, args.t_from, args.to), args.dt) for p in args.frames}
    print(json.dumps(res, indent=1))
    if args.out:
        args.out.write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
