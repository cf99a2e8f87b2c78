"""Where commands write: the ``--out`` rule, the output lock, and publishing of folders and files.

Every command that writes (``coloc run``, ``coloc sweep``, ``coloc report``, ``coloc net import``,
``python -m couplers.net.build``, the studies) goes through this module, so the rule below lives in
one place:

- **coloc replaces or deletes only files it can prove it wrote.** Every output folder holds a
  manifest, the hidden file :data:`MARKER`: ``{"kind": ..., "files": {relpath: sha256}}``. A file
  is coloc's when the manifest lists it and its content still has that hash; nothing else is
  (never judged by names: a folder holding ``summary.json`` and ``config.toml`` is not thereby a
  run). Publishing over an earlier output replaces and deletes only coloc's files; anything else
  (a user's ``notes.md``, a figure of their own, a file they edited, an unknown folder) is kept in
  place and the new output is merged around it.
- **What is in the way is refused, or with ``--force`` kept aside, never deleted.** A non-empty
  folder without a manifest (or with one of another kind, or with a manifest of an older coloc
  that lists no files) is refused with one line naming it; ``--force`` writes into it. A file the
  new output must occupy that is not coloc's is refused with one line naming it; with ``--force``
  it is renamed to ``NAME.before-coloc`` (``-2``, ``-3``, ... if taken). So not even ``--force``
  deletes a byte coloc did not write.
- **A file never becomes a folder**, not even with ``--force``; the folder a command runs in (or
  one holding it) is never renamed away under it.
- **A symbolic link is never renamed or replaced.** An ``--out`` that is a link is refused, naming
  where it points; with ``--force`` coloc writes through it into the folder it points to.
- **One writer per output.** A command holds ``.NAME.lock`` (``fcntl.flock``) in the parent of
  the output for as long as it writes there; a second command writing to the same place is
  refused with one line. The lock file is removed when released; one left by a killed process (the
  kernel drops its flock) is taken over by the next writer. A file of that name coloc did not write
  is refused, never deleted.
- **Nothing half-written, as far as the file system allows.** Everything is built in a hidden
  staging folder first (``.NAME.partial-PID`` beside a folder output, ``.coloc-staging-PID`` inside
  a folder whose part is rewritten, e.g. a run's report) and removed on any error, Ctrl-C or
  SIGTERM. Then:

  * an absent or empty ``--out``: the staging folder, manifest included, is renamed into place in
    one :func:`os.rename`, so a reader sees nothing or the complete output;
  * an existing output: members are renamed into place one file at a time (each rename atomic, so
    no file is ever seen half-written), between a manifest marked ``"complete": false`` that lists
    the old and the new hashes of every file involved and the final manifest, written last. A
    reader may meanwhile see a mix of old and new files; a process killed there leaves the
    incomplete manifest, from which the next writer still knows every coloc file and cleans them.

  Leftovers of a killed process (SIGKILL: ``.NAME.partial-PID``, ``.NAME.old-PID``,
  ``.coloc-staging-PID``, an older coloc's ``.report-tmp-*``) are removed by the next command that
  writes to the same place, once that process is gone.
"""

from __future__ import annotations

import contextlib
import fcntl
import functools
import glob
import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable, Iterator

from couplers.errors import InputError

MARKER = ".coloc-output"
# "run": every `coloc run` output, studies included; "net": a `coloc net import` folder
KINDS = ("run", "sweep", "report", "net")
ASIDE = ".before-coloc"  # suffix of a file kept aside by --force
_STAGING = (".partial-", ".old-")
_INNER_STAGING = ".coloc-staging-"
_FORCE_HINT = "choose another folder, or pass --force to write into it (nothing in it is deleted)"
# a folder of an older coloc: one --force writes the manifest, later commands need none
_ONCE_HINT = (f"pass --force once to write into it (nothing in it is deleted; a file the new output replaces is "
              f"kept as NAME{ASIDE}), later commands there need no --force")


# --------------------------------------------------------------------------- #
# The manifest
# --------------------------------------------------------------------------- #


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


@functools.lru_cache(maxsize=256)
def _sha256_of(path: str, ino: int, size: int, mtime_ns: int) -> str:
    return sha256_file(Path(path))


