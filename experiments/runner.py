"""One run: frames (SUMO coupler or a controlled scenario) -> estimators -> Parquet files, summary.json, report.

The output folder appears complete or not at all, and replaces only an earlier run's folder
(:mod:`couplers.publish`: the ``--out`` rule and the atomic rename live there).

Frames come from the SUMO coupler (``scenario.kind = "sumo"``) or from
:func:`couplers.scenarios.scenario_frames` (``"single_road"``, ``"crossroad"``;
Brambilla Sec. V), capped at ``run.duration_s``. A controlled scenario has no
traffic statistics: its traffic.parquet has the schema and no rows and
summary["traffic"] is None.

Association scoring (outside the estimators): every method whose StepEstimate
carries ``v2f_assignment`` is scored with
:func:`experiments.scoring.score_association` (track labels over the whole run),
giving association.parquet rows and summary["association"][method]. Feature
errors of such methods compare each track with its label's true feature; for
the known-association bound the track ids are the true feature indices.

Infrastructure mode (config ``[infra]``): the coupler adds ``frame.infra`` (RSUs, radar,
odometry; couplers.sensing.infra); estimates.parquet gains ``covered`` (the vehicle is within V2I
range of an RSU, from the frame, the same for every method) and ``rsu`` (the lowest-index
RSU covering it, "" when none), and summary.json gains ``within_rsu_coverage``: per method
RMSE / p95 / n on the covered vehicle-steps, overall and per area, the method's counters
(topology updates / skips, feature births / drops), and ``rsu_vehicle_steps`` per RSU.
Runs without ``[infra]`` are unchanged, byte for byte.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from coloc.core.frame import Frame, StepEstimate
from coloc.inference.params import IcpParams
from coloc.methods.coop_fusion import CoopFusion
from coloc.methods.icp_da_pf import PfParams
from coloc.methods.registry import METHODS, MethodParams, build_method
from couplers.errors import InputError
from couplers.sensing.infra import InfraSetup, junction_positions
from couplers.net.check import require_usable_net_folder
from couplers.net.folder import load_net_folder
from couplers.net.importer.sumocfg import clock
from couplers.sensing.perception import detection_model
from couplers.publish import staged_folder
from couplers.scenarios import scenario_frames
from couplers.sumo_coupler import SumoCoupler, SumoScenario
from experiments.config import Config
from experiments.config_toml import config_to_toml
from experiments.gnss_world import GnssWorldTally
from experiments.oracle_world import oracle_sensors, oracle_world
from experiments.pipeline import BATCH, estimator_stats, step_batch
from experiments.rowstream import StreamLog, association_rows, concat_steps, estimate_rows, position_nees
from experiments.run_checks import _empty_run, _nothing_to_estimate, check_finite_estimate  # noqa: F401
from experiments.scoring import (
    DETECTION_KINDS,
    label_arrays,
    labelled,
    detection_kinds,
    analysis_summary,
    scored_from,
    traffic_only_s,
    scored_mask,
    association_summary,
    score_association,
    traffic_summary,
)

if TYPE_CHECKING:
    import pandas as pd

    from coloc.methods.infra import InfraMethodParams

# pandas, pyarrow and tqdm are imported where they are used (the tables and Parquet files at the end
# of a run, the progress bar), and the infrastructure methods' module only for an [infra] config, so
# that `coloc run` reaches its first simulation step without them (docs/performance.md, start-up).

PROJECT_ROOT = Path(__file__).resolve().parents[1]
# Told the true association by the runner (the registry's known_association flag): the Gaussian
# bound, and its particle counterpart (ICP-DA-PF with BP-DA skipped).
KNOWN_ASSOCIATION_METHODS = frozenset(m.name for m in METHODS.values() if m.known_association)


@dataclass
class CommTally:
    """Communication of one method over a run (:mod:`coloc.inference.comm`): sums over steps of what
    each vehicle sent, for summary.json's ``comm`` block."""

    vehicle_steps: int = 0
    steps: int = 0
    messages: int = 0
    bytes: int = 0
    max_bytes: int = 0
    rounds: int = 0

    def add(self, comm) -> None:
        self.vehicle_steps += int(comm.messages.size)
        self.steps += 1
        self.messages += int(comm.messages.sum())
        self.bytes += int(comm.bytes.sum())
        self.max_bytes = max(self.max_bytes, int(comm.bytes.max()) if comm.bytes.size else 0)
        self.rounds += int(comm.rounds)

    def summary(self) -> dict:
        per = max(self.vehicle_steps, 1)
        return {"messages_per_vehicle_step": self.messages / per, "bytes_per_vehicle_step": self.bytes / per,
                "max_bytes_vehicle_step": self.max_bytes, "rounds_per_step": self.rounds / max(self.steps, 1),
                "vehicle_steps": self.vehicle_steps}


