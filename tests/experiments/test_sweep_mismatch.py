"""Mismatch arms: a factor level's ``relative`` sets the estimator's model to a multiple of the simulated
world's value, read from each run's own resolved config (its control's preset)."""
from __future__ import annotations

from pathlib import Path

import pytest

from couplers.errors import InputError
from experiments.sweep.spec import expand_runs, load_sweep, resolved_spec_toml

ROOT = Path(__file__).resolve().parents[2]

SWEEP = f"""
[sweep]
name = "mm"
base = "{ROOT / 'experiments' / 'arterial_tlr_realistic.toml'}"
seeds = [1, 2]
methods = ["gnss", "icp_da_lc"]
[sweep.grid]
"scenario.control" = ["tlr", "vsr"]
[sweep.bases]
"scenario.control" = {{vsr = "{ROOT / 'experiments' / 'arterial_vsr_realistic.toml'}"}}
[sweep.set]
"perception.sensors[*].clutter_per_scan" = 2.0
[sweep.factors]
clutter_model = [
  {{label = "x0.5", relative = {{"estimator_sensors.sensors[*].clutter_per_scan" = {{of = "perception.sensors[*].clutter_per_scan", times = 0.5}}}}}},
  {{label = "matched", preset = true}},
  {{label = "x1.5", relative = {{"estimator_sensors.sensors[*].clutter_per_scan" = {{of = "perception.sensors[*].clutter_per_scan", times = 1.5}}}}}},
]
pd_model = [{{label = "x0.5", set = {{"perception.sensors[*].pd_far" = 0.8}}, relative = {{"estimator_sensors.sensors[*].pd_far" = {{of = "perception.sensors[*].pd_far", times = 0.5}}}}}}]
visibility_model = [{{label = "x0.5", relative = {{"lc.visibility" = {{times = 0.5}}}}}}]
tau_model = [{{label = "x0.5", relative = {{"gnss_model.bias_tau_s" = {{of = "gnss_error.tau_s", times = 0.5}}}}}}]
"""


def _sweep(tmp_path: Path, text: str = SWEEP):
    p = tmp_path / "sweep.toml"
    p.write_text(text)
    return load_sweep(p)


def test_star_keys_in_sweep_set_are_refused_so_the_world_comes_from_levels(tmp_path):
    # [sweep.set] takes plain keys only: the world's values come from the base or a level's own set
    with pytest.raises(InputError) as exc:
        _sweep(tmp_path)
    assert "sweep.set" in str(exc.value)


@pytest.fixture()
def runs(tmp_path):
    text = SWEEP.replace('[sweep.set]\n"perception.sensors[*].clutter_per_scan" = 2.0\n', "")
    spec = _sweep(tmp_path, text)
    base, runs = expand_runs(spec)
    return spec, base, {(r.cfg.scenario.control, r.variant.factor, r.variant.level, r.seed): r.cfg for r in runs}


def test_mismatch_arms_set_the_model_and_leave_the_world(runs):
    _, _, by = runs
    for control in ("tlr", "vsr"):
        preset = by[(control, "preset", "preset", 1)]
        world = [s.clutter_per_scan for s in preset.perception.sensors]
        assert [s.clutter_per_scan for s in preset.estimator_sensors.sensors] == world  # the preset is matched
        for label, times in (("x0.5", 0.5), ("x1.5", 1.5)):
            cfg = by[(control, "clutter_model", label, 2)]
            assert [s.clutter_per_scan for s in cfg.perception.sensors] == world  # the world: unchanged
            assert [s.clutter_per_scan for s in cfg.estimator_sensors.sensors] == [times * w for w in world]
            assert cfg.lc.visibility == preset.lc.visibility
        # the level's own set moves the world first; the model follows it
        cfg = by[(control, "pd_model", "x0.5", 1)]
        assert [s.pd_far for s in cfg.perception.sensors] == [0.8, 0.8]
        assert [s.pd_far for s in cfg.estimator_sensors.sensors] == [0.4, 0.4]
        # relative to the control's own preset: TLR 0.6, VSR 0.85
        cfg = by[(control, "visibility_model", "x0.5", 1)]
        assert cfg.lc.visibility == pytest.approx(0.5 * preset.lc.visibility)
        cfg = by[(control, "tau_model", "x0.5", 1)]
        assert cfg.gnss_model.bias_tau_s == pytest.approx(0.5 * preset.gnss_error.tau_s)
        assert cfg.gnss_error.tau_s == preset.gnss_error.tau_s
    assert by[("tlr", "visibility_model", "x0.5", 1)].lc.visibility == pytest.approx(0.3)
    assert by[("vsr", "visibility_model", "x0.5", 1)].lc.visibility == pytest.approx(0.425)


def test_resolved_spec_keeps_the_arms(runs, tmp_path):
    spec, base, by = runs
    text = resolved_spec_toml(spec, base, len(by))
    assert '"lc.visibility" = {of = "lc.visibility", times = 0.5}' in text
    p = tmp_path / "again" / "sweep.toml"
    p.parent.mkdir()
    p.write_text("\n".join(line for line in text.splitlines()
                           if not line.startswith(("base_config_sha256", "runs =", "#"))) + "\n")
    _, again = expand_runs(load_sweep(p))  # the resolved spec expands to the same runs
    assert {(r.cfg.scenario.control, r.variant.factor, r.variant.level, r.seed): r.cfg.estimator_sensors
            for r in again} == {k: c.estimator_sensors for k, c in by.items()}


@pytest.mark.parametrize("level, field", [
    ('{label = "a", relative = {"estimator_sensors.sensors[*].pd_far" = {of = "gnss_error.tau_s", times = 0.5}}}',
     "relative.estimator_sensors.sensors[*].pd_far.of"),
    ('{label = "a", relative = {"lc.visibility" = {times = -1.0}}}', "relative.lc.visibility.times"),
    ('{label = "a", relative = {"lc.visibility" = {of = "lc.nope", times = 0.5}}}', "relative.lc.visibility.of"),
    ('{label = "a", relative = {"lc.visibility" = {times = 0.5, scale = 2}}}', "relative.lc.visibility.scale"),
    ('{label = "a", preset = true, relative = {"lc.visibility" = {times = 0.5}}}', "sweep.factors.f[0]"),
])
def test_bad_relative_is_refused_naming_the_field(tmp_path, level, field):
    text = SWEEP.split("[sweep.set]")[0] + f"[sweep.factors]\nf = [{level}]\n"
    with pytest.raises(InputError) as exc:
        _sweep(tmp_path, text)
    assert field in str(exc.value)
