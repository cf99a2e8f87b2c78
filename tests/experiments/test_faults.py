"""The fault corpus: what coloc's writing commands must never do to a user's files.

Each case puts a user's files where a command writes (a folder that looks like a run, a comparison
folder of their own, a note inside a run, a symbolic link, a second writer, the leftovers of a
killed command) and checks what the command did: refused with one line and everything left byte
for byte, or written with the user's files kept. coloc replaces or deletes only files its manifest
(:data:`couplers.publish.MARKER`) proves it wrote (:mod:`couplers.publish`). Add a case here for
every new way a command could lose a user's file.
"""

from __future__ import annotations

import fcntl
import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from couplers.publish import ASIDE, LOCK_TAG, MARKER, read_manifest
from experiments.cli import main
from filetree import snapshot

PROJECT = Path(__file__).resolve().parents[2]
SINGLE_ROAD = PROJECT / "experiments" / "single_road.toml"  # no SUMO: the cheapest run with a report


def _run(out: Path, *extra: str) -> int:
    return main(["run", str(SINGLE_ROAD), "--out", str(out), "--duration", "30", "--methods", "gnss", "--quiet",
                 *extra])


def _one_error(capsys, *needles: str) -> str:
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("coloc: error: "), err
    for needle in needles:
        assert needle in err, (needle, err)
    return err


def _seed(run: Path) -> int:
    return json.loads((run / "summary.json").read_text())["seed"]


def _dead_pid() -> int:
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    return dead.pid


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A finished 30 s GNSS run of the single road (cases work on copies of it)."""
    tmp = tmp_path_factory.mktemp("fault_run")
    assert _run(tmp / "run", "--seed", "1") == 0
    return tmp / "run"


def _copy(run_dir: Path, dst: Path) -> Path:
    shutil.copytree(run_dir, dst, symlinks=True)
    return dst


# ----------------------------------------------------------------------------- ownership is proved, not guessed


def test_a_folder_with_a_runs_file_names_is_not_taken_for_a_run(tmp_path, capsys):
    """summary.json + config.toml + estimates.parquet do not make a folder a run: refused; with --force the
    run is written into it, the user's files of those names kept aside, everything else left."""
    p = tmp_path / "p"
    (p / "data").mkdir(parents=True)
    (p / "summary.json").write_text("{}\n")
    (p / "config.toml").write_text("x = 1\n")
    (p / "estimates.parquet").write_text("PAR1\n")
    (p / "thesis.tex").write_text("chapter 1\n")
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert _run(p) == 2
    _one_error(capsys, str(p), "--out", "cannot prove it wrote", "--force")
    assert snapshot(tmp_path) == before

    assert _run(p, "--force") == 0
    assert (p / "thesis.tex").read_text() == "chapter 1\n" and (p / "data").is_dir()
    assert (p / f"summary.json{ASIDE}").read_text() == "{}\n"
    assert (p / f"config.toml{ASIDE}").read_text() == "x = 1\n"
    assert (p / f"estimates.parquet{ASIDE}").read_text() == "PAR1\n"
    assert _seed(p) is not None
    files = read_manifest(p)["files"]
    assert "summary.json" in files and "thesis.tex" not in files and f"summary.json{ASIDE}" not in files
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".")]  # no staging, no lock left


def test_a_users_compare_folder_is_not_taken_for_a_comparison(run_dir, tmp_path, capsys):
    """``coloc report A B`` writes ``compare/`` beside A by default: a user's folder there holding
    report.html and figures/ is refused; with --force its files are kept (report.html aside)."""
    a, b = _copy(run_dir, tmp_path / "A"), _copy(run_dir, tmp_path / "B")
    (tmp_path / "compare" / "figures").mkdir(parents=True)
    (tmp_path / "compare" / "report.html").write_text("<p>mine</p>\n")
    (tmp_path / "compare" / "figures" / "my_plot.png").write_bytes(b"my plot")
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert main(["report", str(a), str(b)]) == 2
    _one_error(capsys, "compare", "--out", "cannot prove it wrote", "--force")
    assert snapshot(tmp_path) == before

    assert main(["report", str(a), str(b), "--force"]) == 0
    cmp = tmp_path / "compare"
    assert (cmp / "figures" / "my_plot.png").read_bytes() == b"my plot"
    assert (cmp / f"report.html{ASIDE}").read_text() == "<p>mine</p>\n"
    assert "coloc comparison" in (cmp / "report.html").read_text()
    assert read_manifest(cmp)["kind"] == "report"


def test_a_rerun_keeps_a_users_file_in_the_run_folder(run_dir, tmp_path):
    run = _copy(run_dir, tmp_path / "run")
    (run / "notes.md").write_text("my notes\n")
    (run / "figures" / "mine.png").write_bytes(b"my figure")
    assert _run(run, "--seed", "2") == 0
    assert _seed(run) == 2
    assert (run / "notes.md").read_text() == "my notes\n"
    assert (run / "figures" / "mine.png").read_bytes() == b"my figure"
    files = read_manifest(run)["files"]
    assert "notes.md" not in files and "figures/mine.png" not in files and "summary.json" in files
    assert not [q for q in tmp_path.iterdir() if q.name.startswith(".")]