@dataclass
class V2vTally:
    """The V2V graph over a run, for summary.json's ``v2v`` block: how many neighbours within Rc each
    vehicle had at each step (``frame.neighbors``: the intended graph, equipped vehicles only under
    ``[v2x]``), and under ``[v2x]`` the mean delivery probability of its directed links."""

    degree_counts: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    links: int = 0
    delivery_sum: float = 0.0

    def add(self, frame: Frame) -> None:
        if frame.n_vehicles == 0:
            return
        deg = np.bincount(np.diff(frame.neighbors.indptr))
        if deg.size > self.degree_counts.size:
            deg[: self.degree_counts.size] += self.degree_counts
            self.degree_counts = deg
        else:
            self.degree_counts[: deg.size] += deg
        if frame.v2x is not None:
            self.links += int(frame.v2x.delivery_prob.size)
            self.delivery_sum += float(np.sum(frame.v2x.delivery_prob))

    def summary(self) -> dict:
        n = int(self.degree_counts.sum())
        k = np.arange(self.degree_counts.size)
        out = {"vehicle_steps": n,
               "mean_degree": float((k * self.degree_counts).sum() / n) if n else None,
               "isolated_share": float(self.degree_counts[0] / n) if n else None,
               "degree_counts": [int(c) for c in self.degree_counts]}
        if self.links:
            out["mean_delivery_probability"] = self.delivery_sum / self.links
        return out


def build_estimators(cfg: Config) -> list:
    """Estimator objects for ``cfg.run.methods``, in that order (built by the method registry)."""
    params = method_params(cfg)
    return [build_method(m, params) for m in cfg.run.methods]


def method_params(cfg: Config) -> MethodParams:
    """The registry builders' parameters from ``[motion]``, ``[icp]``, ``[lc]``, ``[pf]`` (with the seed)
    ``[infra]`` (None without it) and ``[gnss_model]`` (None: the white ``gnss`` tracker)."""
    return MethodParams(
        motion=cfg.motion, icp=IcpParams(motion=cfg.motion, **dataclasses.asdict(cfg.icp)), lc=cfg.lc,
        pf=PfParams(seed=cfg.run.seed, **dataclasses.asdict(cfg.pf)),
        infra=infra_method_params(cfg) if cfg.infra is not None else None,
        detection=estimator_detection_model(cfg),
        gnss_model=cfg.gnss_model,
        oracle_world=oracle_world(cfg),
        fusion=CoopFusion.from_config(cfg.fusion, cfg.gnss_model),
    )


def estimator_detection_model(cfg: Config):
    """The estimators' DetectionModel (``lc.sensor_fov``): from ``[estimator_sensors]``, their own table, when
    the config has one, else from the ``[perception]`` sensors (None without either or without sensor_fov)."""
    if not cfg.lc.sensor_fov:
        return None
    if cfg.estimator_sensors is not None:
        return cfg.estimator_sensors.detection_model(cfg.motion.heading_min_speed, cfg.lc.visibility)
    if cfg.perception is not None:
        return detection_model(cfg.perception, cfg.motion.heading_min_speed, cfg.lc.visibility)
    return None


def infra_method_params(cfg: Config) -> InfraMethodParams:
    """Settings of the infrastructure methods from ``[infra]``, ``[motion]``, ``[sensors]`` and the seed."""
    from coloc.methods.infra import InfraMethodParams

    inf = cfg.infra
    return InfraMethodParams(
        motion=cfg.motion, seed=cfg.run.seed, rsu_bp_particles=inf.rsu_bp_particles,
        detection_prob=inf.rsu_bp_detection_prob, v2f_range_m=cfg.sensors.v2f_range_m,
        feature_drop_s=inf.rsu_bp_feature_drop_s, feature_birth_max_std_m=inf.rsu_bp_birth_max_std_m,
        feature_keep_radius_m=inf.rsu_range_m + cfg.sensors.v2f_range_m + 30.0,
        sme_max_vehicles=inf.sme_max_vehicles, fg_window_steps=inf.fg_window_steps,
    )


