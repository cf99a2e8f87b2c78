"""The estimators' own sensor model: the ``[estimator_sensors]`` table.

The world's sensors (``[perception]``, couplers.sensing.perception) are what the simulator draws from;
an estimator knows only what a datasheet or an integrator would: the field of view and range, the
mounting, a detection profile, a false-alarm rate and the noise. With ``[estimator_sensors]`` the
estimators take these values from this table and never from ``[perception]`` (DESIGN.md "Two models,
never one"); without it they keep taking them from ``[perception]`` as before.

* :meth:`EstimatorSensors.detection_model`: the :class:`coloc.core.detection.DetectionModel` of
  ``lc.sensor_fov`` (ICP-DA-LC, ICP-DA-PF);
* :meth:`EstimatorSensors.clutter_intensity`: ``lc.clutter_intensity`` when the config does not give it,
  the sum of the sensors' ``clutter_per_scan`` over the area of the union of their fields of view
  (false alarms uniform over what the sensors cover), per m^2 and scan;
* ``lc.sensing_range_m`` when not given: the sensors' largest reach.
The noise values (sigma_p_m, sigma_growth, sigma_v_mps) are the datasheet's; the estimators still read
each row's covariance from the frame (``v2f_R``), so they are recorded, not yet used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import shapely

from coloc.core.detection import DetectionModel
from couplers.errors import InputError
from couplers.sensing.perception import SensorSpec


@dataclass(frozen=True)
class EstimatorSensors:
    """The ``[estimator_sensors]`` table: ``[[estimator_sensors.sensors]]`` with the keys of a
    ``[[perception.sensors]]`` table (couplers.sensing.perception.SensorSpec), datasheet values."""

    sensors: tuple[SensorSpec, ...]

    def __post_init__(self):
        if not isinstance(self.sensors, tuple) or not self.sensors:
            raise InputError(None, "sensors", "at least one sensor is needed")
        names = [s.name for s in self.sensors]
        if len(set(names)) != len(names):
            raise InputError(None, "sensors", f"sensor names must be unique, got {names}")

    def detection_model(self, heading_min_speed: float, visibility: float = 1.0) -> DetectionModel:
        return DetectionModel(*(tuple(float(getattr(s, k)) for s in self.sensors) for k in
                                ("fov_deg", "range_m", "yaw_deg", "mount_x_m", "pd_near", "pd_far")),
                              heading_min_speed=heading_min_speed, visibility=visibility)

    @property
    def max_reach_m(self) -> float:
        return max(s.range_m + abs(s.mount_x_m) for s in self.sensors)

    @cached_property
    def coverage_area_m2(self) -> float:
        """Area of the union of the fields of view (sectors drawn with 0.25 deg chords)."""
        return float(shapely.union_all([_sector(s) for s in self.sensors]).area)

    def clutter_intensity(self) -> float:
        return sum(s.clutter_per_scan for s in self.sensors) / self.coverage_area_m2


def _sector(s: SensorSpec):
    """The field of view of ``s`` in the vehicle frame (the reference point, [scenario] reference_point, at the
    origin, heading +x)."""
    n = max(2, int(math.ceil(s.fov_deg / 0.25)))
    ang = np.radians(s.yaw_deg + np.linspace(-s.fov_deg / 2.0, s.fov_deg / 2.0, n + 1))
    arc = np.stack([s.mount_x_m + s.range_m * np.cos(ang), s.range_m * np.sin(ang)], axis=1)
    if s.fov_deg >= 360.0:
        return shapely.Polygon(arc[:-1])
    return shapely.Polygon(np.vstack([[s.mount_x_m, 0.0], arc]))
