"""The occlusion share of a net's own traffic, for ``[lc] visibility`` of its realistic configs.

``[lc] visibility`` is the share of in-view tracks the estimator expects not to be hidden
(coloc/core/detection.py). The arterial presets set it from the coupler's occlusion over their hour
(experiments/arterial_tlr_realistic.toml: 42 % of the in-view pairs occluded in TLR -> 0.6, 13 % in VSR
-> 0.85; docs/validation/realistic_sensing.md). :func:`measure_occlusion` measures the same count on
another net folder: the realistic preset's ``[perception]`` (sensors, occlusion by vehicles, and by the
folder's buildings when it has them) on the folder's own demand, from its begin, for a short window; no
estimator runs, and the other sensing tables (GNSS error, IMU, V2X) are left out (they do not change
what the perception sees). :func:`visibility_of` turns the share into the key's value the way the
presets did: 1 - share, to the nearest 0.05.

:func:`check_building_occlusion` refuses ``[perception] occlusion_buildings = true`` on a net folder
without buildings (config loading).

Like the clutter intensity, this is a calibration from the simulation (the coupler's truth-side
counts), stated as such in the written config; the estimator itself never reads it at run time.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from couplers.errors import InputError

HERE = Path(__file__).resolve().parent


@dataclass(frozen=True)
class OcclusionMeasure:
    control: str
    seed: int
    begin_s: float
    seconds: float  # simulated
    in_fov: int  # (vehicle, feature) pairs inside at least one field of view, summed over the steps
    occluded: int  # of those, hidden from every sensor (by vehicles, or buildings)
    vehicle_steps: int
    wall_s: float

    @property
    def share(self) -> float | None:
        return self.occluded / self.in_fov if self.in_fov else None


def check_building_occlusion(cfg, data: dict, overrides: dict | None) -> None:
    """``occlusion_buildings = true`` given (here, in a file this extends, or as an override) on a net folder
    without buildings is refused; the default (true) means "when it has them". A saved config is not checked."""
    from couplers.net.folder import has_buildings  # noqa: PLC0415

    key = "perception.occlusion_buildings"
    given = (overrides or {}).get(key, data.get("perception", {}).get("occlusion_buildings"))
    if given is True and "provenance" not in data and cfg.scenario.net_dir and not has_buildings(cfg.net_dir):
        raise InputError(cfg.path, key, f"true, but the net folder {cfg.net_dir} has no buildings (no "
                                        "buildings.geojson): set it false, or add the buildings (docs/your-city.md)")


def visibility_of(share: float) -> float:
    """``[lc] visibility`` from the occluded share, as the arterial presets: 1 - share, to the nearest 0.05
    (0.42 -> 0.6, 0.13 -> 0.85), at least 0.05."""
    return max(0.05, round(20.0 * (1.0 - share)) / 20.0)


def measure_occlusion(net_dir: Path, control: str, seed: int, seconds: float, track_area: str,
                      buildings: bool) -> OcclusionMeasure:
    """Occluded / in-view pairs over the first ``seconds`` of ``net_dir``'s demand (from its begin) under
    ``control``, with experiments/arterial_<control>_realistic.toml's ``[perception]`` (``buildings``:
    whether the folder has buildings to occlude)."""
    from coloc.methods.registry import GNSS  # noqa: PLC0415
    from couplers.sumo_coupler import SumoCoupler  # noqa: PLC0415
    from experiments.config import load_config  # noqa: PLC0415
    from experiments.runner import sumo_scenario  # noqa: PLC0415

    preset = HERE / f"arterial_{control}_realistic.toml"
    cfg = load_config(preset, {"scenario.net_dir": str(Path(net_dir).resolve()), "run.seed": seed,
                               "run.duration_s": float(seconds), "run.methods": [GNSS.name],
                               "report.track_areas": [track_area], "perception.occlusion_buildings": buildings,
                               # no GNSS is simulated here (below): the field model, which needs no building
                               # heights, so that the preset's satellite receiver does not refuse the folder
                               "gnss_error.model": "field"})
    keep = {"perception": cfg.sensors.perception, "features": cfg.sensors.features}
    sensors = dataclasses.replace(cfg.sensors, gnss_error=None, v2x=None, inertial=None, **keep)
    scenario = dataclasses.replace(sumo_scenario(cfg), start="fast_start")  # no GNSS fix needed to start
    t0 = time.perf_counter()
    vehicle_steps = 0
    with SumoCoupler(scenario, sensors) as coupler:
        for frame in coupler.frames():
            vehicle_steps += int(frame.vehicle_ids.size)
        totals = dict(coupler.perception_totals)
    return OcclusionMeasure(control=control, seed=seed, begin_s=scenario.begin_s, seconds=float(seconds),
                            in_fov=int(totals.get("in_fov", 0)), occluded=int(totals.get("occluded", 0)),
                            vehicle_steps=vehicle_steps, wall_s=time.perf_counter() - t0)
