"""Experiment configs for an imported net: the arterial's TLR/VSR configs pointed at another net folder.

Every estimator and sensor parameter is the shipped arterial's (the paper's
Sec. VI set-up, ``experiments/arterial_{tlr,vsr}.toml``); only the run name,
the net folder, the control and the report's along/cross-track area change.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

HERE = Path(__file__).resolve().parent
CONTROLS = ("tlr", "vsr")


def _replace_once(text: str, pattern: str, repl: str, template: Path) -> str:
    new, n = re.subn(pattern, repl, text, count=1, flags=re.MULTILINE)
    if n != 1:  # the template changed shape: fail loudly rather than write a wrong config
        raise RuntimeError(f"{template}: pattern {pattern!r} not found")
    return new


def net_config_text(name: str, control: str, net_dir: Path, experiments_dir: Path, track_area: str,
                    source: str, clock: dict | None = None) -> str:
    """The text of ``<experiments_dir>/<name>_<control>.toml`` for the net folder ``net_dir``; ``clock`` (a
    .sumocfg's begin_s, end_s, step_length_s): the run keeps the scenario's clock (:func:`_with_clock`)."""
    template = HERE / f"arterial_{control}.toml"
    text = template.read_text()
    rel = os.path.relpath(Path(net_dir).resolve(), Path(experiments_dir).resolve())
    label = "TLR control" if control == "tlr" else "VSR control (every signal switched off)"
    # header: the first comment block of the template
    body = re.sub(r"\A(#[^\n]*\n)+", "", text)
    header = (f"# {name}: imported by `coloc net import` from {source}, {label}.\n"
              f"# Parameters as experiments/arterial_{control}.toml (paper Sec. VI set-up).\n"
              f"# `coloc run {Path(experiments_dir).name}/{name}_{control}.toml --out results/{name}_{control}`\n")
    body = _replace_once(body, r'^name = "[^"]*"', f'name = "{name}_{control}"', template)
    body = _replace_once(body, r'^net_dir = "[^"]*"', f'net_dir = "{Path(rel).as_posix()}"', template)
    body = _replace_once(body, r'^track_areas = \[[^\]]*\][^\n]*',
                         f'track_areas = ["{track_area}"]      # the area holding the most road length', template)
    if clock is not None:
        body = _with_clock(body, clock, template)
    return header + body


def _with_clock(body: str, clock: dict, template: Path) -> str:
    """[scenario] begin_s (and step_s, when the scenario sets its step) from the scenario's configuration;
    [run] duration_s one hour from begin, or up to the scenario's end when that is sooner."""
    from couplers.netimport.sumocfg import clock as clock_text  # noqa: PLC0415

    begin = float(clock.get("begin_s") or 0.0)
    step = clock.get("step_length_s")
    line = f"step_s = {float(step)!r}" if step is not None else None
    body = _replace_once(body, r'^(step_s = [^\n]*)',
                         (line + "                      # the scenario's step-length" if line else r"\1")
                         + f"\nbegin_s = {begin!r}                # the scenario's begin ({clock_text(begin)})",
                         template)
    end = clock.get("end_s")
    duration, why = (float(end - begin), "to the scenario's end") if end is not None and end - begin < 3600.0 else \
        (3600.0, "one hour from the scenario's begin")
    return _replace_once(body, r'^duration_s = [^\n]*', f"duration_s = {duration!r}          # {why}", template)


def net_configs(name: str, net_dir: Path, experiments_dir: Path, track_area: str, source: str,
                clock: dict | None = None) -> dict[Path, str]:
    experiments_dir = Path(experiments_dir)
    return {experiments_dir / f"{name}_{c}.toml": net_config_text(name, c, net_dir, experiments_dir, track_area, source,
                                                                  clock)
            for c in CONTROLS}
