"""A report page and its figures published atomically into a folder."""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from couplers.publish import publish_members


# --------------------------------------------------------------------------- #
# Atomic output
# --------------------------------------------------------------------------- #


def _atomic_publish(target_dir: Path, build: Callable[[Path], None], kind: str | None = None,
                    force: bool = False, field: str | None = None) -> Path:
    """Build report.html + figures/ (``build(tmp)`` fills ``tmp/figures`` and writes ``tmp/report.html``)
    and move them into ``target_dir``: readers never see a half-written file, and only coloc's earlier
    report files are replaced (:func:`couplers.publish.publish_members`; ``kind``: the folder's kind
    if it has no manifest yet; ``force``: files in the way are kept aside instead of refused)."""

    def staged(tmp: Path) -> None:
        (tmp / "figures").mkdir()
        build(tmp)

    publish_members(target_dir, staged, ("figures", "report.html"), kind=kind, force=force, field=field)
    return target_dir / "report.html"