def test_a_file_the_user_changed_is_not_replaced(run_dir, tmp_path, capsys):
    """A file coloc wrote but the user edited since is the user's now: a rerun is refused naming it (the
    run's files are left as they were), and --force keeps the edited file aside."""
    run = _copy(run_dir, tmp_path / "run")
    with open(run / "report.html", "a") as fh:
        fh.write("<!-- my remark -->\n")
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert _run(run, "--seed", "2") == 2
    _one_error(capsys, "report.html", "--out", "cannot prove it wrote it", "--force")
    assert snapshot(tmp_path) == before

    assert _run(run, "--seed", "2", "--force") == 0
    assert (run / f"report.html{ASIDE}").read_text().endswith("<!-- my remark -->\n")
    assert _seed(run) == 2 and "my remark" not in (run / "report.html").read_text()


def test_a_report_keeps_a_users_figure_and_removes_its_own_old_one(run_dir, tmp_path):
    """``coloc report RUN`` rewrites report.html and figures/: the user's figures/mine.png is kept; a figure
    an earlier report drew and this one does not is deleted (listed in the manifest with its hash)."""
    run = _copy(run_dir, tmp_path / "run")
    (run / "figures" / "mine.png").write_bytes(b"my figure")
    (run / "figures" / "old.png").write_bytes(b"an earlier report's figure")
    manifest = json.loads((run / MARKER).read_text())
    manifest["files"]["figures/old.png"] = hashlib.sha256(b"an earlier report's figure").hexdigest()
    (run / MARKER).write_text(json.dumps(manifest))
    estimates = (run / "estimates.parquet").read_bytes()
    assert main(["report", str(run)]) == 0
    assert (run / "figures" / "mine.png").read_bytes() == b"my figure"
    assert not (run / "figures" / "old.png").exists()
    assert (run / "estimates.parquet").read_bytes() == estimates
    files = read_manifest(run)["files"]
    assert "figures/old.png" not in files and "figures/mine.png" not in files
    assert files["estimates.parquet"] == hashlib.sha256(estimates).hexdigest()  # the run's part carried over
    assert set(files) == {p.relative_to(run).as_posix() for p in run.rglob("*") if p.is_file()} - {
        MARKER, "figures/mine.png"}


def test_an_interrupted_publish_is_finished_by_the_next_writer(run_dir, tmp_path):
    """A process killed while moving files into an existing output leaves the incomplete manifest (old and
    new hashes): the next run still knows every coloc file there, replaces or deletes them, keeps the rest."""
    run = _copy(run_dir, tmp_path / "run")
    (run / "notes.md").write_text("my notes\n")
    (run / "figures" / "extra.png").write_bytes(b"half-published")
    manifest = json.loads((run / MARKER).read_text())
    manifest["complete"] = False
    manifest["replaced"] = {"figures/extra.png": hashlib.sha256(b"half-published").hexdigest()}
    (run / MARKER).write_text(json.dumps(manifest))
    assert _run(run, "--seed", "3") == 0
    assert not (run / "figures" / "extra.png").exists() and (run / "notes.md").read_text() == "my notes\n"
    assert "complete" not in json.loads((run / MARKER).read_text()) and _seed(run) == 3


def test_a_marker_without_a_file_list_is_refused_without_force(run_dir, tmp_path, capsys):
    """An older coloc's marker names the kind only: its files cannot be told from a user's."""
    run = _copy(run_dir, tmp_path / "run")
    (run / MARKER).write_text('{"kind": "run"}\n')
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert _run(run) == 2
    _one_error(capsys, "run", "--out", "older coloc", "pass --force once", "later commands there need no --force")
    assert snapshot(tmp_path) == before
    # as the message says: --force once (the files it replaces kept aside), then no --force any more
    assert _run(run, "--seed", "5", "--force") == 0 and (run / f"summary.json{ASIDE}").is_file()
    assert _run(run, "--seed", "6") == 0 and _seed(run) == 6


def test_a_run_folder_of_a_coloc_before_manifests_needs_force_once(run_dir, tmp_path, capsys):
    run = _copy(run_dir, tmp_path / "run")
    (run / MARKER).unlink()
    capsys.readouterr()
    assert _run(run) == 2
    _one_error(capsys, "run", "--out", f"has no {MARKER}", "--force once")
    assert _run(run, "--seed", "5", "--force") == 0
    assert _run(run, "--seed", "6") == 0 and _seed(run) == 6


# ----------------------------------------------------------------------------- one writer per output


def _hold_lock(out: Path):
    """Hold ``out``'s lock as another coloc command would (a separate open file: flock conflicts in-process too)."""
    fh = open(out.parent / f".{out.name}.lock", "a+")
    fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    fh.write(f"{LOCK_TAG}{os.getpid()}\n")
    fh.flush()
    return fh


