"""Deterministic netconvert build of a net folder's plain sources.

A net folder written by the project (e.g. ``sumo_nets/arterial``) holds plain
XML sources (``*.nod.xml``, ``*.edg.xml``, ``*.con.xml``, optionally
``*.tll.xml``) and a netconvert configuration ``netconvert.netccfg`` whose file
names are relative to the folder. :func:`build_net` runs netconvert on it and
writes ``tlr.net.xml`` so that two builds on any machine, from any working
directory, give identical bytes: netconvert's header comment (date, version
banner, option dump with paths) is replaced by a fixed comment.

Run as ``python -m couplers.net.build sumo_nets/arterial``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

from couplers.publish import write_file_atomic

CONFIG_NAME = "netconvert.netccfg"
NET_NAME = "tlr.net.xml"

# netconvert writes "<?xml ...?>" then one comment block ("generated on DATE by
# Eclipse SUMO netconvert Version X" plus the configuration) before <net>.
_HEADER_COMMENT = re.compile(r"\A(<\?xml[^>]*\?>\s*)<!--.*?-->\s*", re.DOTALL)


class NetBuildError(RuntimeError):
    """netconvert could not build a net folder (message names the file)."""


def _netconvert() -> str:
    try:
        import sumolib  # noqa: PLC0415
    except ImportError as exc:  # pragma: no cover - environment problem
        raise NetBuildError("sumolib is not installed: cannot locate netconvert") from exc
    binary = sumolib.checkBinary("netconvert")
    if not (os.path.isfile(binary) or _on_path(binary)):
        raise NetBuildError(f"netconvert not found (sumolib.checkBinary returned {binary!r})")
    return binary


def _on_path(name: str) -> bool:
    from shutil import which  # noqa: PLC0415

    return which(name) is not None


def _normalise(text: str) -> str:
    m = _HEADER_COMMENT.match(text)
    if not m:
        raise NetBuildError(f"{NET_NAME}: unexpected netconvert output header")
    fixed = (
        f"<!-- built by couplers.net.build from {CONFIG_NAME} in this folder "
        "(netconvert header with date and paths removed for reproducibility) -->\n\n"
    )
    return m.group(1) + fixed + text[m.end():]


def build_net(folder: Path | str, *, output_name: str = NET_NAME) -> Path:
    """Build ``folder/tlr.net.xml`` from ``folder/netconvert.netccfg``.

    Returns the path of the written net. Raises :class:`NetBuildError` naming
    the offending file when the configuration is missing or netconvert fails.
    The output is first written to a temporary file in the folder and moved
    into place only on success (nothing half-written).
    """
    folder = Path(folder).resolve()
    cfg = folder / CONFIG_NAME
    if not folder.is_dir():
        raise NetBuildError(f"{folder}: not a directory")
    if not cfg.is_file():
        raise NetBuildError(f"{cfg}: netconvert configuration missing")
    binary = _netconvert()
    target = folder / output_name
    fd, tmp_name = tempfile.mkstemp(prefix=".netbuild-", suffix=".net.xml", dir=folder)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        cmd = [
            binary,
            "-c", CONFIG_NAME,
            "--output-file", tmp.name,
            "--no-warnings", "true",
            "--xml-validation", "never",
        ]
        proc = subprocess.run(cmd, cwd=folder, capture_output=True, text=True)
        if proc.returncode != 0:
            msg = (proc.stderr or proc.stdout).strip()
            raise NetBuildError(f"{cfg}: netconvert failed (exit {proc.returncode}): {msg}")
        write_file_atomic(target, _normalise(tmp.read_text(encoding="utf-8")).encode("utf-8"))
    finally:
        if tmp.exists():
            tmp.unlink()
    return target


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m couplers.net.build NET_FOLDER", file=sys.stderr)
        return 2
    try:
        out = build_net(Path(args[0]))
    except NetBuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    print(out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
