"""Two-level fractional factorial designs of resolution >= IV, and the effects a sweep over one estimates.

A 2^(k-p) design runs the full factorial of its first k - p factors (the *basic* factors, columns of -1/+1
in standard order) and sets each of the p others to a product of basic columns, its *generator*. The
generators are the minimum-aberration ones of Montgomery, Design and Analysis of Experiments (8th ed.),
Table 8.14, the same as the NIST/SEMATECH e-Handbook, 5.3.3.4.7 (letters A, B, ... without I). The defining
relation is the group the words ``I = <added letter><generator>`` span; the design's resolution is its
shortest word's length. At resolution IV no main effect is aliased with another main effect or with a
two-factor interaction; two-factor interactions may be aliased with each other (:func:`alias_pairs`).

Effects (:func:`effects`): ordinary least squares of a response on the coded columns (-1/+1) of the main
effects and of the two-factor interactions that are not aliased with an earlier one, over every run (seed
replicates included); an effect is the change from the low to the high level, 2 x the coefficient; its 95 %
interval is the t interval of the coefficient with the residual degrees of freedom.
"""
from __future__ import annotations

import itertools

import numpy as np

LETTERS = "ABCDEFGHJKLMNOPQRSTUVWXYZ"  # I is the identity of the defining relation, never a factor

# (k, p): (resolution, generators of the added factors in letter order). Montgomery Table 8.14 / NIST
# 5.3.3.4.7, the designs of resolution IV or more with k <= 11.
GENERATORS: dict[tuple[int, int], tuple[int, tuple[str, ...]]] = {
    (4, 1): (4, ("ABC",)),
    (5, 1): (5, ("ABCD",)),
    (6, 1): (6, ("ABCDE",)),
    (6, 2): (4, ("ABC", "BCD")),
    (7, 1): (7, ("ABCDEF",)),
    (7, 2): (4, ("ABCD", "ABDE")),
    (7, 3): (4, ("ABC", "BCD", "ACD")),
    (8, 2): (5, ("ABCD", "ABEF")),
    (8, 3): (4, ("ABC", "ABD", "BCDE")),
    (8, 4): (4, ("BCD", "ACD", "ABC", "ABD")),
    (9, 2): (6, ("ACDFG", "BCEFG")),
    (9, 3): (4, ("ABCD", "ACEF", "CDEF")),
    (9, 4): (4, ("BCDE", "ACDE", "ABDE", "ABCE")),
    (10, 3): (5, ("ABCG", "BCDE", "ACDF")),
    (10, 4): (4, ("BCDF", "ACDF", "ABDE", "ABCE")),
    (10, 5): (4, ("ABCD", "ABCE", "ABDE", "ACDE", "BCDE")),
    (11, 5): (4, ("CDE", "ABCD", "ABF", "BDEF", "ADEF")),
    (11, 6): (4, ("ABC", "BCD", "CDE", "ACD", "ADE", "BDE")),
}
MIN_FACTORS = 4  # below 4 factors no fraction of resolution IV exists: run the full design (2^k runs)


def choose(k: int, runs: int | None = None) -> tuple[int, int, tuple[str, ...]]:
    """(p, resolution, generators) of the smallest tabulated fraction with at least ``runs`` runs (None:
    the smallest of resolution >= IV). ValueError when there is none for k factors."""
    options = sorted(((p, *GENERATORS[(k, p)]) for kk, p in GENERATORS if kk == k), key=lambda o: -o[0])
    if runs is not None:
        options = [o for o in options if 2 ** (k - o[0]) >= runs]
    if not options:
        have = sorted(kk for kk, _ in GENERATORS)
        raise ValueError(f"no tabulated fraction of resolution >= IV for {k} factors "
                         f"(from {have[0]} to {have[-1]} factors{'' if runs is None else f' with >= {runs} runs'})")
    return options[0]


def full_design(k: int) -> np.ndarray:
    """(2^k, k) coded levels -1/+1 in standard (Yates) order: the first factor alternates fastest."""
    return np.array([[1 if (i >> j) & 1 else -1 for j in range(k)] for i in range(2 ** k)], dtype=np.int8)