def _digest(path: Path) -> str:
    """:func:`sha256_file`, computed once per file version (a rerun checks a large estimates.parquet
    several times: owned?, its previous hash, ...)."""
    st = os.stat(path)
    return _sha256_of(str(path), st.st_ino, st.st_size, st.st_mtime_ns)


def read_manifest(folder: Path) -> dict | None:
    """The manifest of ``folder``: ``{"kind", "files", "replaced", "legacy"}``, or None (no readable marker).

    ``legacy``: a marker of an older coloc that names the kind but lists no files. ``replaced``:
    the previous hashes of files an interrupted publish was replacing (their old and new content
    are both coloc's)."""
    try:
        data = json.loads((Path(folder) / MARKER).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict):
        return None
    files, replaced = data.get("files"), data.get("replaced") or {}
    legacy = files is None
    if not isinstance(files, dict):
        files = {}
    if not isinstance(replaced, dict):
        replaced = {}
    kind = data.get("kind")
    return {"kind": kind if kind in KINDS else None, "files": files, "replaced": replaced, "legacy": legacy}


def output_kind(path: Path) -> str | None:
    """The kind of coloc output ``path`` holds (``"run"``, ``"sweep"``, ...) by its manifest, or None."""
    m = read_manifest(path)
    return None if m is None else m["kind"]


def _owned(folder: Path, rel: str, manifest: dict | None) -> bool:
    """Whether ``folder/rel`` is a regular file coloc wrote: listed in the manifest with its current hash."""
    if manifest is None:
        return False
    p = folder / rel
    if p.is_symlink() or not p.is_file():
        return False
    hashes = {manifest["files"].get(rel), manifest["replaced"].get(rel)} - {None}
    return bool(hashes) and _digest(p) in hashes


def owns(folder: Path, rel: str) -> bool:
    """Whether ``folder/rel`` is a file coloc wrote (its manifest lists it with its current content)."""
    folder = Path(os.path.realpath(folder))
    return _owned(folder, rel, read_manifest(folder))


def _write_manifest(folder: Path, kind: str | None, files: dict[str, str], replaced: dict | None = None) -> None:
    data: dict = {"kind": kind, "files": dict(sorted(files.items()))}
    if replaced is not None:
        data = {"kind": kind, "complete": False, "files": data["files"], "replaced": dict(sorted(replaced.items()))}
    write_file_atomic(Path(folder) / MARKER, json.dumps(data, indent=1) + "\n")


def _tree(root: Path) -> tuple[dict[str, Path], list[str]]:
    """Files (relative POSIX path -> path) and folders under ``root``, the manifest and staging excluded."""
    files, dirs = {}, []
    for here, subdirs, names in os.walk(root):
        rel_here = Path(here).relative_to(root)
        subdirs[:] = sorted(d for d in subdirs if not (here == str(root) and d.startswith(_INNER_STAGING)))
        for d in subdirs:
            dirs.append((rel_here / d).as_posix())
        for n in sorted(names):
            if here == str(root) and n == MARKER:
                continue
            files[(rel_here / n).as_posix()] = Path(here) / n
    return files, dirs


def mark(folder: Path, kind: str) -> None:
    """Give a folder a command writes into in place (a sweep) a manifest of ``kind``, if it has none."""
    if not (Path(folder) / MARKER).is_file():
        _write_manifest(Path(folder), kind, {})


# --------------------------------------------------------------------------- #
# The --out rule
# --------------------------------------------------------------------------- #


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


def _through_link(out: Path, field: str | None, force: bool) -> Path:
    """``out``, or with ``force`` the folder a symbolic link ``out`` points to (refused without ``force``)."""
    if not out.is_symlink():
        return out
    if not out.exists():
        raise InputError(out, field, "is a broken symbolic link: choose another name")
    if not force:
        raise InputError(out, field, f"is a symbolic link to {os.readlink(out)}: choose another name, or pass "
                                     "--force to write through it (the link is kept)")
    return Path(os.path.realpath(out))


