"""No tracker numbers in the product: a user who clones coloc has no issue tracker, so code, configs
and docs say what a thing is (the model, the source, the measurement, the study), never which ticket
asked for it. Fails on "issue 21", "Issues 21, 22", "issue #7" in every tracked *.py, *.toml, *.md,
*.txt, *.cfg and Makefile (the list from ``git ls-files``; skipped outside a git checkout)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SELF = Path(__file__).resolve().relative_to(ROOT).as_posix()
PATTERN = re.compile(r"\bissues?\s*#?\s*[0-9]", re.IGNORECASE)
SUFFIXES = (".py", ".toml", ".md", ".txt", ".cfg")
#: Files still allowed to carry a tracker number; must stay empty.
ALLOWED: set[str] = set()  # nothing: a mention of a tracker number says what it stands for instead


def _tracked_files() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("not a git checkout")
    out = subprocess.run(
        ["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True
    ).stdout.decode()
    return [p for p in out.split("\0") if p and (p.endswith(SUFFIXES) or Path(p).name == "Makefile")]


def test_no_tracker_numbers_in_code_configs_and_docs():
    hits = []
    for rel in _tracked_files():
        if rel == SELF or rel in ALLOWED:
            continue
        path = ROOT / rel
        if not path.is_file():
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            if PATTERN.search(line):
                hits.append(f"{rel}:{n}: {line.strip()}")
    assert not hits, "tracker numbers (say what they stand for instead):\n" + "\n".join(hits)


def test_the_pattern_catches_what_it_should():
    for text in ("issue 21 item 4", "(Issue 26)", "issues 21, 22", "issue #7", "ISSUE 2"):
        assert PATTERN.search(text), text
    for text in ("the GNSS tracker", "an issue of scale", "tissue 5"):
        assert not PATTERN.search(text), text