def infra_setup(cfg: Config, net) -> "InfraSetup | None":
    """RSU positions and sensor parameters of ``[infra]`` (None without it)."""
    if cfg.infra is None:
        return None
    inf = cfg.infra
    xy = junction_positions(net.net, inf.rsu_junctions, cfg.path, "infra.rsu_junctions")
    return InfraSetup(rsu_ids=tuple(inf.rsu_junctions), rsu_xy=xy, range_m=inf.rsu_range_m,
                      radar_sigma_m=inf.radar_sigma_m, pose_offset_sigma_m=inf.radar_pose_offset_sigma_m,
                      odom_sigma_m=inf.odom_sigma_m)


def git_revision() -> str:
    try:
        rev = subprocess.run(
            ["git", "-C", str(PROJECT_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10
        )
        if rev.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            ["git", "-C", str(PROJECT_ROOT), "status", "--porcelain", "--untracked-files=no"],
            capture_output=True, text=True, timeout=10,
        )
        return rev.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@dataclass
class EstimateLog:
    """Per-step rows of one run, kept as arrays and concatenated once at the end: the in-memory
    reference of :class:`experiments.rowstream.StreamLog`, which the runner uses (tests)."""

    truth_parts: list = field(default_factory=list)
    method_parts: dict = field(default_factory=dict)
    feature_parts: list = field(default_factory=list)
    # method -> per step (t, assignment (O,), true feature (O,))
    assoc_parts: dict = field(default_factory=dict)
    # method -> per step, the GNSS zone of each V2F row's vehicle
    assoc_zone_parts: dict = field(default_factory=dict)
    # method -> per step (t, track ids (T,), estimated xy (T, 2), true feature xy (K, 2))
    track_parts: dict = field(default_factory=dict)
    # Infrastructure mode: per step (covered (N,), home RSU id (N,) str, "" when not covered).
    infra_parts: list = field(default_factory=list)
    # V2F rows by what they truly are (couplers.sensing.road_users KIND_NAMES order), summed over the run.
    kind_counts: np.ndarray = field(default_factory=lambda: np.zeros(len(DETECTION_KINDS), dtype=np.int64))

    def add_truth(self, frame: Frame) -> None:
        tr = frame.truth
        self.kind_counts += detection_kinds(tr)
        self.truth_parts.append(
            (np.full(frame.n_vehicles, frame.t), frame.vehicle_ids, tr.x_true, tr.heading, tr.zone, tr.area)
        )
        if frame.infra is not None:
            from coloc.methods.infra import home_rsu

            home = home_rsu(frame.infra.v2i) if frame.n_vehicles else np.empty(0, dtype=np.int64)
            names = np.append(frame.infra.rsu_ids.astype(str), "")[home]
            self.infra_parts.append((home >= 0, names))

    def add(self, method: str, est: StepEstimate) -> None:
        self.method_parts.setdefault(method, []).append(
            (est.mean, est.cov[:, 0, 0], est.cov[:, 1, 1], est.cov[:, 0, 1])
        )

    def position_nees(self, method: str) -> np.ndarray:
        """2-D position NEES e^T P^-1 e of every (vehicle, step) sample of ``method``, in the row order
        of :meth:`table` (2 on average for a consistent estimator)."""
        x_true = np.concatenate([p[2] for p in self.truth_parts])
        mean, vx_, vy_, cxy = (np.concatenate(c) for c in zip(*self.method_parts[method]))
        return position_nees(mean[:, 0] - x_true[:, 0], mean[:, 1] - x_true[:, 1], vx_, vy_, cxy)

    def add_association(self, method: str, frame: Frame, est: StepEstimate) -> None:
        """Keep the V2F pairing of a method that reports one, with the truth, for scoring at the end."""
        rows = association_rows(method, frame, est)
        if rows is None:
            return
        assign, truth, zone = rows
        self.assoc_parts.setdefault(method, []).append((frame.t, assign, truth))
        self.assoc_zone_parts.setdefault(method, []).append(zone)

    def add_features(self, method: str, frame: Frame, est: StepEstimate) -> None:
        """Feature-track estimates; scored against the truth once the track labels are known."""
        if est.feature_mean is None or est.feature_track_ids is None or est.feature_mean.shape[0] == 0:
            return
        ids = np.asarray(est.feature_track_ids, dtype=np.int64)
        self.track_parts.setdefault(method, []).append(
            (frame.t, ids, est.feature_mean[:, :2].copy(), frame.truth.features_true[:, :2].copy())
        )

    def association_scores(self) -> dict[str, tuple[np.ndarray, np.ndarray, dict[int, int]]]:
        """method -> (t (S,), counts (S, 3) [correct, wrong, discarded], track labels)."""
        out = {}
        for method, parts in self.assoc_parts.items():
            counts, labels = score_association([(a, f) for _, a, f in parts])
            out[method] = (np.array([t for t, _, _ in parts], dtype=float), counts, labels)
        return out

    def association_table(self, methods: list[str], scores: dict) -> pd.DataFrame:
        return association_table(methods, scores)

    def feature_table(self, methods: list[str], scores: dict) -> pd.DataFrame:
        """Feature errors: known-association tracks are true feature indices; other tracks are
        compared with their label's true feature (tracks without a label, and ghost tracks labelled
        -1 because clutter formed most of their rows, are not scored)."""
        import pandas as pd

        cols = {"method": "string", "t": "float64", "track": "int64", "feature": "int64", "err_pos": "float64"}
        rows = []
        for m in methods:
            if m not in self.track_parts:
                continue
            if m in KNOWN_ASSOCIATION_METHODS:
                label_of = None
            elif m in scores:
                label_of = label_arrays(scores[m][2])
            else:
                continue  # tracks without any pairing cannot be scored
            for t, ids, xy, truth_xy in self.track_parts[m]:
                if label_of is None:
                    feat = ids
                else:
                    if label_of[0].size == 0:
                        continue
                    has, feat = labelled(ids, *label_of)
                    ids, xy, feat = ids[has], xy[has], feat[has]
                if ids.size == 0:
                    continue
                if truth_xy.shape[0] and feat.max() >= truth_xy.shape[0]:
                    # SUMO pedestrians: a label registered after this step (couplers.sensing.pedestrians)
                    ok = feat < truth_xy.shape[0]
                    ids, xy, feat = ids[ok], xy[ok], feat[ok]
                if not np.isfinite(truth_xy[feat]).all():
                    # SUMO pedestrians: a person that has left (NaN state) has no error to score
                    ok = np.isfinite(truth_xy[feat]).all(axis=1)
                    ids, xy, feat = ids[ok], xy[ok], feat[ok]
                    if ids.size == 0:
                        continue
                err = xy - truth_xy[feat]
                rows.append((m, t, ids, feat, np.hypot(err[:, 0], err[:, 1])))
        if not rows:
            return pd.DataFrame(columns=list(cols)).astype(cols)
        return pd.DataFrame(
            {
                "method": np.concatenate([np.full(ids.size, m, dtype=object) for m, _, ids, _, _ in rows]),
                "t": np.concatenate([np.full(ids.size, t) for _, t, ids, _, _ in rows]),
                "track": np.concatenate([ids for _, _, ids, _, _ in rows]),
                "feature": np.concatenate([f for _, _, _, f, _ in rows]),
                "err_pos": np.concatenate([e for _, _, _, _, e in rows]),
            }
        ).astype(cols)

    def table(self, run_name: str) -> pd.DataFrame:
        import pandas as pd

        if not self.truth_parts:
            cols = {"run": [], "method": [], "t": [], "vehicle": []}
            return pd.DataFrame(cols)
        truth, infra = concat_steps(self.truth_parts, self.infra_parts)
        frames = [estimate_rows(run_name, method, truth, infra, tuple(np.concatenate(c) for c in zip(*parts)))
                  for method, parts in self.method_parts.items()]
        return pd.concat(frames, ignore_index=True)


def association_table(methods: list[str], scores: dict) -> pd.DataFrame:
    """association.parquet: per method and step (method -> (t, counts, labels) of
    :meth:`EstimateLog.association_scores`), the correct / wrong / discarded V2F rows."""
    import pandas as pd

    table = empty_association_table()
    parts = []
    for m in methods:
        if m in scores:
            t, counts, _ = scores[m]
            parts.append(pd.DataFrame({"method": m, "t": t, "correct": counts[:, 0],
                                       "wrong": counts[:, 1], "discarded": counts[:, 2]}))
    if not parts:
        return table
    return pd.concat(parts, ignore_index=True).astype(table.dtypes.to_dict())


def empty_association_table() -> pd.DataFrame:
    """The association.parquet schema (correct / wrong / discarded V2F rows per method and step)."""
    import pandas as pd

    columns = {"method": "string", "t": "float64", "correct": "int64", "wrong": "int64", "discarded": "int64"}
    return pd.DataFrame(columns=list(columns)).astype(columns)


def empty_traffic_table() -> pd.DataFrame:
    """The traffic.parquet schema (5-minute SUMO statistics) with no rows: controlled scenarios."""
    import pandas as pd

    columns = {
        "interval_start_s": "float64", "interval_end_s": "float64", "mean_vehicles": "float64",
        "exit_flow_vph": "float64", "mean_queue": "float64", "stop_time_s_per_km": "float64",
        "teleports": "int64", "vehicle_seconds": "float64", "distance_km": "float64", "arrived": "int64",
    }
    return pd.DataFrame(columns=list(columns)).astype(columns)


def write_parquet(df: pd.DataFrame, path) -> None:
    """Deterministic Parquet: fixed schema from the frame, no pandas index, zstd (``path``: a path or a
    binary file object)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pa.Table.from_pandas(df, preserve_index=False)
    table = table.replace_schema_metadata(None)
    pq.write_table(table, path, compression="zstd", write_statistics=True)


class _ScenarioSource:
    """Frames of a controlled scenario (Sec. V), capped at ``run.duration_s``; the
    same interface as the SUMO coupler's where the runner needs it."""

    sumo_version = None

    def __init__(self, cfg: Config):
        self.params = cfg.scenario_params()
        self.seed = cfg.run.seed
        self.duration_s = cfg.run.duration_s
        steps = self.params.n_steps if hasattr(self.params, "n_steps") else self.params.max_steps
        self.n_steps = min(steps, int(math.floor(self.duration_s / self.params.dt + 1e-9)) + 1)

    def __enter__(self) -> "_ScenarioSource":
        return self

    def __exit__(self, *exc) -> None:
        return None

    def frames(self):
        for frame in scenario_frames(self.params, self.seed):
            if frame.t > self.duration_s + 1e-9:
                return
            yield frame

    def traffic_table(self) -> pd.DataFrame:
        return empty_traffic_table()


def sumo_scenario(cfg: Config, net=None) -> SumoScenario:
    """The SUMO run of ``cfg`` as `coloc run` starts it (also every bench): the net folder's every route
    file, its additional files and its clock (``SumoScenario.sumo_options``), from ``[scenario] begin_s``
    for ``[run] duration_s``; ``net``: the loaded net folder (default: ``cfg``'s)."""
    return SumoScenario(net=net if net is not None else load_net_folder(cfg.net_dir), control=cfg.scenario.control,
                        seed=cfg.run.seed, step_length=cfg.scenario.step_s, duration_s=cfg.run.duration_s,
                        ballistic=cfg.scenario.ballistic, begin_s=cfg.scenario.begin_s or 0.0,
                        start=cfg.scenario.start, traffic_only_s=traffic_only_s(cfg),
                        reference_point=cfg.scenario.reference_point)


def folder_scenario(net_dir: str | Path, control: str, seed: int, duration_s: float | None = None) -> SumoScenario:
    """:func:`sumo_scenario` of a config that names only the net folder: its clock and step are the folder's
    ``[sumo]`` (duration: its end - begin, else one hour), the rest the config defaults (tools, benches)."""
    from experiments.config import config_from_dict  # noqa: PLC0415

    run = {"name": "folder", "seed": seed, **({"duration_s": float(duration_s)} if duration_s is not None else {})}
    net_dir = Path(net_dir).resolve()
    return sumo_scenario(config_from_dict({"run": run, "scenario": {"kind": "sumo", "net_dir": str(net_dir),
                                                                     "control": control}}, net_dir / "bench.toml"))


class _SumoSource:
    """The SUMO coupler for a net folder."""

    def __init__(self, cfg: Config):
        require_usable_net_folder(cfg.net_dir)  # the checks of `coloc net check`, before SUMO starts
        net = load_net_folder(cfg.net_dir)
        if cfg.scenario.control not in net.tls_off:
            raise InputError(cfg.path, "scenario.control", f"no control named {cfg.scenario.control!r} in "
                                                           f"{net.root / 'scenario.toml'} (have {sorted(net.tls_off)})")
        self.scenario = sumo_scenario(cfg, net)
        self.sensors = oracle_sensors(cfg)
        self.infra = infra_setup(cfg, net)
        self.coupler = None

    def __enter__(self) -> "_SumoSource":
        self.coupler = SumoCoupler(self.scenario, self.sensors, self.infra).__enter__()
        self.sumo_version = self.coupler.traffic.sumo_version
        self.n_steps = self.coupler.n_steps
        return self

    def __exit__(self, *exc) -> None:
        self.coupler.__exit__(*exc)

    def frames(self):
        return self.coupler.frames()

    def traffic_table(self) -> pd.DataFrame:
        import pandas as pd

        return pd.DataFrame(self.coupler.traffic.stats.rows)

    def traffic_losses(self) -> dict:
        """Vehicles never inserted, dropped at load, teleported or in collisions, and the gridlock verdict."""
        return self.coupler.traffic.losses()


def seconds_since_process_start() -> float | None:
    """Wall seconds since this process started (Linux ``/proc``; None elsewhere)."""
    try:
        with open("/proc/self/stat") as f:
            start_ticks = int(f.read().rsplit(")", 1)[1].split()[19])  # field 22, starttime
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None
    return uptime - start_ticks / os.sysconf("SC_CLK_TCK")


def _timing_line(what: str) -> None:
    """``COLOC_TIMING=1``: one line on stderr with the seconds since process start (bench/startup.py)."""
    since = seconds_since_process_start()
    print(f"coloc timing: {what} at {since if since is not None else float('nan'):.2f} s after process start, "
          f"{time.process_time():.2f} s of CPU (wall clock {time.time():.3f})", file=sys.stderr, flush=True)


PROGRESS_LINE_S = 300.0  # simulated seconds between two progress lines when stderr is not a terminal
ETA_FROM_STEP = 2 * BATCH  # steps before the ETA is timed: the estimators' first batches (numba compiles)


def progress_frames(frames, n_steps: int, name: str, progress: bool | None, begin: float = 0.0):
    """The frames, with progress on stderr: ``progress`` True, or None on a terminal, a tqdm bar with
    an ETA; None elsewhere (logs of sweeps and CI), one line per :data:`PROGRESS_LINE_S` simulated
    seconds (counted from ``begin``, the run's begin on the scenario's clock); False nothing."""
    tty = sys.stderr.isatty()
    if progress is False:
        yield from frames
        return
    # The first ETA_FROM_STEP steps carry numba's compilation on a cold cache (minutes, once per install,
    # experiments.warm): the ETA is timed over the steps after them.
    skip = min(ETA_FROM_STEP, n_steps // 4)
    if progress or tty:
        from tqdm import tqdm

        frames = iter(frames)
        for _, frame in zip(range(skip), frames):
            yield frame
        yield from tqdm(frames, total=n_steps, initial=skip, desc=name, unit="step", mininterval=1.0)
        return
    t0 = t_eta = time.perf_counter()
    next_line = PROGRESS_LINE_S
    for k, frame in enumerate(frames, start=1):
        yield frame
        if k == skip:
            t_eta = time.perf_counter()
        if frame.t - begin + 1e-9 >= next_line:
            next_line += PROGRESS_LINE_S
            elapsed = time.perf_counter() - t0
            left = (time.perf_counter() - t_eta) * max(n_steps - k, 0) / max(k - skip, 1)
            at = f" (to {clock(frame.t)})" if begin else ""
            print(f"{name}: {frame.t - begin:.0f} s simulated{at}, step {k} of {n_steps} "
                  f"({100.0 * k / max(n_steps, 1):.0f} %), "
                  f"{elapsed:.0f} s elapsed, about {left:.0f} s left", file=sys.stderr, flush=True)


def frame_source(cfg: Config):
    """The frame source of a config: the SUMO coupler or a controlled scenario (context manager)."""
    return _ScenarioSource(cfg) if cfg.is_controlled_scenario else _SumoSource(cfg)


def _serial_steps(frames, estimators: list, timing: bool):
    """Step every estimator on every frame in this process: (frame, [StepResult, ...]) per frame, in
    step order. Each estimator steps through :data:`experiments.pipeline.BATCH` frames before the next
    one runs (the same results, fewer cache misses: :func:`experiments.pipeline.step_batch`)."""
    known = [METHODS[est.name].known_association for est in estimators]
    batch: list = []
    first = True
    for k, frame in enumerate(frames):
        if timing and k == 0:
            _timing_line("first frame")
        batch.append(frame)
        if len(batch) < BATCH and not (timing and first):
            continue
        yield from _step_frames(batch, estimators, known)
        if timing and first:
            _timing_line("first step of the estimators done")
            first = False
        batch = []
    yield from _step_frames(batch, estimators, known)


def _step_frames(frames: list, estimators: list, known: list[bool]):
    # The bound is told the true association, by the runner, never from the frame.
    pairs = [(f.without_truth(), f.truth.v2f_feature if any(known) else None) for f in frames]
    yield from zip(frames, step_batch(estimators, known, pairs))


def _pooled_steps(frames, pool, timing: bool):
    """The same as :func:`_serial_steps` with the estimators spread over this process and ``pool``'s
    workers (:mod:`experiments.pipeline`): the frames are made while the workers step the earlier
    ones. With ``timing``, the second line comes when the first batch's results are back (BATCH
    frames and LOOKAHEAD batches after the first frame), not after the first step."""
    pool.wait_ready()
    first_frame, first_result = timing, timing
    for frame in frames:
        if first_frame:
            _timing_line("first frame")
            first_frame = False
        for done in pool.submit(frame):
            yield done
            if first_result:
                _timing_line("first results of the estimators back")
                first_result = False
    for done in pool.finish():
        yield done
        if first_result:
            _timing_line("first results of the estimators back")
            first_result = False


def run_experiment(cfg: Config, out_dir: Path, progress: bool | None = None, write_report: bool = True,
                   force: bool = False, workers: int = 0) -> dict:
    """Run one config; returns the summary dict also written to summary.json.

    ``out_dir`` must be absent, empty or an earlier run's folder (``force``: anything but a file);
    it is replaced only when the run has finished (:func:`couplers.publish.staged_folder`).
    ``workers`` >= 1 steps the estimators in that many worker processes beside the frame source
    (:mod:`experiments.pipeline`); every file written is the same, byte for byte, except the wall
    and estimator seconds of summary.json.
    """
    out_dir = Path(out_dir)
    source = frame_source(cfg)
    pool = None
    if workers >= 1:
        from experiments.pipeline import EstimatorPool

        estimators = []
    else:
        estimators = build_estimators(cfg)
    with staged_folder(out_dir, "run", force=force) as tmp:
        # the rows go to spill files in the staging folder as the run goes (experiments.rowstream)
        log = StreamLog(tmp / ".rows", cfg.run.name, list(cfg.run.methods))
        seconds = {m: 0.0 for m in cfg.run.methods}
        comm = {m: CommTally() for m in cfg.run.methods}
        v2v = V2vTally()
        # [gnss_error]: the raw receiver errors, scored from truth (experiments.gnss_world)
        gnss_world = GnssWorldTally() if cfg.gnss_error is not None else None
        t_start = time.perf_counter()
        timing = os.environ.get("COLOC_TIMING", "") not in ("", "0")
        try:
            if workers >= 1:  # started before SUMO, so that the workers' imports overlap its start-up
                pool = EstimatorPool(cfg.run.methods, method_params(cfg), workers)
            with source:
                version = source.sumo_version
                frames = progress_frames(source.frames(), source.n_steps, cfg.run.name, progress,
                                         cfg.scenario.begin_s or 0.0)
                steps = _serial_steps(frames, estimators, timing) if pool is None else _pooled_steps(frames, pool,
                                                                                                     timing)
                for frame, results in steps:
                    log.add_truth(frame)
                    v2v.add(frame)
                    if gnss_world is not None:
                        gnss_world.add(frame)
                    for r in results:
                        seconds[r.name] += r.seconds
                        if r.sent is not None:
                            comm[r.name].add(r.sent)
                        check_finite_estimate(cfg, r.name, frame, r.estimate)
                        log.add(r.name, r.estimate)
                        log.add_association(r.name, frame, r.estimate)
                        log.add_features(r.name, frame, r.estimate)
                log.flush()
        finally:
            if pool is not None:
                pool.close()
        method_stats = (dict(pool.stats) if pool is not None else
                        {e.name: stats for e in estimators if (stats := estimator_stats(e)) is not None})
        # The estimators' state is not needed for the files: let it go before the files are written (the
        # PF's kept kernel matrices are 2 GB).
        estimators.clear()
        wall = time.perf_counter() - t_start
        traffic = source.traffic_table()
        if log.rows == 0:  # nothing to score: say so rather than write an empty run
            raise _nothing_to_estimate(cfg, traffic)
        provenance = {"git": git_revision(), "config_source": str(cfg.path)}
        if version is not None:
            provenance = {"sumo_version": version, **provenance}
        else:
            provenance["frames"] = f"couplers.scenarios ({cfg.scenario.kind}), no SUMO"
        methods = list(cfg.run.methods)
        t0 = scored_from(cfg)  # [analysis] warmup_s: the statistics score t >= t0 only (every row stays in the files)
        log.scored_from = t0
        scores = log.association_scores()
        (tmp / "config.toml").write_text(config_to_toml(cfg, provenance))
        blocks = log.write_estimates(tmp / "estimates.parquet")
        write_parquet(traffic, tmp / "traffic.parquet")
        # Correct / wrong / discarded V2F rows per method and step, for methods that pair
        # measurements with tracks; a GNSS-only run writes the schema with no rows.
        write_parquet(association_table(methods, scores), tmp / "association.parquet")
        feature_blocks = log.write_features(tmp / "features.parquet", scores, KNOWN_ASSOCIATION_METHODS)
        log.discard()  # the spill files (on an error, staged_folder removes them with the staging folder)
        summary = {
            "config": str(cfg.path),
            "seed": cfg.run.seed,
            "sumo_version": version,
            "git": provenance["git"],
            "methods": {},
            "association": {},
            "traffic": {**traffic_summary(traffic), **source.traffic_losses()} if version is not None else None,
            "v2v": v2v.summary(),
            "wall_seconds": wall,
        }
        if version is not None:  # zones / areas that are a default layout, not derived from data (net import)
            from couplers.net.placeholders import folder_placeholders

            summary["placeholders"] = folder_placeholders(cfg.net_dir)
        if (analysis := analysis_summary(cfg)) is not None:  # [analysis] warmup_s: what the statistics score
            summary["analysis"] = analysis
        for method in methods:
            block = blocks[method]
            block["seconds"] = seconds[method]
            if comm[method].steps:
                block["comm"] = comm[method].summary()
            if method in feature_blocks:
                block["features"] = feature_blocks[method]
            summary["methods"][method] = block
            if method in scores:
                sk = scored_mask(scores[method][0], t0)  # [analysis] warmup_s: steps from t0 on
                summary["association"][method] = association_summary(*scores[method][1][sk].sum(axis=0).tolist())
                summary["association"][method]["by_zone"] = log.association_by_zone[method]
        if gnss_world is not None:
            summary["gnss_world"] = gnss_world.summary()
        summary["detections"] = dict(zip(DETECTION_KINDS, (int(c) for c in log.kind_counts)))
        totals = getattr(getattr(source, "coupler", None), "perception_totals", None)
        if totals:
            # [perception]: what the sensors did, over the run and per vehicle-step.
            vehicle_steps = log.vehicle_steps
            summary["perception"] = {"totals": dict(totals),
                                     "per_vehicle_step": {k: v / vehicle_steps for k, v in totals.items()}}
        if log.infra:
            cov_summary = blocks["_coverage"]
            for name, stats in method_stats.items():
                if stats is not None and name in cov_summary["methods"]:
                    cov_summary["methods"][name]["stats"] = stats
            summary["within_rsu_coverage"] = cov_summary
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=False) + "\n")
        if write_report and cfg.report.figures:
            from experiments.report import write_run_report
            from experiments.report.parallel import available_workers

            # with --workers, the figures are drawn in two processes where there are two cores
            write_run_report(tmp, workers=available_workers(2) if workers >= 1 else 1)
    return summary