def check_target(out: Path, kinds: tuple[str, ...], force: bool = False, field: str | None = "--out",
                 replaces_folder: bool = True, file: bool = False) -> None:
    """Raise :class:`InputError` unless a command may write an output of one of ``kinds`` at ``out``.

    ``kinds`` empty: only an absent or empty folder (``force``: any folder).
    ``replaces_folder``: the command publishes a new folder at ``out`` (a run, an import), rather
    than writing files into it (a sweep, a comparison report).
    ``file``: ``out`` is a file the command writes (absent, or any file with ``force``; never a folder).
    Files in the way inside an accepted folder are checked when publishing (:func:`publish_tree`).
    """
    out = _through_link(Path(out), field, force)
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
    if not kinds:
        raise InputError(out, field, f"already exists: {_FORCE_HINT}")
    m = read_manifest(out)
    if m is None:
        raise InputError(out, field, f"has no {MARKER}, so coloc cannot prove it wrote anything in it: choose "
                                     "another folder, or pass --force to write into it (nothing in it is deleted; "
                                     f"a folder an older coloc wrote before {MARKER} existed needs --force once, "
                                     "later commands there need none)")
    if m["kind"] not in kinds:
        raise InputError(out, field, f"holds a coloc {m['kind'] or 'unknown'} output, not a {' or '.join(kinds)} "
                                     f"output: {_FORCE_HINT}")
    if m["legacy"]:
        raise InputError(out, field, f"was written by an older coloc whose {MARKER} lists no files: {_ONCE_HINT}")


# --------------------------------------------------------------------------- #
# The lock
# --------------------------------------------------------------------------- #

_HELD: dict[str, list] = {}  # lock path -> [fd, depth]: a command re-entering its own lock (a sweep's report)
LOCK_TAG = "coloc output lock, pid "  # the first bytes of every lock file coloc writes


def _lock_text(pid: int) -> bytes:
    return f"{LOCK_TAG}{pid}\n".encode()


def _is_coloc_lock(data: bytes) -> bool:
    """Whether a lock file's bytes are coloc's: its tag and a PID (a bare PID: a coloc before the tag)."""
    text = data.decode("ascii", "replace").strip()
    return text.removeprefix(LOCK_TAG.strip()).strip().isdigit()


class OutputLock:
    """``.NAME.lock`` in the parent of an output, held with ``fcntl.flock`` until :meth:`close`.

    The file is created whole (written under a PID-named temporary, then hard-linked into place, so
    no reader ever sees it empty) and removed on release. A process killed while holding it (SIGKILL
    between publishing and releasing) leaves the file, but the kernel drops its flock: a lock file
    nobody holds is stale and the next writer takes it over. A file of that name coloc did not write
    (without :data:`LOCK_TAG`) is refused with one line, never locked, rewritten or deleted.
    """

    def __init__(self, out: Path, field: str | None = "--out", named: Path | None = None):
        real = Path(os.path.realpath(out))
        self.path = real.parent / f".{real.name}.lock"
        self._key = str(self.path)
        if self._key in _HELD:
            _HELD[self._key][1] += 1
            return
        named = named or Path(out)
        created = make_folder(real.parent, named, field)
        try:
            fd = self._acquire(named, field)
        except BaseException:
            remove_created(created)
            raise
        _HELD[self._key] = [fd, 1]

    def _create(self) -> bool:
        """Put a new lock file (tag and PID) in place; False if one is there already."""
        tmp = self.path.with_name(f"{self.path.name}-new-{os.getpid()}")
        tmp.unlink(missing_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 & ~_umask())
        try:
            os.write(fd, _lock_text(os.getpid()))
        finally:
            os.close(fd)
        try:
            os.link(tmp, self.path)
            return True
        except FileExistsError:
            return False
        finally:
            tmp.unlink(missing_ok=True)

    def _acquire(self, named: Path, field: str | None) -> int:
        busy = InputError(named, field, "another coloc command is writing there (it holds "
                                        f"{self.path}): wait for it, or choose another folder")
        while True:
            try:
                created = self._create()
                fd = os.open(self.path, os.O_RDWR)
            except FileNotFoundError:  # released (and removed) by its holder meanwhile: try again
                continue
            except OSError as exc:
                raise InputError(named, field, f"cannot be created ({exc.strerror or exc})") from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise busy from None
            try:  # the holder before may have removed the file between our open and flock: lock the new one
                same = os.path.samestat(os.fstat(fd), os.stat(self.path))
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            if not created and not _is_coloc_lock(os.pread(fd, 256, 0)):
                os.close(fd)
                raise InputError(self.path, None, "is in the way of the lock coloc takes for "
                                                  f"{named} and was not written by coloc: move it away") from None
            # ours, or a stale lock of a killed coloc (nobody held its flock): taken over
            for leftover in self.path.parent.glob(f"{glob.escape(self.path.name)}-new-*"):
                if _stale(leftover.name):  # a temporary of a coloc killed inside _create
                    leftover.unlink(missing_ok=True)
            if not created:
                os.ftruncate(fd, 0)
                os.pwrite(fd, _lock_text(os.getpid()), 0)
            return fd

    def close(self) -> None:
        held = _HELD.get(self._key)
        if held is None:
            return
        held[1] -= 1
        if held[1] == 0:
            del _HELD[self._key]
            with contextlib.suppress(OSError):
                if os.path.samestat(os.fstat(held[0]), os.stat(self.path)):  # our file, nothing put in its place
                    os.unlink(self.path)  # before unlocking: a waiter then locks a fresh file (see above)
            os.close(held[0])

    def __enter__(self) -> "OutputLock":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def lock_output(out: Path, field: str | None = "--out", named: Path | None = None) -> OutputLock:
    """Lock the output ``out`` for this process (refused with :class:`InputError` if another holds it)."""
    return OutputLock(out, field, named)


