"""numba's compiled kernels: whether this install has them cached, and a warm-up that compiles them.

Every hot loop of coloc is an ``njit(cache=True)`` kernel; numba compiles each on its first call and
keeps the machine code next to the source (``__pycache__/<module>.<function>-<line>.py<ver>.nbi``
index files, or under ``NUMBA_CACHE_DIR``). The first run after an install compiles them all:
about COMPILE_CPU_S seconds of one core (measured, see there), silent without a word. So
``coloc run`` says so when most index files are missing (:func:`cold_cache_note`), and ``make run``'s
install step compiles them once (``python -m experiments.warm``: a 30 s run of the arterial under TLR
with the methods of ``make run``, into a temporary folder).
"""

from __future__ import annotations

import hashlib
import os
import re
import sys
import tempfile
import time
from pathlib import Path

# Measured: `python -m experiments.warm` (the 30 s arterial run of make run's methods) with a fresh
# NUMBA_CACHE_DIR took 208.6 s of CPU (user; 24 min wall on a shared 2-core AMD EPYC VM at load 20-25),
# the same run on the filled cache 5.9 s (67 s wall): compiling costs about 200 s of one core, and numba
# compiles on one thread, so about 3.5 min on an idle machine, longer when the machine is shared.
COMPILE_CPU_S = 203.0
COLD_SHARE = 0.5  # the cache counts as cold when at least this share of the core kernels' index files is missing
# The kernels every SUMO run calls (the GNSS tracker, the sensor rows, the traffic's continuity): a run of
# any method compiles them, a method's own kernels (PF, RSU, ...) only when that method runs.
CORE = ("coloc/kernels/kalman.py", "couplers/sensing/sensors.py", "couplers/sensing/rows.py",
        "couplers/traffic/sumo.py")

_DECORATOR = re.compile(r"^\s*@(?:numba\.|nb\.)?njit\((?:.*,\s*)?cache=True")
_DEF = re.compile(r"^\s*def\s+([A-Za-z_][A-Za-z0-9_]*)\s*\(")
_PACKAGES = ("coloc", "couplers")


def _index_dir(source_dir: Path) -> Path:
    """Where numba keeps the index files of a source folder's kernels (numba's cache locators; under
    ``NUMBA_CACHE_DIR``: ``<folder name>_<sha1 of its absolute path>``, numba.core.caching
    ``_CacheLocator.get_suitable_cache_subpath``)."""
    custom = os.environ.get("NUMBA_CACHE_DIR", "")
    if custom:
        folder = os.path.abspath(source_dir)
        return Path(custom) / f"{os.path.basename(folder)}_{hashlib.sha1(folder.encode()).hexdigest()}"
    return source_dir / "__pycache__"


def kernel_index_files(root: Path | None = None, sources: tuple[str, ...] | None = None) -> list[Path]:
    """The index file each cached kernel of coloc and couplers (or of ``sources``, paths relative to the
    project) has once it was compiled (from the sources: nothing imported)."""
    root = Path(root) if root is not None else Path(__file__).resolve().parents[1]
    tag = f"py{sys.version_info.major}{sys.version_info.minor}"
    out = []
    files = ([root / s for s in sources] if sources is not None else
             [src for pkg in _PACKAGES for src in sorted((root / pkg).rglob("*.py"))])
    for src in files:
        lines = src.read_text(encoding="utf-8", errors="replace").splitlines()
        for i, line in enumerate(lines):
            if not _DECORATOR.match(line):
                continue
            for nxt in lines[i + 1:i + 4]:  # the def, after any further decorators
                m = _DEF.match(nxt)
                if m:
                    out.append(_index_dir(src.parent) / f"{src.stem}.{m.group(1)}-{i + 1}.{tag}.nbi")
                    break
    return out


def cold_cache_note(root: Path | None = None) -> str | None:
    """One line for a run on a cold numba cache (None when most of the CORE kernels are cached)."""
    files = kernel_index_files(root, CORE)
    missing = sum(1 for f in files if not f.is_file())
    if not files or missing < COLD_SHARE * len(files):
        return None
    return ("coloc: compiling numba kernels (first run after install: "
            f"{missing} of the {len(files)} every run calls not cached), "
            f"about {COMPILE_CPU_S / 60:.1f} min of one core (measured with a fresh cache; longer on a busy "
            "machine), once per install; "
            "the progress ETA leaves it out")


def warm(duration_s: float = 30.0) -> float:
    """Compile the kernels of ``make run``: a short run of the arterial under TLR; returns the seconds."""
    from experiments.config import load_config  # noqa: PLC0415
    from experiments.runner import run_experiment  # noqa: PLC0415

    root = Path(__file__).resolve().parents[1]
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="coloc-warm-") as tmp:
        cfg = load_config(root / "experiments" / "arterial_tlr.toml", {"run.duration_s": duration_s})
        run_experiment(cfg, Path(tmp) / "run", progress=False, write_report=False)
    return time.perf_counter() - t0


def main() -> int:
    note = cold_cache_note()
    if note is None:
        print("coloc: numba kernels already compiled")
        return 0
    print(note.replace("; the progress ETA leaves it out", "") + "...", flush=True)
    print(f"coloc: kernels compiled in {warm():.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
