"""SHA-256 over every field of every frame of a coupled run (no estimator): a check that a change to the
sensing kept the frames byte for byte.

    python bench/frame_hashes.py [--duration 120] [--seed 1] [--only tlr_realistic,...]

Cases: TLR realistic, TLR realistic with ``[gnss_error] model = "satellites"`` (and with its reflections, Doppler
velocity and residual covariance too, as experiments/sweeps/realistic_tuning_satellites.toml; the realistic presets
now are that world), the TLR realistic preset with the field model, VSR realistic, the pedestrian TLR realistic
preset, TLR idealised (experiments/arterial_*.toml). Arrays hash as dtype, shape and bytes (object arrays by each element's str),
sparse matrices by their CSR arrays, dataclasses field by field in order, other values by repr. Prints the
first 16 hex digits per case.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import sys
from pathlib import Path

import numpy as np
import scipy.sparse as sp

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from couplers.net.folder import load_net_folder  # noqa: E402
from couplers.sumo_coupler import SumoCoupler  # noqa: E402
from experiments.config import load_config  # noqa: E402
from experiments.runner import sumo_scenario  # noqa: E402

CASES = {"tlr_realistic": ("arterial_tlr_realistic.toml", {}),
         "tlr_realistic_satellites": ("arterial_tlr_realistic.toml", {"gnss_error.model": "satellites"}),
         "tlr_realistic_satellites_full": ("arterial_tlr_realistic.toml", {
             "gnss_error.model": "satellites", "gnss_error.nlos": "reflect", "gnss_error.velocity": "doppler",
             "gnss_error.reported_covariance": "residual"}),
         "tlr_realistic_field": ("arterial_tlr_realistic.toml", {"gnss_error.model": "field"}),
         "vsr_realistic": ("arterial_vsr_realistic.toml", {}),
         "ped_tlr_realistic": ("arterial_ped_tlr_realistic.toml", {}),
         "tlr_idealised": ("arterial_tlr.toml", {})}


def update(h, v) -> None:
    if dataclasses.is_dataclass(v) and not isinstance(v, type):
        h.update(type(v).__name__.encode())
        for f in dataclasses.fields(v):
            if f.name == "oracle_gnss" and v.oracle_gnss is None:
                continue  # joint_oracle's channel, off: not hashed, so the hashes from before it stand
            h.update(f.name.encode())
            update(h, getattr(v, f.name))
    elif isinstance(v, np.ndarray):
        h.update(f"{v.dtype}{v.shape}".encode())
        if v.dtype == object:
            for x in v.ravel().tolist():
                b = str(x).encode()
                h.update(len(b).to_bytes(8, "little") + b)
        else:
            h.update(np.ascontiguousarray(v).tobytes())
    elif sp.issparse(v):
        c = sp.csr_matrix(v)
        for a in (c.indptr, c.indices, c.data):
            update(h, np.asarray(a))
        h.update(repr(c.shape).encode())
    elif isinstance(v, (list, tuple)):
        h.update(f"{type(v).__name__}{len(v)}".encode())
        for x in v:
            update(h, x)
    elif isinstance(v, dict):
        for k in sorted(v, key=str):
            h.update(str(k).encode())
            update(h, v[k])
    else:
        h.update(repr(v).encode())


def frames_hash(config: str, overrides: dict, duration: float, seed: int) -> str:
    cfg = load_config(ROOT / "experiments" / config, {"run.duration_s": duration, "run.seed": seed, **overrides})
    h = hashlib.sha256()
    with SumoCoupler(sumo_scenario(cfg, load_net_folder(cfg.net_dir)), cfg.sensors) as coupler:
        for frame in coupler.frames():
            update(h, frame)
    return h.hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--only", default="", help="comma separated case names")
    args = ap.parse_args()
    for name, (config, over) in CASES.items():
        if args.only and name not in args.only.split(","):
            continue
        print(f"{name:>26}: {frames_hash(config, over, args.duration, args.seed)}", flush=True)


if __name__ == "__main__":
    main()