# --------------------------------------------------------------------------- #
# Leftovers
# --------------------------------------------------------------------------- #


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def _stale(name: str) -> bool:
    pid = name.rsplit("-", 1)[-1]
    return pid.isdigit() and int(pid) != os.getpid() and not _pid_alive(int(pid))


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p, ignore_errors=True)
    else:
        p.unlink(missing_ok=True)


def remove_stale(parent: Path, name: str) -> list[Path]:
    """Remove ``.NAME.partial-PID`` / ``.NAME.old-PID`` entries in ``parent`` of processes that are gone.

    An ``.old-`` folder whose ``NAME`` is missing (an older coloc killed between its two renames) is
    the previous output: it is put back, not removed.
    """
    removed = []
    if not parent.is_dir():
        return removed
    for tag in _STAGING:
        for p in sorted(parent.glob(f".{name}{tag}*")):
            if not _stale(p.name):
                continue
            if tag == ".old-" and not (parent / name).exists():
                os.replace(p, parent / name)
                continue
            _remove(p)
            removed.append(p)
    return removed


def remove_stale_inside(folder: Path) -> list[Path]:
    """Remove staging folders a killed command left inside ``folder`` (the caller holds its lock).

    ``.coloc-staging-PID`` of a process that is gone; ``.report-tmp-*`` / ``.report-old-*`` of an
    older coloc (they carry no PID; under the lock no coloc of this version writes them)."""
    removed = []
    try:
        entries = sorted(Path(folder).iterdir())
    except OSError:
        return removed
    for p in entries:
        if (p.name.startswith(_INNER_STAGING) and _stale(p.name)) or p.name.startswith((".report-tmp-", ".report-old-")):
            _remove(p)
            removed.append(p)
    return removed


# --------------------------------------------------------------------------- #
# Publishing
# --------------------------------------------------------------------------- #


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _aside(p: Path) -> Path:
    """Rename ``p`` (a file, folder or link in the way) to a free ``NAME.before-coloc[-k]`` beside it."""
    k = 1
    while True:
        dest = p.with_name(p.name + ASIDE + (f"-{k}" if k > 1 else ""))
        if not dest.exists() and not dest.is_symlink():
            os.rename(p, dest)
            return dest
        k += 1


