"""Two-level fractional factorial designs: the defining relations and alias chains of the reference tables
(Montgomery, Design and Analysis of Experiments, Table 8.14 and Sec. 8.4-8.5; NIST e-Handbook 5.3.3.4.7),
and effects recovered from synthetic data with known effects."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from experiments.sweep import design as d


@pytest.mark.parametrize("kp", sorted(d.GENERATORS))
def test_every_tabulated_design_has_its_stated_resolution(kp):
    k, p = kp
    res, gens = d.GENERATORS[kp]
    assert d.resolution(k, gens) == res >= 4
    x = d.fractional_design(k, gens)
    assert x.shape == (2 ** (k - p), k)
    assert len({tuple(r) for r in x}) == len(x)  # no run twice
    # resolution >= IV: every main-effect column is orthogonal to every other main effect and to every
    # two-factor interaction column
    for a in range(k):
        for b in range(k):
            if b != a:
                assert int(x[:, a] @ x[:, b]) == 0
        for b, c in itertools.combinations(range(k), 2):
            assert int(x[:, a] @ (x[:, b] * x[:, c])) == 0


# The defining relations as printed (Montgomery Table 8.14 / Example 8.4 / Table 8.13).
REFERENCE = {
    (4, 1): ["ABCD"],
    (5, 1): ["ABCDE"],
    (6, 2): ["ABCE", "ADEF", "BCDF"],
    (7, 3): ["ABCE", "ABFG", "ACDG", "ADEF", "BCDF", "BDEG", "CEFG"],
}


@pytest.mark.parametrize("kp", sorted(REFERENCE))
def test_defining_relation_matches_the_reference(kp):
    k, _ = kp
    words = d.defining_relation(k, d.GENERATORS[kp][1])
    assert sorted(words) == sorted(REFERENCE[kp])


def test_alias_chains_of_the_two_to_the_six_minus_two():
    # Montgomery Example 8.4 (2^(6-2)_IV, E = ABC, F = BCD): the two-factor interactions' alias chains
    chains = d.alias_pairs(6, ("ABC", "BCD"))
    expected = {"AB": ["CE"], "AC": ["BE"], "AD": ["EF"], "AE": ["BC", "DF"], "AF": ["DE"], "BD": ["CF"],
                "BF": ["CD"]}
    for ab, chain in expected.items():
        assert chains[ab] == chain
    # the 2^(8-4)_IV: 14 words of length 4 and the full word
    words = d.defining_relation(8, d.GENERATORS[(8, 4)][1])
    assert sorted(len(w) for w in words) == [4] * 14 + [8]


def test_full_design_count_and_choice():
    assert d.full_design(3).shape == (8, 3)
    assert len({tuple(r) for r in d.full_design(5)}) == 32
    assert d.choose(6)[:2] == (2, 4)  # the smallest resolution-IV fraction of 6 factors: 16 runs
    assert d.choose(6, runs=32)[:2] == (1, 6)
    with pytest.raises(ValueError):
        d.choose(3)


def _response(levels, true, intercept=2.0):
    return intercept + sum(0.5 * v * np.prod([levels[:, d.LETTERS.index(c)] for c in t], axis=0)
                           for t, v in true.items())


TRUE = {"A": 1.0, "C": -0.6, "F": 0.3, "AB": 0.5}  # in the 2^(6-2): AB is aliased with CE only


def test_effects_recovered_exactly_without_noise():
    k, gens = 6, d.GENERATORS[(6, 2)][1]
    x = d.fractional_design(k, gens)
    rows = {r["letters"]: r for r in d.effects(x, _response(x, TRUE), k, gens)}
    for t in d.model_terms(k, gens):
        assert rows[t]["effect"] == pytest.approx(TRUE.get(t, 0.0), abs=1e-12)
    assert rows["AB"]["aliases"].split(",")[0] == "CE"
    assert rows["A"]["term"] == "A"


def test_effect_intervals_cover_at_their_level():
    """Over 200 synthetic studies (4 seed replicates of each run, noise 0.3), each effect's 95 % interval
    covers the true effect in 95 % of them (binomial 99.9 % band: 0.90-0.99)."""
    k, gens = 6, d.GENERATORS[(6, 2)][1]
    levels = np.repeat(d.fractional_design(k, gens), 4, axis=0)
    rng = np.random.default_rng(11)
    terms = d.model_terms(k, gens)
    hits = np.zeros(len(terms))
    n = 200
    for _ in range(n):
        y = _response(levels, TRUE) + rng.normal(0.0, 0.3, len(levels))
        for i, r in enumerate(d.effects(levels, y, k, gens, names=["p", "q", "r", "s", "t", "u"])):
            hits[i] += r["ci_low"] <= TRUE.get(r["letters"], 0.0) <= r["ci_high"]
    cover = hits / n
    assert np.all((cover > 0.90) & (cover < 0.995)), dict(zip(terms, cover))
