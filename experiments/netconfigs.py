"""Experiment configs for an imported net: overlays of the arterial's shipped configs on another net folder.

Each generated ``<name>_<control>.toml`` says ``extends = ".../arterial_<control>.toml"`` (the paper's
Sec. VI set-up, :mod:`experiments.config_extends`) and sets only the run name, the net folder and the
report's along/cross-track area; ``<name>_<control>_realistic.toml`` does the same over
``arterial_<control>_realistic.toml`` (realistic sensing). Every estimator and sensor parameter is
thereby the shipped arterial's, also after the arterial's configs change, but for the two that depend
on the net (:func:`realistic_values`): ``[lc] visibility``, from the occlusion measured on the net's
own traffic (:mod:`experiments.occlusion`), and ``[perception] occlusion_buildings``, false when the
folder has no buildings (the presets set it true, which is refused on such a folder).

Paths: ``extends`` is relative to the written file when the experiments folder lies inside this checkout
(the two then move together, e.g. the default ``experiments/``), and absolute otherwise (a folder
elsewhere, e.g. a scratch folder, keeps working wherever it is copied to, as long as the checkout stays
where it is). ``net_dir`` is relative to the written file, as in the shipped configs.
"""

from __future__ import annotations

import os
from pathlib import Path

HERE = Path(__file__).resolve().parent
CONTROLS = ("tlr", "vsr")
#: (file-name suffix, shipped config it extends, what it is), per control.
VARIANTS = (("", "arterial_{control}.toml", "paper Sec. VI set-up"),
            ("_realistic", "arterial_{control}_realistic.toml", "realistic sensing, the arterial's calibrations"))