def publish_tree(staging: Path, out: Path, kind: str | None, part: tuple[str, ...] | None = None,
                 force: bool = False, field: str | None = "--out") -> list[Path]:
    """Move the files under ``staging`` into the existing folder ``out``, one rename each; returns
    what ``force`` kept aside.

    ``part``: the top-level names of ``out`` this output rewrites (a report: ``figures``,
    ``report.html``); coloc files listed in the manifest under those names and absent from the
    new output are deleted, the rest of the manifest is carried over. None: the whole output.
    ``kind``: the manifest's kind (None: keep the existing one).
    """
    old = read_manifest(out)
    new_files, new_dirs = _tree(staging)
    new = {rel: sha256_file(p) for rel, p in new_files.items()}

    def in_part(rel: str) -> bool:
        return part is None or rel.split("/", 1)[0] in part

    def in_way() -> list[str]:
        """Paths the new output must occupy that hold something not coloc's (a folder, a link, a user file)."""
        bad = []
        for rel in new_dirs:
            p = out / rel
            if p.is_symlink() or (p.exists() and not p.is_dir()):
                bad.append(rel)
        for rel in new:
            p = out / rel
            if (p.is_symlink() or p.exists()) and not _owned(out, rel, old):
                bad.append(rel)
        return bad

    kept = []
    bad = in_way()
    if bad and not force:
        raise InputError(out / bad[0], field, f"is in the way and coloc cannot prove it wrote it (not in {MARKER}, "
                                              f"or changed since): move it away, or pass --force to keep it as "
                                              f"{Path(bad[0]).name}{ASIDE}")
    while bad:  # shortest first: a file in the place of a folder goes aside with whatever would go in it
        rel = min(bad, key=lambda r: (r.count("/"), r))
        kept.append(_aside(out / rel))
        bad = in_way()
    listed = sorted((old["files"] | old["replaced"]).keys()) if old else []
    # coloc's earlier files of this part that the new output does not have: deleted below
    drop = {rel: _digest(out / rel) for rel in listed
            if in_part(rel) and rel not in new and _owned(out, rel, old)}
    # the rest of the output (a run's files under a rewritten report): listed as they were
    carry = {rel: h for rel, h in (old["files"].items() if old else ()) if not in_part(rel) and rel not in new}
    # files about to be replaced (coloc's, or in_way() would have refused): their old content is coloc's too
    previous = {rel: _digest(out / rel) for rel in new if (out / rel).is_file()}
    kind = kind if kind is not None else (old["kind"] if old else None)
    # From here until the last manifest, the incomplete one lists every file involved, old and new.
    _write_manifest(out, kind, carry | drop | new, previous)
    for rel in new_dirs:
        (out / rel).mkdir(exist_ok=True)
    for rel, src in new_files.items():
        os.replace(src, out / rel)
    for rel, digest in drop.items():
        p = out / rel
        if _owned(out, rel, {"files": {rel: digest}, "replaced": {}}):
            p.unlink()
        for d in p.parents:  # folders emptied by the deletion (coloc's: a user's file keeps its folder)
            if d == out or out not in d.parents:
                break
            try:
                d.rmdir()
            except OSError:
                break
    _write_manifest(out, kind, carry | new)
    return kept


def _publish_new(tmp: Path, out: Path, kind: str | None, force: bool, field: str | None,
                 replace: tuple[str, ...]) -> None:
    """Publish the complete staging folder ``tmp`` at ``out``: one rename onto an absent or empty
    folder, else member by member (:func:`publish_tree`)."""
    if not out.is_symlink() and (not out.exists() or _is_empty_dir(out)):
        files, _ = _tree(tmp)
        _write_manifest(tmp, kind, {rel: sha256_file(p) for rel, p in files.items()})
        os.chmod(tmp, 0o777 & ~_umask())  # an ordinary folder, as mkdir would make it
        try:
            os.rename(tmp, out)  # onto an absent or empty folder: atomic
            return
        except OSError:
            if not out.is_dir():  # not "a file appeared there since", nor "not empty any more"
                raise
        (tmp / MARKER).unlink()
    check_target(out, replace, force=force, field=field, replaces_folder=False)  # may have changed meanwhile
    publish_tree(tmp, out, kind, None, force, field)


@contextlib.contextmanager
def staged_folder(out: Path, kind: str | None, force: bool = False, field: str | None = "--out",
                  replace: tuple[str, ...] | None = None) -> Iterator[Path]:
    """``with staged_folder(out, "run") as tmp:`` write into ``tmp``; it is published at ``out`` on success.

    ``kind`` is written into the manifest (None: ``"net"``, a net folder, replaced only with ``force``).
    ``out`` is checked first (:func:`check_target`: an output of ``replace``, by default ``(kind,)``,
    is written over without ``force``; ``()``: only an absent or empty folder) and locked for the
    whole block; the hidden staging folder sits beside it (same file system, so renames are atomic)
    and is removed on any exception, including KeyboardInterrupt and the SIGTERM the command line
    turns into one.
    """
    named = Path(out)
    replace = ((kind,) if kind else ()) if replace is None else replace
    kind = kind or "net"
    check_target(named, replace, force=force, field=field)
    out = _through_link(named, field, force)
    parent = out.parent
    created = make_folder(parent, named, field)
    try:
        lock = lock_output(out, field, named)
    except BaseException:
        remove_created(created)
        raise
    tmp = parent / f".{out.name}.partial-{os.getpid()}"
    try:
        remove_stale(parent, out.name)
        if out.is_dir():
            remove_stale_inside(out)
        try:
            if tmp.exists():
                shutil.rmtree(tmp)
            tmp.mkdir()
        except OSError as exc:
            raise InputError(named, field, f"cannot be created ({exc.strerror or exc})") from None
        yield tmp
        _publish_new(tmp, out, kind, force, field, replace)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        lock.close()  # its file sits in the parent: released first, so that a parent it created can go too
        lock = None
        remove_created(created)
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if lock is not None:
            lock.close()


