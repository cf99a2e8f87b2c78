"""numba's compiled kernels: whether this install has them cached, and a warm-up that compiles them.

Every hot loop of coloc is an ``njit(cache=True)`` kernel; numba compiles each on its first call and
keeps the machine code next to the source (``__pycache__/<module>.<function>-<line>.py<ver>.nbi``
index files, or under ``NUMBA_CACHE_DIR``). The first run after an install compiles them all:
COMPILE_MIN_S to COMPILE_MAX_S on 2 cores (see COMPILE_MIN_S), silent without a word. So
``coloc run`` says so when most index files are missing (:func:`cold_cache_note`), and ``make run``'s
install step compiles them once (``python -m experiments.warm``: a 30 s run of the arterial under TLR
with the methods of ``make run``, into a temporary folder).
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
import time
from pathlib import Path

# A new user's first run on 2 cores took 2-5 minutes longer than the next ones (the compilation of the
# kernels make run's methods call: gnss, icp_known_da, icp_da_lc). Not re-measured here: the machine this
# was written on was shared (load ~24 on 2 cores), which makes any timing of it meaningless.
COMPILE_MIN_S = 120.0
COMPILE_MAX_S = 300.0
COLD_SHARE = 0.5  # the cache counts as cold when at least this share of the core kernels' index files is missing
# The kernels every SUMO run calls (the GNSS tracker, the sensor rows, the traffic's continuity): a run of
# any method compiles them, a method's own kernels (PF, RSU, ...) only when that method runs.
CORE = ("coloc/kernels/kalman.py", "couplers/sensing/sensors.py", "couplers/sensing/rows.py",
        "couplers/traffic/sumo.py")

_DECORATOR = re.compile(r"^\s*@(?:numba\.|nb\.)?njit\((?:.*,\s*)?cache=True")
_DEF = re.compile(r"^\s*def\s+([A-Za-z_][A-Za-z0-9_]*)\s*\(")
_PACKAGES = ("coloc", "couplers")


def _index_dir(source_dir: Path) -> Path:
    """Where numba keeps the index files of a source folder's kernels (numba's cache locators)."""
    custom = os.environ.get("NUMBA_CACHE_DIR", "")
    if custom:
        return Path(custom) / source_dir.resolve().relative_to(source_dir.resolve().anchor)
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
            f"about {COMPILE_MIN_S / 60:.0f}-{COMPILE_MAX_S / 60:.0f} min on 2 cores, once per install; "
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
