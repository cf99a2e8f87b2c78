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


# --------------------------------------------------------------------------- sweeps with a design

from pathlib import Path  # noqa: E402

import pandas as pd  # noqa: E402

from couplers.errors import InputError  # noqa: E402
from experiments.sweep.effects import effects_table  # noqa: E402
from experiments.sweep.spec import expand_runs, load_sweep  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
FACTORS = {
    "clutter": '[{label = "1", preset = true}, {label = "3", set = {"perception.sensors[*].clutter_per_scan" = 3.0}}]',
    "tau": '[{label = "0", set = {"gnss_error.tau_s" = 0.0}}, {label = "30", preset = true}]',
    "eta": '[{label = "0.5", preset = true}, {label = "1", set = {"lc.eta_threshold" = 1.0}}]',
    "vis": '[{label = "matched", preset = true}, {label = "x0.5", relative = {"lc.visibility" = {times = 0.5}}}]',
    "pd": '[{label = "a", preset = true}, {label = "b", set = {"perception.sensors[*].pd_far" = 0.5}}, '
          '{label = "c", set = {"perception.sensors[*].pd_far" = 0.6}}]',
}


def _design_sweep(tmp_path: Path, design: str, names: list[str]):
    text = (f'[sweep]\nname = "d"\nbase = "{ROOT / "experiments" / "arterial_tlr_realistic.toml"}"\n'
            f'seeds = [1, 2]\nmethods = ["gnss"]\ndesign = "{design}"\n[sweep.grid]\n'
            '"scenario.control" = ["tlr", "vsr"]\n[sweep.factors]\n'
            + "".join(f"{n} = {FACTORS[n]}\n" for n in names))
    p = tmp_path / "sweep.toml"
    p.write_text(text)
    return load_sweep(p)


def test_fractional_sweep_runs_the_half_fraction(tmp_path):
    spec = _design_sweep(tmp_path, "fractional", ["clutter", "tau", "eta", "vis"])
    assert spec.generators == ("ABC",)
    _, runs = expand_runs(spec)
    assert len(runs) == 2 * 8 * 2  # controls x 2^(4-1) points x seeds
    for r in runs:
        c = r.cfg
        coded = [1 if c.perception.sensors[0].clutter_per_scan == 3.0 else -1, 1 if c.gnss_error.tau_s == 30.0 else -1,
                 1 if c.lc.eta_threshold == 1.0 else -1]
        vis = 1 if c.lc.visibility == pytest.approx(0.3) else -1  # no [sweep.bases]: the TLR preset's 0.6 x 0.5
        assert vis == coded[0] * coded[1] * coded[2]  # D = ABC
        assert r.run_id.startswith(f"control={c.scenario.control},clutter=")


def test_full_design_counts_every_combination(tmp_path):
    spec = _design_sweep(tmp_path, "full", ["clutter", "tau", "pd"])
    _, runs = expand_runs(spec)
    assert len(runs) == 2 * (2 * 2 * 3) * 2
    assert len({r.run_id for r in runs}) == len(runs)


@pytest.mark.parametrize("design, names, field, needle", [
    ("fractional", ["clutter", "tau", "eta"], "sweep.design", "no tabulated fraction"),
    ("fractional", ["clutter", "tau", "eta", "pd"], "sweep.factors.pd", "two levels"),
    ("full", ["clutter"], "sweep.design", "at least 2 factors"),
    ("halton", ["clutter", "tau"], "sweep.design", "unknown design"),
])
def test_bad_designs_are_refused(tmp_path, design, names, field, needle):
    with pytest.raises(InputError) as exc:
        _design_sweep(tmp_path, design, names)
    assert field in str(exc.value) and needle in str(exc.value)


def test_effects_table_recovers_known_effects_per_grid_value(tmp_path):
    spec = _design_sweep(tmp_path, "fractional", ["clutter", "tau", "eta", "vis"])
    x = fractional = d.fractional_design(4, spec.generators)
    rows = []
    rng = np.random.default_rng(3)
    for control, shift in (("tlr", 0.0), ("vsr", 0.4)):
        for seed in range(1, 6):
            for row in fractional:
                y = 1.0 + shift + 0.5 * (0.8 * row[0] + 0.2 * row[0] * row[1]) + rng.normal(0, 0.01)
                rows.append({"scenario.control": control, "method": "gnss", "seed": seed, "rmse_pos_m": y,
                             **{f.name: f.levels[int(v > 0)].label for f, v in zip(spec.factors, row)}})
    eff = effects_table(spec, pd.DataFrame(rows))
    assert x.shape == (8, 4)
    for control in ("tlr", "vsr"):
        e = eff[eff["scenario.control"] == control].set_index("letters")
        assert e.loc["A", "effect"] == pytest.approx(0.8, abs=0.02)
        assert e.loc["AB", "effect"] == pytest.approx(0.2, abs=0.02)
        assert e.loc["AB", "ci_low"] < 0.2 < e.loc["AB", "ci_high"]
        assert e.loc["AB", "aliases"].startswith("CD")  # AB = CD in the 2^(4-1), D = ABC
        assert e.loc["A", "term"] == "clutter" and e.loc["AB", "term"] == "clutter x tau"


