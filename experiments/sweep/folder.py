"""A sweep's output folder: its lock, the resolved spec and the recorded inputs a restart is checked against,
and the leftovers of killed runs (the sweep command: :mod:`experiments.sweep.run`)."""

from __future__ import annotations

import glob
import hashlib
import json
import os
import shutil
import tomllib
from pathlib import Path

from couplers.errors import InputError
from couplers.publish import MARKER, lock_output, owns, publish_files
from experiments.sweep.spec import RUNS_DIR, SweepSpec, SweepRun, _first_difference

# --------------------------------------------------------------------------- #
# Output folder: lock, spec check, leftovers
# --------------------------------------------------------------------------- #


def _acquire_lock(out: Path, spec_path: Path):
    return lock_output(out)  # the lock of every coloc output (couplers.publish)


def _check_spec(out: Path, text: str, spec_path: Path, ignore: tuple[str, ...] = ()) -> None:
    """Refuse a sweep that resolves differently from the one stored in ``out/sweep.toml`` (``ignore``:
    keys of [sweep] left out of the comparison)."""
    target = out / "sweep.toml"
    try:
        old = tomllib.loads(target.read_text())
    except tomllib.TOMLDecodeError:
        old = {}
    new = tomllib.loads(text)
    for d in (old, new):
        for key in ignore:
            d.get("sweep", {}).pop(key, None)
    if old != new:
        diff = _first_difference(new, old) or "sweep"
        raise InputError(spec_path, diff,
                         f"{out} holds a different sweep ({target} has another {diff}); "
                         "use another --out folder, or remove that one to start over")


def _check_or_write_spec(out: Path, text: str, spec_path: Path, ignore: tuple[str, ...] = (),
                         force: bool = False) -> None:
    target = out / "sweep.toml"
    if target.exists():
        _check_spec(out, text, spec_path, ignore)
        # --force over changed configs: the sweep as resolved now; a file the manifest does not list (a sweep
        # folder of an older coloc, adopted with --force): written as coloc's
        if (ignore and target.read_text() != text) or not owns(out, target.name):
            publish_files(out, {target.name: text}, force=force)
        return
    if (out / RUNS_DIR).exists():
        raise InputError(spec_path, None, f"{out / RUNS_DIR} exists without {target}: not a sweep folder of this sweep")
    publish_files(out, {target.name: text}, force=force)


INPUTS_FILE = "inputs.json"
# The aggregate tables of a sweep folder and every top-level file the sweep writes there (all listed in
# its manifest, couplers.publish): a user's file of such a name is never replaced.
TABLES = ("sweep.parquet", "curves.parquet", "zones.parquet", "v2v.parquet", "paired.parquet",
          "consistency.parquet", "effects.parquet", "effects.png")
OWN_FILES = ("sweep.toml", INPUTS_FILE, *TABLES, "report.html")


def _sha256(path: Path) -> str | None:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    except FileNotFoundError:
        return None
    return h.hexdigest()


def _net_files(net_dir: Path) -> list[Path]:
    """Every file of a net folder (hidden ones, e.g. an editor's swap files, left out)."""
    return sorted(p.resolve() for p in net_dir.rglob("*")
                  if p.is_file() and not any(part.startswith(".") for part in p.relative_to(net_dir).parts))


def sweep_inputs(spec: SweepSpec, runs: list[SweepRun], config_files: list[Path]) -> dict:
    """What ``DIR/inputs.json`` holds: the sha256 of every file the runs read, and per run the files it
    read. ``config_files``: the TOML files read while the configs were loaded (bases, ``extends``
    chains, net folders' scenario.toml); a factor's own base counts only for that factor's runs. The
    sweep file itself is checked by its resolved values (``DIR/sweep.toml``), not by its bytes."""
    own_bases = {Path(lv.base).resolve() for f in spec.factors for lv in f.levels if lv.base is not None}
    net_dirs = {Path(r.cfg.scenario.net_dir) for r in runs if r.cfg.scenario.net_dir}
    # a net folder's files count for the runs on that net only
    shared = sorted({Path(p) for p in config_files if not any(Path(p).is_relative_to(d) for d in net_dirs)}
                    - (own_bases - {spec.base}) - {spec.path})
    nets: dict[str, list[Path]] = {}
    per_run: dict[str, list[str]] = {}
    for run in runs:
        files = set(shared)
        if run.variant is not None and run.variant.base is not None:
            files.add(Path(run.variant.base).resolve())
        net_dir = run.cfg.scenario.net_dir
        if net_dir and Path(net_dir).is_dir():
            files.update(nets.setdefault(net_dir, _net_files(Path(net_dir))))
        per_run[run.run_id] = sorted(str(p) for p in files)
    hashes = {p: _sha256(Path(p)) for p in sorted({p for ps in per_run.values() for p in ps})}
    return {"files": hashes, "runs": per_run}


