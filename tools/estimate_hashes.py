"""SHA-256 of what each shipped config writes, to show that a change leaves estimates as they were.

    python tools/estimate_hashes.py [--quick] [--studies] [--only NAME ...] [--keep DIR]

Runs every shipped run config (``experiments/*.toml`` that is not a study) with ``coloc run`` into a
temporary folder and prints one line per config: the hash of ``estimates.parquet`` (and of
``association.parquet`` / ``features.parquet`` where written). ``--quick`` caps the arterial
configs at 300 simulated seconds, and the configs that run a particle method (``arterial_*_pf.toml``,
hours of PF) at 60; ``--studies`` also runs the study configs of the other source papers (their
Parquet files are hashed). A PF case of the single road (``single_road.toml`` with ``icp_da_pf`` and
``icp_known_da_pf``) is always included.

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


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


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
    coloc = Path(sys.executable).parent / "coloc"
    with tempfile.TemporaryDirectory() as tmpdir:
        base = Path(args.keep) if args.keep else Path(tmpdir)
        for name, cfg, extra in cases(args.quick, args.studies):
            if args.only and name not in args.only:
                continue
            out = base / name
            cmd = [str(coloc), "run", str(ROOT / "experiments" / cfg), "--out", str(out), "--quiet", *extra]
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
            if proc.returncode != 0:
                print(f"{name:>22}: FAILED ({proc.stderr.strip().splitlines()[-1:]})", flush=True)
                continue
            # traffic.parquet is SUMO's (not an estimate); timings.parquet holds wall-clock times (differs
            # from run to run by design)
            files = sorted(p for p in out.rglob("*.parquet") if p.name not in ("traffic.parquet", "timings.parquet"))
            hashes = " ".join(f"{p.relative_to(out)}={_sha(p)}" for p in files)
            print(f"{name:>22} {' '.join(extra)}: {hashes}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