def _quoted(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def config_names(name: str) -> list[str]:
    """The file names ``net_configs`` writes for the net ``name``."""
    return [f"{name}_{control}{suffix}.toml" for suffix, _, _ in VARIANTS for control in CONTROLS]


def _parent_ref(parent: Path, experiments_dir: Path) -> str:
    inside = experiments_dir.resolve().is_relative_to(HERE.parent)
    return Path(os.path.relpath(parent, experiments_dir.resolve())).as_posix() if inside else parent.as_posix()


def realistic_values(net_dir: Path, track_area: str, seed: int, seconds: float, say=None) -> dict[str, str]:
    """Per control, the lines of a realistic overlay that depend on the net folder ``net_dir``: ``[lc]
    visibility`` from the occlusion of its own traffic over ``seconds`` from its begin (seed ``seed``;
    0: not measured, the arterial's kept and said so), ``[perception] occlusion_buildings`` false without
    buildings. ``say``: called with one line per measurement (progress)."""
    from couplers.net.folder import has_buildings  # noqa: PLC0415
    from couplers.net.importer.sumocfg import clock as clock_text  # noqa: PLC0415
    from experiments.occlusion import measure_occlusion, visibility_of  # noqa: PLC0415

    buildings = has_buildings(net_dir)
    gnss = _gnss_world_lines(net_dir, buildings)
    out = {}
    for control in CONTROLS:
        preset = f"experiments/arterial_{control}_realistic.toml"
        if seconds > 0:
            m = measure_occlusion(net_dir, control, seed, seconds, track_area, buildings)
            what = "vehicles and buildings" if buildings else "vehicles (the folder has no buildings)"
            if m.share is None:
                lc = (f"# visibility: not derived: no (vehicle, feature) pair was in view in the {seconds:g} s\n"
                      f"# measured from the begin ({clock_text(m.begin_s)}), seed {seed}: {preset}'s value is kept\n")
            else:
                lc = (f"# visibility: 1 - the share of in-view (vehicle, feature) pairs hidden by other {what},\n"
                      f"# to 0.05 as in {preset}: measured by `coloc net import` on this net's own\n"
                      f"# demand, {control.upper()}, seed {seed}, {seconds:g} s simulated from the begin "
                      f"({clock_text(m.begin_s)}), the preset's\n# [perception] sensors: {m.occluded} of {m.in_fov} "
                      f"pairs occluded ({100 * m.share:.1f} %) over {m.vehicle_steps} vehicle-steps.\n"
                      f"visibility = {visibility_of(m.share)!r}\n")
            if say is not None:
                say(f"occlusion ({control.upper()}, {seconds:g} s from the begin, seed {seed}): " + (
                    "no pair in view, [lc] visibility not derived" if m.share is None else
                    f"{m.occluded} of {m.in_fov} in-view pairs occluded ({100 * m.share:.1f} %) -> [lc] visibility "
                    f"{visibility_of(m.share)!r}") + f" ({m.wall_s:.0f} s)")
        else:
            lc = (f"# visibility: not derived (imported with --occlusion-s 0): {preset}'s value,\n"
                  "# measured on the arterial's hour, is kept\n")
        perception = ("" if buildings else
                      "\n[perception]\n# the net folder has no buildings.geojson: only vehicles occlude (the preset's "
                      "true is refused on it)\nocclusion_buildings = false\n")
        out[control] = "\n[lc]\n" + lc + perception + gnss
    return out


def _gnss_world_lines(net_dir: Path, buildings: bool) -> str:
    """The realistic overlay's [gnss_error] lines: none when every building of the folder has a height (the
    preset's satellite receiver then takes its error from them); the field model over the zones when the folder
    has no buildings or some without a height (the satellite receiver refuses a building without one)."""
    from couplers.net.folder import load_net_folder  # noqa: PLC0415
    from couplers.sensing.gnss_satellites import missing_heights  # noqa: PLC0415

    if not buildings:
        why = "# the net folder has no buildings.geojson: no building to take the receivers' error from"
    else:
        known = load_net_folder(net_dir).buildings
        missing = int(missing_heights(known).size)
        if missing == 0:
            return ""
        why = (f"# {missing} of {len(known)} buildings have no height (OSM height or building:levels): the\n"
               "# preset's satellite receiver needs every one (each satellite's line of sight)")
    return ("\n[gnss_error]\n" + why + "; the field model over the zones instead\n"
            "# (docs/validation/realistic_sensing.md \"GNSS error model and its calibration\")\nmodel = \"field\"\n")


def net_config_text(name: str, control: str, net_dir: Path, experiments_dir: Path, track_area: str,
                    source: str, suffix: str = "", clock: dict | None = None, realistic: dict | None = None) -> str:
    """The text of ``<experiments_dir>/<name>_<control><suffix>.toml`` for the net folder ``net_dir``; ``clock``
    (a .sumocfg's begin_s, end_s, step_length_s): the run keeps the scenario's clock (:func:`_clock_lines`);
    ``realistic``: :func:`realistic_values`, appended to the realistic overlay."""
    _, template, what = next(v for v in VARIANTS if v[0] == suffix)
    parent = HERE / template.format(control=control)
    run_name = f"{name}_{control}{suffix}"
    rel_net = Path(os.path.relpath(Path(net_dir).resolve(), Path(experiments_dir).resolve())).as_posix()
    label = "TLR control" if control == "tlr" else "VSR control (every signal switched off)"
    run_clock, scenario_clock = _clock_lines(clock) if clock is not None else ("", "")
    return (f"# {name}: imported by `coloc net import` from {source}, {label}.\n"
            f"# Parameters as experiments/{parent.name}, which this file extends ({what}).\n"
            f"# `coloc run {Path(experiments_dir).name}/{run_name}.toml --out results/{run_name}`\n"
            f"extends = {_quoted(_parent_ref(parent, Path(experiments_dir)))}\n"
            "\n"
            "[run]\n"
            f"name = {_quoted(run_name)}\n"
            + run_clock +
            "\n"
            "[scenario]\n"
            f"net_dir = {_quoted(rel_net)}   # relative to this file\n"
            + scenario_clock +
            "\n"
            "[report]\n"
            f"track_areas = [{_quoted(track_area)}]      # the area holding the most road length\n"
            + (realistic[control] if realistic is not None and suffix == "_realistic" else ""))


def _clock_lines(clock: dict) -> tuple[str, str]:
    """The [run] and [scenario] lines that keep a .sumocfg's clock: ``duration_s`` one hour from begin, or up
    to the scenario's end when that is sooner; ``begin_s``; ``step_s`` when the scenario sets its step."""
    from couplers.net.importer.sumocfg import clock as clock_text  # noqa: PLC0415

    begin = float(clock.get("begin_s") or 0.0)
    end = clock.get("end_s")
    duration, why = (float(end - begin), "to the scenario's end") if end is not None and end - begin < 3600.0 else \
        (3600.0, "one hour from the scenario's begin")
    run = f"duration_s = {duration!r}          # {why}\n"
    scenario = f"begin_s = {begin!r}                # the scenario's begin ({clock_text(begin)})\n"
    step = clock.get("step_length_s")
    if step is not None:
        scenario += f"step_s = {float(step)!r}                      # the scenario's step-length\n"
    return run, scenario


def net_configs(name: str, net_dir: Path, experiments_dir: Path, track_area: str, source: str,
                clock: dict | None = None, realistic: dict | None = None) -> dict[Path, str]:
    experiments_dir = Path(experiments_dir)
    return {experiments_dir / f"{name}_{c}{suffix}.toml":
            net_config_text(name, c, net_dir, experiments_dir, track_area, source, suffix, clock, realistic)
            for suffix, _, _ in VARIANTS for c in CONTROLS}
