"""A report page and its figures published atomically into a folder."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from couplers.publish import publish_members


# --------------------------------------------------------------------------- #
# Atomic output
# --------------------------------------------------------------------------- #


def _atomic_publish(target_dir: Path, build: Callable[[Path], None]) -> Path:
    """Build report.html + figures/ (``build(tmp)`` fills ``tmp/figures`` and writes ``tmp/report.html``)
    and move them into ``target_dir``: readers see the old or the new complete page, never a half-written one."""

    def staged(tmp: Path) -> None:
        (tmp / "figures").mkdir()
        build(tmp)

    publish_members(target_dir, staged, ("figures", "report.html"))
    return target_dir / "report.html"
