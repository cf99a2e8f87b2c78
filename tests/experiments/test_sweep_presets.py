"""Every shipped sweep's runs carry, per control, the values the shipped preset of that control sets."""
from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from experiments.config_toml import config_to_toml
from experiments.sweep.run import expand_runs, load_sweep

ROOT = Path(__file__).resolve().parents[2]
PRESETS = sorted((ROOT / "experiments").glob("*.toml"))
SWEEPS = sorted((ROOT / "experiments" / "sweeps").rglob("*.toml"))


def _flat(table: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flat(v, key + "."))
        else:
            out[key] = v
    return out


def _own(path: Path) -> dict:
    data = tomllib.loads(path.read_text())
    return data


def _chain(path: Path) -> list[Path]:
    """path, then the file it extends, and so on."""
    out = [path.resolve()]
    while "extends" in _own(out[-1]):
        out.append((out[-1].parent / _own(out[-1])["extends"]).resolve())
    return out


def _control_preset(base: Path, control: str) -> Path | None:
    """The shipped preset of ``control`` that overlays the nearest config of ``base``'s chain."""
    for ancestor in _chain(base):
        for p in PRESETS:
            own = _own(p)
            if own.get("scenario", {}).get("control") == control and "extends" in own \
                    and (p.parent / own["extends"]).resolve() == ancestor:
                return p
        if _own(ancestor).get("scenario", {}).get("control") == control:
            return None  # the chain itself is of that control
    return None


def test_the_check_sees_the_vsr_realistic_visibility():
    p = _control_preset(ROOT / "experiments" / "arterial_tlr_realistic.toml", "vsr")
    assert p is not None and p.name == "arterial_vsr_realistic.toml"
    assert _flat(_own(p))["lc.visibility"] == 0.85


@pytest.mark.parametrize("sweep", SWEEPS, ids=[str(s.relative_to(ROOT)) for s in SWEEPS])
def test_control_specific_values_follow_the_shipped_preset(sweep):
    spec = load_sweep(sweep)
    _, runs = expand_runs(spec)
    checked = 0
    for run in runs:
        control = run.cfg.scenario.control
        base = run.variant.base if run.variant is not None and run.variant.base is not None else spec.base
        preset = _control_preset(base, control)
        if preset is None:
            continue
        values = _flat(tomllib.loads(config_to_toml(run.cfg, {})))
        own = {k: v for k, v in _flat(_own(preset)).items() if k not in ("extends", "run.name")}
        for key, want in own.items():
            assert values[key] == want, f"{run.run_id}: {key} = {values[key]!r}, preset {preset.name} sets {want!r}"
            checked += 1
    if spec.grid and any(k == "scenario.control" for k in spec.grid_keys):
        assert checked > 0
