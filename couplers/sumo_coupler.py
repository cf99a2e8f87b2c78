"""The SUMO coupler: a libsumo run turned into one frame per step."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, replace

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from coloc.core.frame import Frame
from coloc.core.vehicles import match_ids
from couplers.traffic import sumo
from couplers.errors import InputError
from couplers.sensing.gnss_error import gnss_error_process
from couplers.sensing.inertial import InertialProcess
from couplers.sensing.infra import InfraSetup, InfraSynth
from couplers.net.folder import NetFolder
from couplers.sensing.pedestrians import FeatureRegistry, person_states
from couplers.sensing.occlusion import _footprints, vehicle_footprints
from couplers.sensing.perception import Detections, PerceptionNoise, perceive, sensor_boresights
from couplers.sensing import road_users as ru
from couplers.sensing.sensor_frame import SensorFrameRows
from couplers.sensing.sensors import SensorNoise, SensorParams, features_in_range, points_in_range, synthesize_frame
from couplers.traffic.sumo import SumoOptions, SumoTraffic, VehicleStates
from couplers.sensing.v2x import V2xChannel
from couplers.net.zones import RegionIndex, gnss_sigma_for_zone


@dataclass(frozen=True)
class SumoScenario:
    net: NetFolder
    control: str  # a key of the net folder's [controls], e.g. "tlr" or "vsr"
    seed: int
    step_length: float = 0.75
    duration_s: float = 3600.0
    ballistic: bool = True
    lanechange_duration: float = 3.0
    begin_s: float = 0.0  # the scenario's clock: the run simulates [begin_s, begin_s + duration_s]
    # The prior of an entering vehicle: "fast_start" (N(truth, 2 m), the paper's) or "gnss_fix" (its
    # receiver's fix of that step; couplers.sensing.sensors.synthesize_frame).
    start: str = "fast_start"
    # Seconds after begin_s that SUMO simulates alone before the first frame (a traffic-only warm-up,
    # [analysis] warmup_start = "traffic"): sensing, its random streams and the estimators start then.
    traffic_only_s: float = 0.0
    # The point of a vehicle the world reports (couplers.traffic.reference_point.REFERENCE_POINTS): "front_bumper"
    # (SUMO's position) or "centre"; sensor mounts ([perception] mount_x_m) are measured from it.
    reference_point: str = "front_bumper"

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
            end=self.begin_s + self.duration_s,
            tls_off=self.net.tls_off[self.control],
            ballistic=self.ballistic,
            lanechange_duration=self.lanechange_duration,
            extra_routes=(*self.net.more_routes, *((self.net.persons,) if self.net.persons is not None else ())),
            begin=self.begin_s,
            additional=self.net.additional,
        )


class SumoCoupler:
    """Context manager yielding frames from a libsumo run.

    ``with SumoCoupler(scenario, sensors) as c: for frame in c.frames(): ...``;
    afterwards ``c.traffic.stats.rows`` holds the 5-minute traffic statistics.

    With ``sensors.perception`` (the ``[perception]`` table) the V2F rows come from
    :func:`couplers.sensing.perception.perceive`: ``c.last_detections`` holds the step's
    :class:`couplers.sensing.perception.Detections` (with the sensor and class of every row) and
    ``c.perception_totals`` the counts over the run. With ``sensors.features`` (``[features]
    pedestrians``) every SUMO person is a moving feature (:mod:`couplers.sensing.pedestrians`): the frame
    carries ``v2f_class`` and the truth keeps stable feature rows (``c.registry``). With
    ``sensors.gnss_error`` (``[gnss_error]``) the GNSS position error is
    :class:`couplers.sensing.gnss_error.GnssErrorProcess`'s (``model = "field"``: ``FieldErrorProcess``'s; ``"satellites"``:
    ``couplers.sensing.gnss_satellites.SatelliteErrorProcess``'s, whose reported covariance is the frame's ``gnss_R``). With ``sensors.v2x`` (``[v2x]``) only the
    equipped vehicles (:class:`couplers.sensing.v2x.V2xChannel`) are in the frames, and each frame carries
    the channel (``frame.v2x``); every SUMO vehicle on the road, equipped or not, still occludes the
    perception's sight lines and counts in the traffic statistics. With ``sensors.inertial``
    (``[inertial]``) each frame carries the body-frame IMU of :class:`couplers.sensing.inertial.InertialProcess`
    (``frame.imu``) and ``frame.accel`` is NaN (the net-frame input would carry the true heading);
    the IMU draws from streams of its own, so every other measurement is unchanged.
    """

    def __init__(self, scenario: SumoScenario, sensors: SensorParams, infra: InfraSetup | None = None):
        self.scenario = scenario
        self.sensors = sensors
        self.noise = SensorNoise(scenario.seed)
        # Infrastructure mode (RSUs, radars, odometry): its own random stream (couplers.sensing.infra).
        self.infra = InfraSynth(infra, scenario.seed) if infra is not None else None
        self.zones = RegionIndex(scenario.net.zones)
        self.areas = RegionIndex(scenario.net.areas)
        feats = scenario.net.features
        self.features_true = np.hstack([feats.xy, np.zeros_like(feats.xy)])  # static: zero velocity
        self.feature_tree = cKDTree(feats.xy) if len(feats.xy) else None
        # [features] pedestrians: SUMO persons as moving features (couplers.sensing.pedestrians).
        self.pedestrians = sensors.features is not None and sensors.features.pedestrians
        if self.pedestrians and scenario.net.persons is None:
            raise InputError(scenario.net.root / "scenario.toml", "files.persons",
                             "[features] pedestrians = true needs a persons file (e.g. sumo_nets/arterial_ped)")
        self.registry = FeatureRegistry(feats.ids, self.features_true) if self.pedestrians else None
        self.traffic = SumoTraffic(scenario.sumo_options(), scenario.reference_point)
        buildings = scenario.net.buildings
        self.perception = sensors.perception
        self.perception_noise = PerceptionNoise(scenario.seed) if self.perception is not None else None
        self.last_detections: Detections | None = None
        # Other road users / persistent clutter / classifier error (couplers.sensing.road_users), opt-in.
        self.road_noise = (ru.RoadUserNoise(scenario.seed) if self.perception is not None and self.perception.extended
                           else None)
        self.persistent_sites: np.ndarray | None = None  # drawn at the first step (SUMO's lanes)
        self._persistent_part: tuple | None = None  # their targets, P_D, footprint, class and kind rows
        self._target_cols: tuple = (None, ())  # (part sizes, the targets' P_D, footprint, class, kind) of the last step
        # [perception] detections = "range_bearing": the rows in each sensor's frame (couplers.sensing.sensor_frame).
        self.sensor_frame = (SensorFrameRows(self.perception, scenario.seed)
                             if self.perception is not None and self.perception.detections == "range_bearing" else None)
        self.perception_totals: dict[str, int] = {}
        self.gnss_error = (gnss_error_process(sensors.gnss_error, scenario.seed, scenario.step_length, buildings,
                                              net_path=scenario.net.net)
                           if sensors.gnss_error is not None else None)
        self.v2x = V2xChannel(sensors.v2x, scenario.seed, buildings) if sensors.v2x is not None else None
        self.inertial = (InertialProcess(sensors.inertial, scenario.seed, scenario.step_length)
                         if sensors.inertial is not None else None)
        self._dim_ids = np.empty(0, dtype=object)
        self._dims = np.empty((0, 2))

    def __enter__(self) -> "SumoCoupler":
        self.traffic.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.traffic.__exit__(*exc)

    @property
    def n_steps(self) -> int:
        return int(round((self.scenario.duration_s - self.scenario.traffic_only_s) / self.scenario.step_length))

    def frames(self) -> Iterator[Frame]:
        dt = self.scenario.step_length
        if self.scenario.traffic_only_s > 0:  # SUMO alone first: no frame, no draw of any sensing stream
            self.traffic.advance(self.scenario.begin_s + self.scenario.traffic_only_s)
        while not self.traffic.done():
            road = self.traffic.step()  # every SUMO vehicle: occluders and traffic statistics
            states = road if self.v2x is None else _subset(road, self.v2x.equipped(road.ids))
            zone, sp, sv = gnss_sigma_for_zone(self.zones, states.xy)
            area = self.areas.names_at(states.xy, outside="outside")
            x_true = np.hstack([states.xy, states.velocity])
            feats_true, tree, present, klass = self.features_true, self.feature_tree, None, None
            if self.pedestrians:  # static features then the persons walking now (registry rows ``present``)
                rows = self.registry.update(person_states(sumo.libsumo.person))
                present = np.concatenate([np.arange(self.registry.k0), rows])
                feats_true, klass = self.registry.states[present], self.registry.klass[present]
                tree = cKDTree(feats_true[:, :2]) if present.size else None
            # Row of each vehicle in the previous step's states: SumoTraffic's (the processes' previous ids are
            # the previous step's road ids) unless the V2X subset changes the rows (then they match ids).
            prev_row = states.prev_row if states is road else None
            detections = (self._perceive(road, states, x_true, feats_true, tree, klass)
                          if self.perception is not None else None)
            # The IMU draws from its own streams: computed before the frame so that the frame is built once.
            imu = (self.inertial.step(states.ids, states.entered, states.heading, states.accel, idx=prev_row)
                   if self.inertial is not None else None)
            # The fields the sensing sets beside synthesize_frame's: with the frame where nothing in between reads
            # them (no pedestrians: their registry rows come first), else in one replace after it.
            upd, truth_upd = {}, {}
            if self.sensor_frame is not None:
                upd = self.sensor_frame.frame_fields(detections, x_true, states.heading, feats_true, states.ids,
                                                     states.entered, float(dt))
            if detections is not None and detections.kind is not None:  # the classifier's classes, the truth's kinds
                upd["v2f_class"] = detections.klass
                truth_upd["v2f_kind"] = detections.kind
            early = not self.pedestrians
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
                features_true=feats_true,
                feature_tree=tree,
                params=self.sensors,
                noise=self.noise,
                zone=zone,
                area=area,
                feature_ids=self.scenario.net.features.ids,
                detections=detections,
                gnss_error=self.gnss_error,
                prev_row=prev_row,
                imu=imu,
                start=self.scenario.start,
                frame_fields=upd if early else None,
                truth_fields=truth_upd if early else None,
            )
            if not early:
                sensor_upd = {k: v for k, v in upd.items() if k != "v2f_class"}
                if sensor_upd:
                    frame = replace(frame, **sensor_upd)
                frame = self._with_registry_rows(frame, present, klass)
                if truth_upd:
                    frame = replace(frame, v2f_class=detections.klass, truth=replace(frame.truth, **truth_upd))
            if self.v2x is not None:
                frame = replace(frame, v2x=self.v2x.frame(states.xy, frame.neighbors))
            if self.infra is not None:
                infra, radar_vehicle = self.infra.step(states.ids, states.entered, states.xy)
                frame = replace(frame, infra=infra, truth=replace(frame.truth, radar_vehicle=radar_vehicle))
            yield frame

    def _vehicle_dims(self, ids: np.ndarray, idx: np.ndarray | None = None) -> np.ndarray:
        """(N, 2) length and width of each vehicle (its vType's), asked of SUMO once per vehicle. ``idx``: the
        row of each vehicle among the ``ids`` of the previous call (-1 if new); None: matched here."""
        if idx is None:
            idx = match_ids(self._dim_ids, ids)
        dims, new = _carried_rows(np.asarray(idx, dtype=np.int64), self._dims)
        veh = sumo.libsumo.vehicle
        for i in new.tolist():  # new vehicles only
            dims[i] = (veh.getLength(ids[i]), veh.getWidth(ids[i]))
        self._dim_ids, self._dims = ids, dims
        return dims

    def _with_registry_rows(self, frame, present: np.ndarray, klass: np.ndarray):
        """Truth in registry rows (stable for the run) and the class label of every V2F row."""
        feat = frame.truth.v2f_feature
        real = feat >= 0
        row = np.full(feat.shape, -1, dtype=np.int64)
        row[real] = present[feat[real]]
        v2f_class = np.zeros(feat.shape, dtype=np.int8)  # CLASS_STATIC for clutter
        v2f_class[real] = klass[feat[real]]
        reg = self.registry
        truth = replace(frame.truth, v2f_feature=row, features_true=reg.states, feature_ids=reg.ids,
                        feature_class=reg.klass)
        return replace(frame, truth=truth, v2f_class=v2f_class)

    def _perceive(self, road: VehicleStates, states: VehicleStates, x_true: np.ndarray,
                  features_true: np.ndarray, feature_tree, feature_class) -> Detections:
        """V2F rows of the frame's vehicles ``states``; every vehicle on the ``road`` occludes
        (pedestrians do not: couplers.sensing.pedestrians)."""
        p = self.perception
        owner, feat = features_in_range(states.xy, feature_tree, p.max_reach_m)
        corners, dims, front = None, None, None
        if p.occlusion_vehicles or p.road_users:
            dims = self._vehicle_dims(road.ids, road.prev_row)
        if p.occlusion_vehicles:  # footprints behind the front bumper (couplers.sensing.occlusion)
            front = _front_bumpers(road)
            corners = (_footprints(front, road.direction, dims[:, 0], dims[:, 1]) if road.direction is not None
                       else vehicle_footprints(front, road.heading, dims[:, 0], dims[:, 1]))
        # the sensors' boresights, the same for the landmarks' and the road users' perception of this step
        boresight = sensor_boresights(p, np.asarray(states.heading, dtype=np.float64), len(states.ids))
        det = perceive(
            x_true=x_true, heading=states.heading, features_true=features_true,
            pair_owner=owner, pair_feature=feat, params=p, noise=self.perception_noise,
            occluder_corners=corners,
            observer_occluder=np.arange(len(states.ids)) if states is road else match_ids(road.ids, states.ids),
            buildings=self.scenario.net.buildings, feature_class=feature_class, direction=states.direction,
            boresight=boresight,
        )
        for key, val in det.stats.items():
            self.perception_totals[key] = self.perception_totals.get(key, 0) + val
        if p.extended:
            det = self._with_road_users(det, road, states, x_true, corners, dims, feature_class, front, boresight)
        self.last_detections = det
        return det

    def _road_lanes(self) -> list:
        """(shape, width) of the rightmost lane open to cars of every non-internal edge, by edge id."""
        edge, lane = sumo.libsumo.edge, sumo.libsumo.lane
        out = []
        for e in sorted(edge.getIDList()):
            if e.startswith(":"):
                continue
            for i in range(edge.getLaneNumber(e)):
                lid = f"{e}_{i}"
                allowed = lane.getAllowed(lid)
                if allowed and "passenger" not in allowed:
                    continue
                out.append((np.array(lane.getShape(lid), dtype=float), float(lane.getWidth(lid))))
                break
        return out

    def _with_road_users(self, det: Detections, road: VehicleStates, states: VehicleStates, x_true: np.ndarray,
                         corners, dims, feature_class, front=None, boresight=None) -> Detections:
        """The perception's rows plus other road users and persistent clutter (couplers.sensing.road_users).
        ``front``: the road's front bumpers when the caller has them; ``boresight``: the sensors' boresights of
        the frame's vehicles (couplers.sensing.perception.sensor_boresights) when the caller has them."""
        p = self.perception
        kinds = ru.row_kinds(det.feature, feature_class)  # the perception's rows' kinds (merged_rows sets them)
        parts = []  # (targets (M, 4), what they are: "vehicle" | "person" | "persistent")
        if p.road_users:
            direction = road.direction if road.direction is not None else ru_unit(road.heading)
            front = _front_bumpers(road) if front is None else front
            # the body's middle, whatever road.xy is, and its velocity
            parts.append((ru.body_centre_states(front, dims, direction, road.velocity), "vehicle"))
            if not self.pedestrians and self.scenario.net.persons is not None:
                ps = person_states(sumo.libsumo.person)
                parts.append((np.hstack([ps.xy, ps.velocity]), "person"))
        if p.persistent_clutter_per_km > 0:
            if self.persistent_sites is None:
                self.persistent_sites = ru.persistent_clutter_sites(self._road_lanes(), p.persistent_clutter_per_km,
                                                                    self.road_noise.sites)
                s = self.persistent_sites.shape[0]  # the same part every step
                self._persistent_part = (np.hstack([self.persistent_sites, np.zeros((s, 2))]), "persistent")
            parts.append(self._persistent_part)
        extra = []
        if parts:
            targets = np.concatenate([c[0] for c in parts])
            key = tuple((c[0].shape[0], c[1]) for c in parts)
            if self._target_cols[0] != key:  # the same columns for every step with these parts and sizes
                self._target_cols = (key, self._target_columns(key))
            pd, occ, klass, kind = self._target_cols[1]
            owner, tgt = points_in_range(states.xy, targets[:, :2], p.max_reach_m)
            if states is road:  # observer i is footprint i (the vehicle part first): a vehicle never sees itself
                if p.road_users:
                    owner, tgt = ru.other_pairs(owner, tgt)
                observer = np.arange(len(states.ids))
            else:
                observer = match_ids(road.ids, states.ids)
                keep = (occ[tgt] < 0) | (occ[tgt] != observer[owner])
                owner, tgt = owner[keep], tgt[keep]
            direction = states.direction if states.direction is not None else ru_unit(states.heading)
            r_owner, r_tgt, r_sensor, z, sp, sv = ru.perceive_targets(
                x_true=x_true, direction=direction, heading=states.heading, targets=targets, target_pd=pd,
                target_occluder=occ, pair_owner=owner, pair_target=tgt, params=p,
                noise=self.road_noise, occluder_corners=corners, observer_occluder=observer,
                buildings=self.scenario.net.buildings, boresight=boresight)
            extra.append((r_owner, z, sp, sv, r_sensor, klass[r_tgt], kind[r_tgt]))
        return ru.merged_rows(det, extra, self.road_noise, p.class_error, kind=kinds)

    def _target_columns(self, key: tuple) -> tuple:
        """(P_D (-1: the sensor's), footprint row (-1: none), class, kind) of the targets of parts ``key`` ((size,
        what) each, in order): :func:`couplers.sensing.road_users.target_columns`."""
        return ru.target_columns(key, self.perception.persistent_clutter_pd)


def _front_bumpers(states: VehicleStates) -> np.ndarray:
    """(N, 2) front bumper centres of ``states`` (their ``xy`` itself unless the reference point is another)."""
    if states.front_offset is None:
        return states.xy
    direction = states.direction if states.direction is not None else ru_unit(states.heading)
    return states.xy + states.front_offset[:, None] * direction


def ru_unit(heading: np.ndarray) -> np.ndarray:
    """(N, 2) unit vectors of the headings."""
    return np.stack([np.cos(heading), np.sin(heading)], axis=1).reshape(-1, 2)


@njit(cache=True)
def _carried_rows(idx, prev):
    """prev[idx[i]] for the rows with idx[i] >= 0 (the others left unset), and those others' rows."""
    out = np.empty((idx.size, prev.shape[1]))
    new = np.empty(idx.size, dtype=np.int64)
    m = 0
    for i in range(idx.size):
        if idx[i] >= 0:
            out[i] = prev[idx[i]]
        else:
            new[m] = i
            m += 1
    return out, new[:m]


def _subset(states: VehicleStates, keep: np.ndarray) -> VehicleStates:
    """The vehicles of ``states`` where ``keep`` (rows in the same order)."""
    if keep.all():
        return states
    return VehicleStates(t=states.t, ids=states.ids[keep], xy=states.xy[keep], velocity=states.velocity[keep],
                         heading=states.heading[keep], accel=states.accel[keep], entered=states.entered[keep],
                         front_offset=None if states.front_offset is None else states.front_offset[keep])