def test_a_second_run_into_the_same_folder_is_refused_while_the_first_writes(run_dir, tmp_path, capsys):
    out = tmp_path / "o"
    fh = _hold_lock(out)
    try:
        capsys.readouterr()
        assert _run(out, "--seed", "12") == 2
        _one_error(capsys, str(out), "--out", "another coloc command is writing there")
        assert not out.exists()
        assert sorted(p.name for p in tmp_path.iterdir()) == [".o.lock"]
    finally:
        fh.close()
    assert _run(out, "--seed", "11") == 0 and _seed(out) == 11
    assert not (tmp_path / ".o.lock").exists()  # removed on release


def test_a_report_is_refused_while_a_run_writes_its_folder(run_dir, tmp_path, capsys):
    run = _copy(run_dir, tmp_path / "run")
    before = snapshot(tmp_path)
    fh = _hold_lock(run)
    try:
        capsys.readouterr()
        assert main(["report", str(run)]) == 2
        _one_error(capsys, "run", "another coloc command is writing there")
    finally:
        fh.close()
    (tmp_path / ".run.lock").unlink()
    assert snapshot(tmp_path) == before


_KILL_AFTER_PUBLISH = """
import os, signal, sys
import couplers.publish as pub
from experiments.cli import main

publish = pub._publish_new


def publish_then_die(*args, **kwargs):  # SIGKILL after publishing, before the lock is released
    publish(*args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)


pub._publish_new = publish_then_die
sys.exit(main(sys.argv[1:]))
"""


def test_a_lock_left_by_a_command_killed_after_publishing_is_taken_over(tmp_path):
    """SIGKILL between publishing and releasing the lock: the output is complete, the lock file stays but
    nobody holds its flock; the next writer takes it over and removes it when done."""
    out = tmp_path / "o"
    proc = subprocess.run([sys.executable, "-c", _KILL_AFTER_PUBLISH, "run", str(SINGLE_ROAD), "--out", str(out),
                           "--duration", "30", "--methods", "gnss", "--quiet", "--seed", "3"],
                          cwd=PROJECT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr
    lock = tmp_path / ".o.lock"
    assert lock.read_text().startswith(LOCK_TAG) and _seed(out) == 3  # published whole, the lock file left
    assert _run(out, "--seed", "4") == 0 and _seed(out) == 4
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]  # the stale lock was taken over and removed


def test_a_users_file_with_the_locks_name_is_refused_never_deleted(tmp_path, capsys):
    (tmp_path / ".o.lock").write_text("my own notes, not a lock\n")
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert _run(tmp_path / "o", "--seed", "3") == 2
    _one_error(capsys, ".o.lock", "was not written by coloc", "move it away")
    assert snapshot(tmp_path) == before
    assert _run(tmp_path / "o", "--seed", "3", "--force") == 2  # not even --force takes a user's file
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------- symbolic links


@pytest.mark.parametrize("points_at", ["run", "empty"])
def test_a_symbolic_link_out_is_refused_and_written_through_with_force(points_at, run_dir, tmp_path, capsys):
    target = _copy(run_dir, tmp_path / "target") if points_at == "run" else tmp_path / "target"
    target.mkdir(exist_ok=True)
    (tmp_path / "link").symlink_to("target")
    before = snapshot(tmp_path)
    capsys.readouterr()
    assert _run(tmp_path / "link", "--seed", "7") == 2
    _one_error(capsys, "link", "--out", "is a symbolic link to target", "--force")
    assert snapshot(tmp_path) == before

    assert _run(tmp_path / "link", "--seed", "7", "--force") == 0
    assert (tmp_path / "link").is_symlink() and os.readlink(tmp_path / "link") == "target"
    assert _seed(target) == 7
    assert sorted(p.name for p in tmp_path.iterdir()) == ["link", "target"]  # nothing renamed aside


# ----------------------------------------------------------------------------- leftovers of killed commands


def test_leftovers_of_a_killed_report_are_removed_by_the_next_report(run_dir, tmp_path):
    """A report killed (SIGKILL) while drawing leaves its staging folder inside the run folder; the next
    command writing there removes it once its process is gone (an older coloc's ``.report-tmp-*`` too)."""
    run = _copy(run_dir, tmp_path / "run")
    dead = run / f".coloc-staging-{_dead_pid()}"
    (dead / "figures").mkdir(parents=True)
    (dead / "figures" / "rmse_time.png").write_bytes(b"half")
    (run / ".report-tmp-k3j2h1").mkdir()
    alive = run / f".coloc-staging-{os.getppid()}"  # a live process's: left alone
    alive.mkdir()
    assert main(["report", str(run)]) == 0
    assert not dead.exists() and not (run / ".report-tmp-k3j2h1").exists() and alive.is_dir()


def test_leftovers_of_a_killed_run_are_removed_by_the_next_run_into_an_existing_output(run_dir, tmp_path):
    run = _copy(run_dir, tmp_path / "run")
    partial = tmp_path / f".run.partial-{_dead_pid()}"
    partial.mkdir()
    (partial / "estimates.parquet").write_bytes(b"half")
    (tmp_path / ".run.lock").write_text("12345\n")  # a killed holder's lock file: its flock died with it
    assert _run(run, "--seed", "4") == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run"] and _seed(run) == 4