def _inputs_text(inputs: dict) -> str:
    return json.dumps(inputs, indent=1, sort_keys=True) + "\n"


def _check_inputs(out: Path, inputs: dict, runs: list[SweepRun], force: bool) -> tuple[frozenset[str], tuple[str, ...]]:
    """Compare the inputs with those a resumed sweep was started with (``out/inputs.json``).

    Returns the finished runs to recompute (``force`` only) and the sweep.toml keys to leave out of its
    check (the resolved base config's hash, when a config file changed and ``force`` recomputes its
    runs). Without ``force``, a changed, removed or added file read by a finished run is an InputError
    naming the file. A folder without inputs.json (written before it existed) is not checked."""
    try:
        old = json.loads((out / INPUTS_FILE).read_text())
        old_files, old_runs = dict(old["files"]), dict(old["runs"])
    except FileNotFoundError:
        return frozenset(), ()
    except (ValueError, KeyError, TypeError):
        raise InputError(out / INPUTS_FILE, None, "not the record of a sweep's inputs (damaged): remove the "
                                                  "sweep folder to start over") from None
    new_files = inputs["files"]
    changed: dict[str, list[str]] = {}  # file -> finished runs made with its old version
    for run in runs:
        if run.run_id not in old_runs or not run_complete(out / RUNS_DIR / run.run_id):
            continue  # computed with the inputs of now
        before = {p: old_files.get(p) for p in old_runs[run.run_id]}
        now = {p: new_files.get(p) for p in inputs["runs"][run.run_id]}
        for p in sorted(set(before) | set(now)):
            if before.get(p) != now.get(p):
                changed.setdefault(p, []).append(run.run_id)
    if not changed:
        return frozenset(), ()
    redo = frozenset(r for ids in changed.values() for r in ids)
    if force:
        net_dirs = {r.cfg.scenario.net_dir for r in runs if r.cfg.scenario.net_dir}
        configs_changed = any(not any(Path(p).is_relative_to(d) for d in net_dirs) for p in changed)
        return redo, ("base_config_sha256",) if configs_changed else ()
    first = next(iter(changed))
    if first not in old_files:
        state = "is new"
    elif new_files.get(first) is None:
        state = "is no longer read by the runs" if Path(first).exists() else "was removed"
    else:
        state = "changed"
    others = f" (and {len(changed) - 1} other file(s))" if len(changed) > 1 else ""
    raise InputError(first, None,
                     f"{state} since the sweep in {out} started{others}: {len(redo)} finished run(s) read the old "
                     f"inputs (e.g. {min(redo)}); restore it, pass --force to recompute those runs, or use another "
                     "--out folder")


def _restart_changed(out: Path, inputs: dict, redo: frozenset[str], force: bool = False) -> None:
    """Remove the finished runs to recompute (through a hidden name, so a kill leaves a leftover that
    :func:`clean_leftovers` removes, never a half-removed run), then record the inputs of now."""
    for run_id in sorted(redo):
        run_dir = out / RUNS_DIR / run_id
        if run_dir.exists():
            hidden = run_dir.with_name(f".{run_id}.old-{os.getpid()}")
            os.replace(run_dir, hidden)
            shutil.rmtree(hidden)
    text = _inputs_text(inputs)
    target = out / INPUTS_FILE
    if not target.is_file() or target.read_text() != text or not owns(out, INPUTS_FILE):
        publish_files(out, {INPUTS_FILE: text}, force=force)


def clean_leftovers(out: Path) -> list[Path]:
    """Remove the hidden partial folders and temporary files a killed sweep or run left behind."""
    removed = []
    # temporaries of coloc's own files only (a user's hidden file is never taken for one)
    candidates = [p for name in (*OWN_FILES, MARKER) for p in out.glob(f".{glob.escape(name)}.tmp-*")]
    candidates += list(out.glob(".report-*"))
    runs = out / RUNS_DIR
    if runs.is_dir():
        candidates += [p for p in runs.iterdir() if p.name.startswith(".") and (".partial-" in p.name or ".old-" in p.name)]
    for p in sorted(candidates):
        if p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
        else:
            p.unlink(missing_ok=True)
        removed.append(p)
    return removed


def run_complete(run_dir: Path) -> bool:
    # run_experiment renames a finished folder into place: if it exists it is complete.
    return (run_dir / "summary.json").is_file()
