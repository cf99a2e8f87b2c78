"""SUMO tools from the eclipse-sumo wheel for ``coloc net import``.

Where the wheel's SUMO_HOME and binaries are, the tools' environment, running them, and headers
normalised so that outputs are reproducible.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

from couplers.errors import InputError

_HEADER_COMMENT = re.compile(r"\A(<\?xml[^>]*\?>\s*)<!--.*?-->\s*", re.DOTALL)


# --------------------------------------------------------------------------
# SUMO tools from the eclipse-sumo wheel
# --------------------------------------------------------------------------

def _wheel_home() -> str:
    """SUMO_HOME of the eclipse-sumo wheel (bin/, tools/, data/typemap); else the environment's."""
    try:
        import sumo  # noqa: PLC0415  (the eclipse-sumo wheel)

        return sumo.SUMO_HOME
    except ImportError:  # pragma: no cover - environment problem
        return os.environ.get("SUMO_HOME", "")


def _sumo_env() -> dict[str, str]:
    """Environment of the SUMO tools: the wheel's SUMO_HOME (libsumo may point it at its data-only
    package) and its PROJ data (polyconvert needs proj.db)."""
    env = dict(os.environ)
    home = _wheel_home()
    if home:
        env["SUMO_HOME"] = home
        proj = os.path.join(home, "data", "proj")
        if os.path.isdir(proj):
            env["PROJ_LIB"] = env["PROJ_DATA"] = proj
    return env


def _sumo_home() -> Path:
    home = _wheel_home()
    if not home or not (Path(home) / "tools" / "randomTrips.py").is_file():
        raise InputError(None, "SUMO_HOME", f"SUMO tools not found in {home!r}: install the eclipse-sumo package")
    return Path(home)


def _binary(name: str) -> str:
    import sumolib  # noqa: PLC0415

    binary = sumolib.checkBinary(name)
    if not (os.path.isfile(binary) or shutil.which(binary)):
        raise InputError(None, name, f"{name} not found (install the eclipse-sumo package)")
    return binary


def _run(cmd: list[str], cwd: Path, path: Path, what: str) -> None:
    proc = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, env=_sumo_env())
    if proc.returncode != 0:
        lines = [ln for ln in (proc.stderr or proc.stdout).splitlines() if ln.strip() and "Warning" not in ln]
        msg = "; ".join(lines[:3]) or f"exit {proc.returncode}"
        raise InputError(path, None, f"{what} failed: {msg}")


def normalise_header(text: str, note: str) -> str:
    """Replace a SUMO tool's header comment (date, paths) by ``note``, so that outputs are reproducible."""
    m = _HEADER_COMMENT.match(text)
    fixed = f"<!-- {note} (tool header with date and paths removed for reproducibility) -->\n\n"
    if not m:
        return text
    return m.group(1) + fixed + text[m.end():]
