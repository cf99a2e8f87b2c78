"""Where commands write: the ``--out`` rule, and atomic publishing of folders and files.

Every command that writes (``coloc run``, ``coloc sweep``, ``coloc report``, ``coloc net import``,
``python -m couplers.net.build``, the studies) goes through this module, so the rule below lives in
one place:

- **Nothing a user owns is replaced.** An existing ``--out`` is used only when it is empty or was
  written by coloc as the same kind of output (a marker file :data:`MARKER` names the kind; folders
  written before the marker existed are recognised by their files). Anything else is refused with
  one line naming the folder, unless the user passes ``--force``.
- **A file never becomes a folder**, not even with ``--force``; and the folder a command runs in
  (or one holding it) is never renamed away under it.
- **Nothing is half-written.** A folder is built in a hidden sibling ``.NAME.partial-PID`` and
  renamed into place only when complete; on any error, Ctrl-C or SIGTERM the partial folder is
  removed. Partial folders left by a killed process (SIGKILL) are removed by the next command that
  writes to the same place, once that process is gone.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator

from couplers.errors import InputError

MARKER = ".coloc-output"
KINDS = ("run", "sweep", "report")  # "run": every `coloc run` output, studies included

# Files by which folders written before the marker are recognised, per kind (any one tuple whole).
_LEGACY = {
    "run": (("summary.json", "config.toml", "estimates.parquet"),  # a run
            ("summary.json", "config.toml", "results.parquet")),  # a study
    "sweep": (("sweep.toml",),),
}
_REPORT_ENTRIES = {"report.html", "figures", MARKER}
_STAGING = (".partial-", ".old-")


def output_kind(path: Path) -> str | None:
    """The kind of coloc output ``path`` holds (``"run"``, ``"sweep"``, ...), or None."""
    path = Path(path)
    marker = path / MARKER
    if marker.is_file():
        try:
            kind = json.loads(marker.read_text()).get("kind")
        except (OSError, ValueError, AttributeError):
            return None
        return kind if kind in KINDS else None
    for kind, alternatives in _LEGACY.items():
        if any(all((path / n).is_file() for n in names) for names in alternatives):
            return kind
    try:
        entries = {p.name for p in path.iterdir()}
    except OSError:
        return None
    if "report.html" in entries and entries <= _REPORT_ENTRIES:
        return "report"
    return None


def _is_empty_dir(path: Path) -> bool:
    try:
        return not any(path.iterdir())
    except OSError:
        return False


def _holds_cwd(path: Path) -> bool:
    try:
        cwd = Path.cwd().resolve()
    except OSError:  # the working folder was removed
        return False
    target = path.resolve()
    return target == cwd or target in cwd.parents


def check_target(out: Path, kinds: tuple[str, ...], force: bool = False, field: str | None = "--out",
                 replaces_folder: bool = True, file: bool = False) -> None:
    """Raise :class:`InputError` unless a command may write an output of one of ``kinds`` at ``out``.

    ``kinds`` empty: only an absent or empty folder (``force``: any folder).
    ``replaces_folder``: the command renames a new folder over ``out`` (a run, an import), rather
    than writing files into it (a sweep, a comparison report).
    ``file``: ``out`` is a file the command writes (absent, or any file with ``force``; never a folder).
    """
    out = Path(out)
    if out.is_symlink() and not out.exists():
        raise InputError(out, field, "is a broken symbolic link: choose another name")
    if file:
        if out.is_dir():
            raise InputError(out, field, "is a folder, not a file: choose another name")
        if out.exists() and not force:
            raise InputError(out, field, "already exists (pass --force to replace it)")
        return
    if out.exists() and not out.is_dir():
        raise InputError(out, field, "is a file, not a folder: choose another folder (a file is never replaced)")
    if replaces_folder and out.exists() and _holds_cwd(out):
        raise InputError(out, field, "is the current working folder or holds it: choose a folder beside or "
                                     "below it (a finished output is renamed into place)")
    if not out.exists() or force or _is_empty_dir(out):
        return
    found = output_kind(out)
    if found in kinds:
        return
    if not kinds:
        what = "already exists"
    elif found:
        what = f"holds a coloc {found} output, not a {' or '.join(kinds)} output"
    else:
        what = "exists and was not written by coloc"
    raise InputError(out, field, f"{what}: choose another folder, or pass --force to replace what is there")


def _write_marker(folder: Path, kind: str) -> None:
    (folder / MARKER).write_text(json.dumps({"kind": kind}) + "\n")


def mark(folder: Path, kind: str) -> None:
    """Mark a folder a command writes into in place (a sweep) as a coloc output of ``kind``."""
    if not (Path(folder) / MARKER).is_file():
        _write_marker(Path(folder), kind)


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_stale(parent: Path, name: str) -> list[Path]:
    """Remove ``.NAME.partial-PID`` / ``.NAME.old-PID`` entries in ``parent`` of processes that are gone.

    An ``.old-`` folder whose ``NAME`` is missing (a process killed between its two renames) is the
    previous output: it is put back, not removed.
    """
    removed = []
    if not parent.is_dir():
        return removed
    for tag in _STAGING:
        for p in sorted(parent.glob(f".{name}{tag}*")):
            pid = p.name.rsplit("-", 1)[-1]
            if not pid.isdigit() or int(pid) == os.getpid() or _pid_alive(int(pid)):
                continue
            if tag == ".old-" and not (parent / name).exists():
                os.replace(p, parent / name)
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            removed.append(p)
    return removed


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def staged_folder(out: Path, kind: str | None, force: bool = False, field: str | None = "--out",
                  replace: tuple[str, ...] | None = None) -> Iterator[Path]:
    """``with staged_folder(out, "run") as tmp:`` write into ``tmp``; it replaces ``out`` only on success.

    ``kind`` is written into the :data:`MARKER` file of the new folder; None writes no marker (a net
    folder: users keep it with their data, and it is only ever replaced with ``force``).

    ``out`` is checked first (:func:`check_target`: an output of ``replace``, by default ``(kind,)``,
    is replaced without ``force``; ``()``: only an absent or empty folder); the hidden staging folder sits beside it (same
    file system, so the final rename is atomic) and is removed on any exception, including
    KeyboardInterrupt and the SIGTERM the command line turns into one.
    """
    out = Path(out)
    replace = ((kind,) if kind else ()) if replace is None else replace
    check_target(out, replace, force=force, field=field)
    parent = out.parent
    created = make_folder(parent, out, field)
    remove_stale(parent, out.name)
    tmp = parent / f".{out.name}.partial-{os.getpid()}"
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
    except OSError as exc:
        remove_created(created)
        raise InputError(out, field, f"cannot be created ({exc.strerror or exc})") from None
    try:
        yield tmp
        if kind is not None:
            _write_marker(tmp, kind)
        os.chmod(tmp, 0o777 & ~_umask())  # an ordinary folder, as mkdir would make it
        check_target(out, replace, force=force, field=field)  # the place may have changed meanwhile
        old = None
        if out.exists():
            old = parent / f".{out.name}.old-{os.getpid()}"
            os.replace(out, old)
        try:
            os.replace(tmp, out)
        except BaseException:
            if old is not None:  # put the previous output back
                os.replace(old, out)
            raise
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        remove_created(created)
        raise


def publish_members(target_dir: Path, build: Callable[[Path], None], names: tuple[str, ...]) -> None:
    """Build ``names`` (files or folders) in a staging folder inside ``target_dir``, then move each into place.

    Used to rewrite part of an existing output (a report's ``report.html`` and ``figures/`` in a
    run folder). The entries are replaced in the given order with :func:`os.replace`, so a reader
    sees the old or the new entry, never a half-written one; the last name should be the one a
    reader opens (``report.html``).
    """
    target_dir = Path(target_dir)
    make_folder(target_dir)
    tmp = Path(tempfile.mkdtemp(prefix=".report-tmp-", dir=target_dir))
    old = None
    try:
        build(tmp)
        for name in names:
            dest = target_dir / name
            if (tmp / name).is_dir() and dest.exists():
                old = old or Path(tempfile.mkdtemp(prefix=".report-old-", dir=target_dir))
                os.replace(dest, old / name)
            os.replace(tmp / name, dest)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def write_file_atomic(target: Path, data: bytes | str) -> None:
    """Write a file through a hidden temporary beside it and :func:`os.replace`; ordinary permissions."""
    target = Path(target)
    fd, name = tempfile.mkstemp(prefix=f".{target.name}.tmp-", dir=target.parent)
    tmp = Path(name)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data.encode() if isinstance(data, str) else data)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def make_folder(path: Path, named: Path | None = None, field: str | None = "--out") -> list[Path]:
    """:func:`make_dirs`, with a refusal of the file system (read-only, no such place) as an
    :class:`InputError` naming ``named`` (default ``path``) and ``field``."""
    try:
        return make_dirs(path)
    except OSError as exc:
        raise InputError(named or path, field, f"cannot be created ({exc.strerror or exc})") from None


def make_dirs(path: Path) -> list[Path]:
    """``mkdir -p path``; returns the folders it created, outermost first (see :func:`remove_created`)."""
    path = Path(path).resolve()
    missing = [p for p in (path, *path.parents) if not p.exists()][::-1]
    path.mkdir(parents=True, exist_ok=True)
    return missing


def remove_created(created: list[Path]) -> None:
    """Remove the folders :func:`make_dirs` created, innermost first, where still empty."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:  # not empty (someone else's files) or already gone
            pass
