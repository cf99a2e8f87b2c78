"""Experiment configs: TOML, validated on load, saved fully resolved next to results.

Every table maps onto a frozen dataclass; unknown keys and wrong types are
errors naming the file and the dotted field.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path

from coloc.models import MotionParams
from couplers.errors import InputError
from couplers.sensors import SensorParams

KNOWN_METHODS = ("gnss", "icp_known_da")


@dataclass(frozen=True)
class RunSection:
    name: str
    seed: int = 1
    duration_s: float = 3600.0
    methods: tuple[str, ...] = ("gnss",)


@dataclass(frozen=True)
class ScenarioSection:
    kind: str = "sumo"
    net_dir: str = ""  # relative to the config file, resolved to an absolute path on load
    control: str = "tlr"
    step_s: float = 0.75
    ballistic: bool = True


@dataclass(frozen=True)
class IcpSection:
    """Gaussian ICP (BPA-L with consensus), coloc.icp.IcpParams; motion comes from [motion]."""

    consensus_iterations: int = 20
    bpa_max_iterations: int = 10
    stop_pos_m: float = 0.1  # BPA-L stopping rule, Brambilla Sec. V-A
    stop_vel_mps: float = 0.1
    feature_sigma_par: float = 0.01  # m/s per step, model (2) for static features
    feature_drop_after_s: float = 10.0


@dataclass(frozen=True)
class ReportSection:
    track_area: str = "5"  # analysis area of the along/cross-track figure (paper Fig. 18b)
    figures: bool = True


@dataclass(frozen=True)
class Config:
    path: Path
    run: RunSection
    scenario: ScenarioSection = field(default_factory=ScenarioSection)
    sensors: SensorParams = field(default_factory=SensorParams)
    motion: MotionParams = field(default_factory=MotionParams)
    icp: IcpSection = field(default_factory=IcpSection)
    report: ReportSection = field(default_factory=ReportSection)

    @property
    def net_dir(self) -> Path:
        return Path(self.scenario.net_dir)


SECTIONS: dict[str, type] = {
    "run": RunSection,
    "scenario": ScenarioSection,
    "sensors": SensorParams,
    "motion": MotionParams,
    "icp": IcpSection,
    "report": ReportSection,
}


def _check_value(value, annotation, where: str, path: Path):
    """Coerce/validate one TOML value against a dataclass annotation."""
    origin = typing.get_origin(annotation)
    if annotation is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(path, where, f"expected a number, got {value!r}")
        if not math.isfinite(value):
            raise InputError(path, where, "must be finite")
        return float(value)
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(path, where, f"expected an integer, got {value!r}")
        return value
    if annotation is bool:
        if not isinstance(value, bool):
            raise InputError(path, where, f"expected true or false, got {value!r}")
        return value
    if annotation is str:
        if not isinstance(value, str):
            raise InputError(path, where, f"expected a string, got {value!r}")
        return value
    if origin is tuple:
        (inner, _ellipsis) = typing.get_args(annotation)
        if not isinstance(value, list):
            raise InputError(path, where, f"expected a list, got {value!r}")
        return tuple(_check_value(v, inner, f"{where}[{i}]", path) for i, v in enumerate(value))
    if origin in (typing.Union, types.UnionType):
        raise TypeError(f"unsupported annotation {annotation} for {where}")
    raise TypeError(f"unsupported annotation {annotation} for {where}")


def section_from_table(cls: type, table: dict, name: str, path: Path):
    if not isinstance(table, dict):
        raise InputError(path, name, "expected a table")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(table) - set(fields))
    if unknown:
        raise InputError(path, f"{name}.{unknown[0]}", f"unknown key (known: {', '.join(sorted(fields))})")
    kwargs = {}
    for key, f in fields.items():
        if key in table:
            kwargs[key] = _check_value(table[key], hints[key], f"{name}.{key}", path)
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise InputError(path, f"{name}.{key}", "required key missing")
    return cls(**kwargs)


def _validate(cfg: Config) -> None:
    p = cfg.path
    for i, m in enumerate(cfg.run.methods):
        if m not in KNOWN_METHODS:
            raise InputError(p, f"run.methods[{i}]", f"unknown method {m!r} (available: {', '.join(KNOWN_METHODS)})")
    if not cfg.run.methods:
        raise InputError(p, "run.methods", "at least one method is needed")
    if len(set(cfg.run.methods)) != len(cfg.run.methods):
        raise InputError(p, "run.methods", "a method is listed twice")
    if cfg.run.duration_s <= 0:
        raise InputError(p, "run.duration_s", "must be positive")
    if cfg.run.seed < 0:
        raise InputError(p, "run.seed", "must be a non-negative integer")
    if cfg.scenario.kind != "sumo":
        raise InputError(p, "scenario.kind", f"unknown scenario kind {cfg.scenario.kind!r} (available: sumo)")
    if not cfg.scenario.step_s > 0:
        raise InputError(p, "scenario.step_s", "must be positive")
    for name in ("accel_sigma", "v2f_range_m", "v2f_sigma_p", "v2f_sigma_v", "v2v_range_m", "prior_sigma_p", "prior_sigma_v"):
        val = getattr(cfg.sensors, name)
        if val < 0 or (val == 0 and name.startswith(("prior", "v2f_sigma"))):
            raise InputError(p, f"sensors.{name}", "must be positive")
    if cfg.icp.consensus_iterations < 0:
        raise InputError(p, "icp.consensus_iterations", "must be >= 0")
    if cfg.icp.bpa_max_iterations < 1:
        raise InputError(p, "icp.bpa_max_iterations", "must be >= 1")
    for name in ("stop_pos_m", "stop_vel_mps", "feature_sigma_par", "feature_drop_after_s"):
        if not getattr(cfg.icp, name) > 0:
            raise InputError(p, f"icp.{name}", "must be positive")
    for name in ("sigma_along", "sigma_cross"):
        if not getattr(cfg.motion, name) > 0:
            raise InputError(p, f"motion.{name}", "must be positive")
    if cfg.scenario.kind == "sumo":
        if not cfg.scenario.net_dir:
            raise InputError(p, "scenario.net_dir", "required for a SUMO scenario")
        if not (Path(cfg.scenario.net_dir) / "scenario.toml").is_file():
            raise InputError(p, "scenario.net_dir", f"no net folder (scenario.toml) at {cfg.scenario.net_dir}")


def config_from_dict(data: dict, path: Path, overrides: dict | None = None) -> Config:
    # A saved (resolved) config carries its provenance; it is informative, not input.
    data = {k: v for k, v in data.items() if k != "provenance"}
    unknown = sorted(set(data) - set(SECTIONS))
    if unknown:
        raise InputError(path, unknown[0], f"unknown table (known: {', '.join(SECTIONS)})")
    data = {k: dict(v) if isinstance(v, dict) else v for k, v in data.items()}
    for dotted, value in (overrides or {}).items():
        sec, key = dotted.split(".")
        data.setdefault(sec, {})[key] = value
    if "run" not in data:
        raise InputError(path, "run", "required table missing")
    sections = {name: section_from_table(cls, data.get(name, {}), name, path) for name, cls in SECTIONS.items()}
    scen = sections["scenario"]
    if scen.net_dir:
        net_dir = (path.parent / scen.net_dir).resolve()
        sections["scenario"] = dataclasses.replace(scen, net_dir=str(net_dir))
    cfg = Config(path=path.resolve(), **sections)
    _validate(cfg)
    return cfg


def load_config(path: str | Path, overrides: dict | None = None) -> Config:
    """Read and validate a config; ``overrides`` maps "section.key" to a value (command-line options)."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            data = tomllib.load(fh)
    except FileNotFoundError:
        raise InputError(path, None, "config file not found") from None
    except IsADirectoryError:
        raise InputError(path, None, "is a directory, not a config file") from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(path, None, f"not valid TOML ({exc})") from None
    return config_from_dict(data, path, overrides)


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def config_to_toml(cfg: Config, provenance: dict[str, str | int | float]) -> str:
    """The fully resolved config (every default spelled out) plus provenance, as TOML."""
    lines = [f"# Resolved from {cfg.path}", ""]
    for name in SECTIONS:
        lines.append(f"[{name}]")
        for f in dataclasses.fields(getattr(cfg, name)):
            lines.append(f"{f.name} = {_toml_value(getattr(getattr(cfg, name), f.name))}")
        lines.append("")
    lines.append("[provenance]")
    for key, val in provenance.items():
        lines.append(f"{key} = {_toml_value(val)}")
    return "\n".join(lines) + "\n"