def publish_members(target_dir: Path, build: Callable[[Path], None], names: tuple[str, ...],
                    kind: str | None = None, force: bool = False, field: str | None = None) -> list[Path]:
    """Build ``names`` (files or folders) in a staging folder inside ``target_dir``, then move them into place.

    Used to rewrite part of an output (a report's ``report.html`` and ``figures/`` in a run folder,
    a sweep folder or a comparison folder): coloc's earlier files under ``names`` are replaced or
    deleted, anything else is kept (:func:`publish_tree`); ``figures`` before ``report.html``, so the
    page a reader opens comes last. ``kind``: the manifest's kind if the folder has none yet.
    ``target_dir`` is locked meanwhile. Returns what ``force`` kept aside.
    """
    target_dir = Path(os.path.realpath(target_dir))
    created = make_folder(target_dir, None, field)
    with lock_output(target_dir, field):
        remove_stale_inside(target_dir)
        tmp = target_dir / f"{_INNER_STAGING}{os.getpid()}"
        try:
            if tmp.exists():
                shutil.rmtree(tmp)
            tmp.mkdir()
            build(tmp)
            m = read_manifest(target_dir)
            return publish_tree(tmp, target_dir, kind if m is None or m["kind"] is None else None,
                                tuple(names), force, field)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            remove_created(created)
            raise
        finally:
            shutil.rmtree(tmp, ignore_errors=True)


def check_members(folder: Path, names: tuple[str, ...], force: bool = False, field: str | None = None) -> None:
    """Refuse, before any work, an entry among ``names`` in ``folder`` that a later :func:`publish_files`
    or :func:`publish_members` would refuse: a file coloc cannot prove it wrote, or a link (``force``: none,
    they are kept aside then)."""
    folder = Path(os.path.realpath(folder))
    if force or not folder.is_dir():
        return
    m = read_manifest(folder)
    for name in names:
        p = folder / name
        if p.is_symlink() or (p.exists() and not p.is_dir() and not _owned(folder, name, m)):
            raise InputError(p, field, f"is in the way and coloc cannot prove it wrote it (not in {MARKER}, or "
                                       f"changed since): move it away, or pass --force to keep it as "
                                       f"{name}{ASIDE}")


def publish_files(folder: Path, files: dict[str, bytes | str], part: tuple[str, ...] = (), kind: str | None = None,
                  force: bool = False, field: str | None = None) -> list[Path]:
    """Write top-level files (name -> content) of an output written in place (a sweep's ``sweep.toml``,
    ``sweep.parquet``, ...) into ``folder`` as coloc's, listed in its manifest: each replaces only a
    file coloc wrote (:func:`publish_members`). ``part``: further names this output owns that it
    does not write this time (coloc's earlier file of that name is deleted). Returns what ``force``
    kept aside."""

    def build(tmp: Path) -> None:
        for name, data in files.items():
            (tmp / name).write_bytes(data.encode() if isinstance(data, str) else data)

    return publish_members(folder, build, (*files, *part), kind, force, field)


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


def write_file_keeping(target: Path, data: bytes | str) -> Path | None:
    """Write a single-file output (an import's experiment config) that ``--force`` allowed over an
    existing file: a file with other content is kept as ``NAME.before-coloc`` first (returned), so
    not even ``--force`` deletes it; a link is written through."""
    target = Path(os.path.realpath(target))
    raw = data.encode() if isinstance(data, str) else data
    kept = None
    if target.is_file() and target.read_bytes() != raw:
        kept = _aside(target)
    write_file_atomic(target, raw)
    return kept


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
