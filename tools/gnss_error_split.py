"""Diagnostic (reads the truth; not an estimator): where the ``gnss`` benchmark's overconfidence comes from, on
frames recorded by ``tools/gnss_model_replay.py record``.

    python tools/gnss_error_split.py CONFIG --dir DIR [--seeds 101,102,103]

Prints per seed, zone C: (1) the receiver's raw fixes taken as estimates with the covariance it reports
(share inside the 95 % ellipse, mean NEES, RMSE); (2) ``gnss`` (CONFIG's ``[gnss_model]``) replayed as recorded;
(3) ``gnss`` replayed on fixes from which, at every step and in every zone, the mean fix error over the vehicles in
that zone has been removed (the error the receivers share: the world's common-mode part, plus the part of
its field and NLOS cells that the vehicles of a zone have in common on average). Each line: share inside (%),
mean NEES, RMSE (m). Tuning seeds only (docs/protocol.md). Not a test.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from coloc.methods.registry import GNSS  # noqa: E402
from experiments.config import load_config  # noqa: E402
from tools import gnss_model_replay as replay_tool  # noqa: E402

INSIDE_95 = replay_tool.INSIDE_95


def shared_removed(frames):
    """The frames with each zone's cross-vehicle mean fix error removed from the position fixes (truth used)."""
    for fr in frames:
        z = np.array(fr.gnss_z, dtype=float)
        zone = np.asarray(fr.truth.zone)
        e = z[:, :2] - fr.truth.x_true[:, :2]
        for name in np.unique(zone):
            sel = zone == name
            if sel.sum() > 1:
                z[sel, :2] -= e[sel].mean(axis=0)
        yield dataclasses.replace(fr, gnss_z=z)


def raw_fix(path: Path):
    err, nees, zone = [], [], []
    for fr in replay_tool.frames(path):
        e = np.asarray(fr.gnss_z, dtype=float)[:, :2] - fr.truth.x_true[:, :2]
        r = np.asarray(fr.gnss_R, dtype=float)[:, :2, :2]
        nees.append(np.einsum("ni,ni->n", e, np.linalg.solve(r, e[..., None])[..., 0]))
        err.append(np.hypot(e[:, 0], e[:, 1]))
        zone.append(np.asarray(fr.truth.zone))
    return tuple(np.concatenate(a) for a in (err, nees, zone))


def line(label, err, nees, zone):
    c = zone == "C"
    return (f"{label}: {100 * np.mean(nees[c] < INSIDE_95):.1f} %, NEES {nees[c].mean():.2f}, "
            f"RMSE {np.sqrt(np.mean(err[c] ** 2)):.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("config", type=Path)
    ap.add_argument("--seeds", default="101,102,103")
    ap.add_argument("--dir", type=Path, required=True)
    args = ap.parse_args()
    cfg = load_config(args.config)
    for s in (int(x) for x in args.seeds.split(",")):
        path = args.dir / f"frames_{s}.pkl"
        print(f"seed {s}, zone C")
        print("  " + line("raw fixes", *raw_fix(path)))
        print("  " + line(GNSS.name, *replay_tool.replay(path, cfg.gnss_model, cfg.motion)[:3]))
        orig = replay_tool.frames
        replay_tool.frames = lambda p: shared_removed(orig(p))
        try:
            print("  " + line(f"{GNSS.name}, shared error removed", *replay_tool.replay(path, cfg.gnss_model, cfg.motion)[:3]))
        finally:
            replay_tool.frames = orig


if __name__ == "__main__":
    main()
