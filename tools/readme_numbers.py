#!/usr/bin/env python3
"""Every number of README.md at a git revision, found again in docs/ or the current README.

The README's measurements moved to docs/. This lists each number the README had
at REV and looks for it, as a whole number token, in ``docs/**/*.md`` and ``README.md`` of
the working tree; it reports the numbers found nowhere, with the old README line they were
on. ``--counts`` also reports numbers that now occur fewer times than they did in the old
README (a number kept elsewhere but dropped from one of its places shows up there), and
``--order`` the old lines whose numbers do not occur in the same order, one after the other,
in any one current file (a table or list rebuilt from a sentence shows up there; read those
lines to see that the numbers kept their context).

    python tools/readme_numbers.py 953e914 [--counts] [--order]

Exit status 1 when some number is missing (0 otherwise). A number is a run of digits with
an optional decimal part and exponent (``2.15``, ``1e-6``, ``5.8e-8``); signs are not part
of it, and ``1.3-1.4x`` is two numbers. Tokens are compared as written (``0.50`` is not
``0.5``).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
NUMBER = re.compile(r"(?<![\d.])\d+(?:\.\d+)?(?:[eE][+-]?\d+)?(?![\d])")


def numbers(text: str) -> list[str]:
    """The number tokens of ``text`` in order (see the module doc for what counts)."""
    return NUMBER.findall(text)


def numbers_by_line(text: str) -> list[tuple[int, str, str]]:
    """(line number, token, line) for every number of ``text``."""
    return [(i, tok, line) for i, line in enumerate(text.splitlines(), 1) for tok in numbers(line)]


def readme_at(rev: str, repo: Path = REPO) -> str:
    return subprocess.run(["git", "show", f"{rev}:README.md"], cwd=repo, check=True,
                          capture_output=True, text=True).stdout


def current_texts(repo: Path = REPO) -> dict[str, str]:
    """The working tree's README.md and docs/**/*.md, by path relative to ``repo``."""
    paths = [repo / "README.md", *sorted((repo / "docs").rglob("*.md"))]
    return {str(p.relative_to(repo)): p.read_text() for p in paths if p.is_file()}


def check(old: str, new_texts: dict[str, str]) -> tuple[list[tuple[int, str, str]], dict[str, tuple[int, int]]]:
    """Missing numbers (line, token, line text) of ``old``, and {token: (old count, new count)}
    for tokens that occur fewer times in ``new_texts`` than in ``old``."""
    have = Counter(tok for text in new_texts.values() for tok in numbers(text))
    occurrences = numbers_by_line(old)
    missing = [(i, tok, line) for i, tok, line in occurrences if tok not in have]
    old_counts = Counter(tok for _, tok, _ in occurrences)
    fewer = {tok: (n, have[tok]) for tok, n in sorted(old_counts.items()) if 0 < have[tok] < n}
    return missing, fewer


def _contains(seq: list[str], sub: list[str]) -> bool:
    n = len(sub)
    return any(seq[i:i + n] == sub for i in range(len(seq) - n + 1))


def out_of_order(old: str, new_texts: dict[str, str]) -> list[tuple[int, str]]:
    """Old lines with two or more numbers whose number sequence is in no current file, in order."""
    streams = [numbers(text) for text in new_texts.values()]
    return [(i, line) for i, line in enumerate(old.splitlines(), 1)
            if len(numbers(line)) >= 2 and not any(_contains(s, numbers(line)) for s in streams)]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rev", help="git revision of the old README (e.g. 953e914)")
    ap.add_argument("--counts", action="store_true", help="also list numbers that now occur fewer times")
    ap.add_argument("--order", action="store_true", help="also list old lines whose numbers are not found in order")
    args = ap.parse_args(argv)
    old = readme_at(args.rev)
    texts = current_texts()
    missing, fewer = check(old, texts)
    occurrences = numbers_by_line(old)
    distinct = {tok for _, tok, _ in occurrences}
    print(f"README.md at {args.rev}: {len(occurrences)} numbers ({len(distinct)} distinct) on "
          f"{len(old.splitlines())} lines; searched in {len(texts)} files: {', '.join(texts)}")
    for i, tok, line in missing:
        print(f"missing: {tok!r} (old README line {i}: {line.strip()[:100]})")
    if args.counts:
        for tok, (n_old, n_new) in fewer.items():
            print(f"fewer: {tok!r} {n_old} times in the old README, {n_new} now")
    if args.order:
        for i, line in out_of_order(old, texts):
            print(f"not in order: old README line {i}: {line.strip()[:100]}")
    print(f"{len({t for _, t, _ in missing})} distinct numbers missing ({len(missing)} occurrences)")
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main())