def test_design_sweep_report_shows_the_effects_table_and_figure(tmp_path):
    """The sweep report of a fractional design gains the effects section (every term's effect, interval and
    aliases as in effects.parquet, and effects.png); without effects.parquet the page is the same as before,
    byte for byte, less that section."""
    import io
    import re

    from experiments.runner import write_parquet
    from experiments.sweep.effects import effects_figure
    from experiments.sweep.report import write_sweep_report

    out = tmp_path / "sw"
    out.mkdir()
    spec = _design_sweep(out, "fractional", ["clutter", "tau", "eta", "vis"])
    curves = pd.DataFrame([{"curve": "overall", "scenario.control": c, "factor": "design", "level": "all",
                            "method": "gnss", "x": 0.0, "n_runs": 16, "n_samples": 100, "rmse_pos_m": 3.0,
                            "rmse_vel_mps": 0.5, "correct_pct": np.nan, "wrong_pct": np.nan,
                            "discarded_pct": np.nan} for c in ("tlr", "vsr")])
    write_parquet(curves, out / "curves.parquet")
    plain = write_sweep_report(out).read_text(encoding="utf-8")
    assert "Main effects" not in plain and "effects.png" not in plain

    rng = np.random.default_rng(5)
    rows = []
    for control in ("tlr", "vsr"):
        for seed in (1, 2):
            for row in d.fractional_design(4, spec.generators):
                rows.append({"scenario.control": control, "method": "gnss", "seed": seed,
                             "rmse_pos_m": 2.0 + 0.4 * row[0] + 0.1 * row[0] * row[1] + rng.normal(0, 0.05),
                             **{f.name: f.levels[int(v > 0)].label for f, v in zip(spec.factors, row)}})
    eff = effects_table(spec, pd.DataFrame(rows))
    assert len(eff) == 2 * 7  # per control: 4 main effects, 3 alias-free-of-mains two-factor chains
    write_parquet(eff, out / "effects.parquet")
    (out / "effects.png").write_bytes(effects_figure(eff))
    page = write_sweep_report(out).read_text(encoding="utf-8")
    assert '<img src="effects.png"' in page
    sec = page[page.index("<h2>Main effects"):page.index("<h2>Figures</h2>")]
    cells = [[re.sub(r"<[^>]+>", "", c) for c in re.findall(r"<td[^>]*>(.*?)</td>", tr)]
             for tr in re.findall(r"<tr>(.*?)</tr>", sec[sec.index("<tbody>"):])]
    assert len(cells) == len(eff)
    for cell, (_, r) in zip(cells, eff.iterrows()):
        assert cell[0] == r["scenario.control"] and cell[2] == r["term"]
        assert cell[3] == (f"{r['low']} → {r['high']}" if len(r["letters"]) == 1 else "differ → agree")
        assert cell[4] == f"{r['effect']:+.3f}"
        assert cell[5] == f"[{r['ci_low']:+.3f}, {r['ci_high']:+.3f}]"
        assert cell[6] == "–" or cell[6].split(" (")[0] == r["aliases"].split(",")[0]
        assert cell[7] == str(int(r["n_runs"]))
    a = next(c for c in cells if c[0] == "tlr" and c[2] == "clutter")
    assert float(a[4]) == pytest.approx(0.8, abs=0.1)  # the known main effect, 2 x 0.4
    ab = next(c for c in cells if c[0] == "tlr" and c[2] == "clutter x tau")
    assert ab[6] == "CD (eta x vis)"  # AB = CD in the 2^(4-1), D = ABC
    # the effects section and its figure are all that differ from the report without effects
    fig = re.search(r'<figure id="effects">.*?</figure>\n?', page).group(0)
    assert page.replace(sec, "").replace(fig, "") == plain