def fractional_design(k: int, generators: tuple[str, ...]) -> np.ndarray:
    """(2^(k-p), k) coded levels: the basic factors' full design, then each added factor the product of its
    generator's columns."""
    p = len(generators)
    base = full_design(k - p)
    cols = [base[:, j] for j in range(k - p)]
    for g in generators:
        cols.append(np.prod([base[:, LETTERS.index(c)] for c in g], axis=0).astype(np.int8))
    return np.stack(cols, axis=1)


def _word_mul(a: str, b: str) -> str:
    """Product of two words (letters squared are the identity)."""
    return "".join(sorted(set(a) ^ set(b), key=LETTERS.index))


def defining_relation(k: int, generators: tuple[str, ...]) -> list[str]:
    """Every word of the defining relation (without I), shortest first then alphabetical."""
    p = len(generators)
    base_words = [g + LETTERS[k - p + i] for i, g in enumerate(generators)]
    words = set()
    for r in range(1, p + 1):
        for combo in itertools.combinations(base_words, r):
            w = ""
            for x in combo:
                w = _word_mul(w, x)
            words.add(w)
    return sorted(words, key=lambda w: (len(w), [LETTERS.index(c) for c in w]))


def resolution(k: int, generators: tuple[str, ...]) -> int:
    return min(len(w) for w in defining_relation(k, generators)) if generators else k + 1


def aliases(effect: str, k: int, generators: tuple[str, ...]) -> list[str]:
    """The effects aliased with ``effect`` (a word such as "A" or "AB")."""
    return sorted((_word_mul(effect, w) for w in defining_relation(k, generators)),
                  key=lambda w: (len(w), [LETTERS.index(c) for c in w]))


def alias_pairs(k: int, generators: tuple[str, ...]) -> dict[str, list[str]]:
    """Each two-factor interaction and the main effects and two-factor interactions aliased with it."""
    out = {}
    for a, b in itertools.combinations(LETTERS[:k], 2):
        out[a + b] = [w for w in aliases(a + b, k, generators) if len(w) <= 2]
    return out


def model_terms(k: int, generators: tuple[str, ...]) -> list[str]:
    """Main effects, then the two-factor interactions not aliased with a main effect or an earlier
    interaction (the first of each alias chain is the one estimated, its chain named in the output)."""
    terms = list(LETTERS[:k])
    taken = set(terms)
    for ab, chain in alias_pairs(k, generators).items():
        if ab in taken or any(w in taken for w in chain):
            continue
        terms.append(ab)
        taken.add(ab)
    return terms


def effects(levels: np.ndarray, y: np.ndarray, k: int, generators: tuple[str, ...] = (),
            names: list[str] | None = None) -> list[dict]:
    """Effects (high - low) with 95 % t intervals: ``levels`` (n, k) coded -1/+1 per run (replicates
    repeated), ``y`` (n,). One dict per term: term (factor names joined by " x "), letters, aliases,
    effect, ci_low, ci_high, se, dof."""
    from scipy import stats  # noqa: PLC0415 - scipy is only needed when effects are estimated

    levels = np.asarray(levels, dtype=float)
    y = np.asarray(y, dtype=float)
    names = names or list(LETTERS[:k])
    terms = model_terms(k, generators)
    cols = [np.ones(len(y))]
    for t in terms:
        cols.append(np.prod([levels[:, LETTERS.index(c)] for c in t], axis=0))
    X = np.stack(cols, axis=1)
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    dof = len(y) - X.shape[1]
    resid = y - X @ coef
    if dof > 0:
        s2 = float(resid @ resid) / dof
        cov = s2 * np.linalg.inv(X.T @ X)
        se = np.sqrt(np.diag(cov))
        q = float(stats.t.ppf(0.975, dof))
    else:  # saturated: no residual left to estimate the noise
        se, q = np.full(X.shape[1], np.nan), np.nan
    out = []
    for i, t in enumerate(terms, start=1):
        e, half = 2.0 * coef[i], 2.0 * q * se[i]
        out.append({"term": " x ".join(names[LETTERS.index(c)] for c in t), "letters": t,
                    "aliases": ",".join(w for w in aliases(t, k, generators) if len(w) <= 3 and w != t),
                    "effect": float(e), "ci_low": float(e - half), "ci_high": float(e + half),
                    "se": float(2.0 * se[i]), "dof": int(dof)})
    return out
