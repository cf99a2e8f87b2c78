"""SHA-256 of what each shipped config writes, to show that a change leaves estimates as they were.

    python tools/estimate_hashes.py [--quick] [--studies] [--only NAME ...] [--keep DIR]

Runs every shipped run config (``experiments/*.toml`` that is not a study) with ``coloc run`` into a
temporary folder and prints one line per config: the hash of ``estimates.parquet`` (and of
``association.parquet`` / ``features.parquet`` where written). ``--quick`` caps the arterial
configs at 300 simulated seconds, and the configs that run a particle method (``arterial_*_pf.toml``,
hours of PF) at 60; ``--studies`` also runs the study configs of the other source papers (their
Parquet files are hashed). A PF case of the single road (``single_road.toml`` with ``icp_da_pf`` and
``icp_known_da_pf``) is always included.

Beside each file's hash, ``estimates.parquet`` also gets ``cols=``: a hash of its columns by name, leaving out
the columns added since (:data:`ADDED_COLUMNS`, e.g. ``cov_pxy``), so that a listing made before a column
was added can be compared with one made after: equal ``cols=`` means every pre-existing column holds
the same values in the same rows.

The runs use ``python -m experiments.cli`` from this checkout (the ``coloc`` console script imports the
installed checkout, which may be another one).

Run it before and after a change on the same machine and compare the two listings.
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import subprocess
import sys
import tempfile
import tomllib
from pathlib import Path

from coloc.methods.registry import ICP_DA_PF, ICP_KNOWN_DA_PF
from experiments.config import load_config

ROOT = Path(__file__).resolve().parents[1]
PARTICLE_METHODS = (ICP_DA_PF.name, ICP_KNOWN_DA_PF.name)
EXTRA = [("single_road_pf", "single_road.toml", ["--methods", ",".join(PARTICLE_METHODS)])]
QUICK_S, QUICK_PF_S = 300, 60  # --quick: simulated seconds of the long configs, and of those with a PF


#: Columns of estimates.parquet added after the first listings: left out of the ``cols=`` hash.
ADDED_COLUMNS = ("cov_pxy",)


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def column_hash(path: Path, leave_out=ADDED_COLUMNS) -> str:
    """SHA-256 of a Parquet file's columns except ``leave_out``, by name (sorted), each as its name, its Arrow
    type and its values (numbers as little-endian bytes, strings UTF-8 with their lengths): independent
    of the file's layout and of the other columns."""
    import numpy as np
    import pyarrow.parquet as pq

    table = pq.read_table(path)
    h = hashlib.sha256()
    for name in sorted(c for c in table.column_names if c not in leave_out):
        col = table.column(name).combine_chunks()
        h.update(f"{name}:{col.type}:{len(col)}|".encode())
        if col.type in ("string", "large_string") or str(col.type).startswith("dictionary"):
            for v in col.to_pylist():
                b = b"\xff" if v is None else str(v).encode()
                h.update(len(b).to_bytes(8, "little") + b)
        else:
            h.update(np.ascontiguousarray(col.to_numpy(zero_copy_only=False)).tobytes())
    return h.hexdigest()[:16]


def cases(quick: bool, studies: bool) -> list[tuple[str, str, list[str]]]:
    out = []
    for cfg in sorted((ROOT / "experiments").glob("*.toml")):
        data = tomllib.loads(cfg.read_text())
        if "study" in data and not studies:
            continue
        extra = []
        # the resolved [run] table of the SUMO configs: an overlay (``extends``) inherits its duration and methods
        resolved = None if "study" in data else load_config(cfg)
        run = dataclasses.asdict(resolved.run) if resolved is not None and resolved.scenario.kind == "sumo" else \
            data.get("run", {})
        cap = QUICK_PF_S if set(run.get("methods", ())) & set(PARTICLE_METHODS) else QUICK_S
        if quick and "study" not in data and run.get("duration_s", 0) > cap:
            extra = ["--duration", str(cap)]
        out.append((cfg.stem, cfg.name, extra))
    return out + EXTRA


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="arterial configs capped at 300 s, those with a PF at 60 s")
    ap.add_argument("--studies", action="store_true", help="also the study configs (slow)")
    ap.add_argument("--only", nargs="*", help="case names to run (config stems, or single_road_pf)")
    ap.add_argument("--keep", help="write the run folders here instead of a temporary folder")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmpdir:
        base = Path(args.keep) if args.keep else Path(tmpdir)
        for name, cfg, extra in cases(args.quick, args.studies):
            if args.only and name not in args.only:
                continue
            out = base / name
            cmd = [sys.executable, "-m", "experiments.cli", "run", str(ROOT / "experiments" / cfg), "--out", str(out), "--quiet", *extra]
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
            if proc.returncode != 0:
                print(f"{name:>22}: FAILED ({proc.stderr.strip().splitlines()[-1:]})", flush=True)
                continue
            # traffic.parquet is SUMO's (not an estimate); timings.parquet holds wall-clock times (differs
            # from run to run by design)
            files = sorted(p for p in out.rglob("*.parquet") if p.name not in ("traffic.parquet", "timings.parquet"))
            hashes = " ".join(f"{p.relative_to(out)}={_sha(p)}"
                              + (f" cols={column_hash(p)}" if p.name == "estimates.parquet" else "") for p in files)
            print(f"{name:>22} {' '.join(extra)}: {hashes}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
