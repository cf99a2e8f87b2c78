"""The SUMO coupler: a libsumo run turned into one frame per step."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from coloc.core.frame import Frame
from couplers.errors import InputError
from couplers.infra import InfraSetup, InfraSynth
from couplers.netfolder import NetFolder
from couplers.sensors import SensorNoise, SensorParams, synthesize_frame
from couplers.sumo_traffic import SumoOptions, SumoTraffic
from couplers.zones import RegionIndex, gnss_sigma_for_zone


@dataclass(frozen=True)
class SumoScenario:
    net: NetFolder
    control: str  # a key of the net folder's [controls], e.g. "tlr" or "vsr"
    seed: int
    step_length: float = 0.75
    duration_s: float = 3600.0
    ballistic: bool = True
    lanechange_duration: float = 3.0

    def sumo_options(self) -> SumoOptions:
        if self.control not in self.net.tls_off:
            raise InputError(
                self.net.root / "scenario.toml", "controls", f"no control named {self.control!r} (have {sorted(self.net.tls_off)})"
            )
        return SumoOptions(
            net=self.net.net,
            routes=self.net.routes,
            seed=self.seed,
            step_length=self.step_length,
            end=self.duration_s,
            tls_off=self.net.tls_off[self.control],
            ballistic=self.ballistic,
            lanechange_duration=self.lanechange_duration,
        )


class SumoCoupler:
    """Context manager yielding frames from a libsumo run.

    ``with SumoCoupler(scenario, sensors) as c: for frame in c.frames(): ...``;
    afterwards ``c.traffic.stats.rows`` holds the 5-minute traffic statistics.
    """

    def __init__(self, scenario: SumoScenario, sensors: SensorParams, infra: InfraSetup | None = None):
        self.scenario = scenario
        self.sensors = sensors
        self.noise = SensorNoise(scenario.seed)
        # Infrastructure mode (RSUs, radars, odometry): its own random stream (couplers.infra).
        self.infra = InfraSynth(infra, scenario.seed) if infra is not None else None
        self.zones = RegionIndex(scenario.net.zones)
        self.areas = RegionIndex(scenario.net.areas)
        feats = scenario.net.features
        self.features_true = np.hstack([feats.xy, np.zeros_like(feats.xy)])  # static: zero velocity
        self.feature_tree = cKDTree(feats.xy) if len(feats.xy) else None
        self.traffic = SumoTraffic(scenario.sumo_options())

    def __enter__(self) -> "SumoCoupler":
        self.traffic.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.traffic.__exit__(*exc)

    @property
    def n_steps(self) -> int:
        return int(round(self.scenario.duration_s / self.scenario.step_length))

    def frames(self) -> Iterator[Frame]:
        dt = self.scenario.step_length
        while not self.traffic.done():
            states = self.traffic.step()
            zone, sp, sv = gnss_sigma_for_zone(self.zones, states.xy)
            area = self.areas.names_at(states.xy, outside="outside")
            x_true = np.hstack([states.xy, states.velocity])
            frame = synthesize_frame(
                t=states.t,
                dt=dt,
                vehicle_ids=states.ids,
                entered=states.entered,
                x_true=x_true,
                accel_true=states.accel,
                heading=states.heading,
                gnss_sigma_p=sp,
                gnss_sigma_v=sv,
                features_true=self.features_true,
                feature_tree=self.feature_tree,
                params=self.sensors,
                noise=self.noise,
                zone=zone,
                area=area,
                feature_ids=self.scenario.net.features.ids,
            )
            if self.infra is not None:
                infra, radar_vehicle = self.infra.step(states.ids, states.entered, states.xy)
                frame = replace(frame, infra=infra, truth=replace(frame.truth, radar_vehicle=radar_vehicle))
            yield frame
