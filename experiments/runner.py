"""One run: SUMO coupler -> estimators -> Parquet files, summary.json, report.

The output folder appears complete or not at all: everything is written into a
hidden sibling folder that is renamed into place at the end.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
from tqdm import tqdm

from coloc.frame import Frame, StepEstimate
from coloc.gnss import GnssTracker
from coloc.icp import IcpParams
from coloc.icp_known_da import IcpKnownDA
from couplers.errors import InputError
from couplers.netfolder import check_region_coverage, load_net_folder
from couplers.sumo_coupler import SumoCoupler, SumoScenario
from couplers.sumo_traffic import sumo_version
from experiments.config import Config, config_to_toml
from experiments.scoring import along_cross_errors, feature_summary, method_summary, traffic_summary

PROJECT_ROOT = Path(__file__).resolve().parents[1]
KNOWN_ASSOCIATION_METHODS = frozenset({"icp_known_da"})


def build_estimators(cfg: Config) -> list:
    """Estimator objects for ``cfg.run.methods``, in that order."""
    icp = IcpParams(motion=cfg.motion, **dataclasses.asdict(cfg.icp))
    factories = {
        "gnss": lambda: GnssTracker(motion=cfg.motion),
        "icp_known_da": lambda: IcpKnownDA(params=icp),
    }
    return [factories[m]() for m in cfg.run.methods]


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
    """Per-step rows of one run, kept as arrays and concatenated once at the end."""

    truth_parts: list = field(default_factory=list)
    method_parts: dict = field(default_factory=dict)
    feature_parts: list = field(default_factory=list)

    def add_truth(self, frame: Frame) -> None:
        tr = frame.truth
        self.truth_parts.append(
            (np.full(frame.n_vehicles, frame.t), frame.vehicle_ids, tr.x_true, tr.heading, tr.zone, tr.area)
        )

    def add(self, method: str, est: StepEstimate) -> None:
        self.method_parts.setdefault(method, []).append(
            (est.mean, est.cov[:, 0, 0], est.cov[:, 1, 1])
        )

    def add_features(self, method: str, frame: Frame, est: StepEstimate) -> None:
        """Feature-track errors; track ids of known-DA methods are true feature indices."""
        if est.feature_mean is None or est.feature_track_ids is None or est.feature_mean.shape[0] == 0:
            return
        ids = np.asarray(est.feature_track_ids, dtype=np.int64)
        err = est.feature_mean[:, :2] - frame.truth.features_true[ids, :2]
        self.feature_parts.append((method, frame.t, ids, np.hypot(err[:, 0], err[:, 1])))

    def feature_table(self) -> pd.DataFrame:
        cols = {"method": "string", "t": "float64", "track": "int64", "err_pos": "float64"}
        if not self.feature_parts:
            return pd.DataFrame(columns=list(cols)).astype(cols)
        return pd.DataFrame(
            {
                "method": np.concatenate([np.full(ids.size, m, dtype=object) for m, _, ids, _ in self.feature_parts]),
                "t": np.concatenate([np.full(ids.size, t) for _, t, ids, _ in self.feature_parts]),
                "track": np.concatenate([ids for _, _, ids, _ in self.feature_parts]),
                "err_pos": np.concatenate([e for _, _, _, e in self.feature_parts]),
            }
        ).astype(cols)

    def table(self, run_name: str) -> pd.DataFrame:
        if not self.truth_parts:
            cols = {"run": [], "method": [], "t": [], "vehicle": []}
            return pd.DataFrame(cols)
        t, vid, x_true, heading, zone, area = (np.concatenate(c) for c in zip(*self.truth_parts))
        frames = []
        for method, parts in self.method_parts.items():
            mean, vx_, vy_ = (np.concatenate(c) for c in zip(*parts))
            err = mean - x_true
            along, cross = along_cross_errors(err[:, :2], heading)
            frames.append(
                pd.DataFrame(
                    {
                        "run": run_name,
                        "method": method,
                        "t": t,
                        "vehicle": vid.astype(str),
                        "px": mean[:, 0], "py": mean[:, 1], "vx": mean[:, 2], "vy": mean[:, 3],
                        "px_true": x_true[:, 0], "py_true": x_true[:, 1],
                        "vx_true": x_true[:, 2], "vy_true": x_true[:, 3],
                        "err_pos": np.hypot(err[:, 0], err[:, 1]),
                        "err_vel": np.hypot(err[:, 2], err[:, 3]),
                        "err_along": along, "err_cross": cross,
                        "zone": zone.astype(str), "area": area.astype(str),
                        "var_px": vx_, "var_py": vy_,
                    }
                )
            )
        return pd.concat(frames, ignore_index=True)


def empty_association_table() -> pd.DataFrame:
    """The association.parquet schema (correct / wrong / discarded V2F rows per method and step)."""
    columns = {"method": "string", "t": "float64", "correct": "int64", "wrong": "int64", "discarded": "int64"}
    return pd.DataFrame(columns=list(columns)).astype(columns)


def write_parquet(df: pd.DataFrame, path: Path) -> None:
    """Deterministic Parquet: fixed schema from the frame, no pandas index, zstd."""
    table = pa.Table.from_pandas(df, preserve_index=False)
    table = table.replace_schema_metadata(None)
    pq.write_table(table, path, compression="zstd", write_statistics=True)


def _fresh_partial_dir(out_dir: Path) -> Path:
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_dir.parent / f".{out_dir.name}.partial-{os.getpid()}"
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir()
    return tmp


def _commit_dir(tmp: Path, out_dir: Path) -> None:
    """Put a finished folder in place; an existing one is replaced only now."""
    old = None
    if out_dir.exists():
        old = out_dir.parent / f".{out_dir.name}.old-{os.getpid()}"
        os.replace(out_dir, old)
    os.replace(tmp, out_dir)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def run_experiment(cfg: Config, out_dir: Path, progress: bool | None = None, write_report: bool = True) -> dict:
    """Run one config; returns the summary dict also written to summary.json."""
    out_dir = Path(out_dir)
    net = load_net_folder(cfg.net_dir)
    check_region_coverage(net)
    scenario = SumoScenario(
        net=net,
        control=cfg.scenario.control,
        seed=cfg.run.seed,
        step_length=cfg.scenario.step_s,
        duration_s=cfg.run.duration_s,
        ballistic=cfg.scenario.ballistic,
    )
    scenario.sumo_options()  # validates the control name before anything is started
    estimators = build_estimators(cfg)
    tmp = _fresh_partial_dir(out_dir)
    try:
        log = EstimateLog()
        seconds = {e.name: 0.0 for e in estimators}
        t_start = time.perf_counter()
        with SumoCoupler(scenario, cfg.sensors) as coupler:
            version = coupler.traffic.sumo_version
            bar = tqdm(
                coupler.frames(), total=coupler.n_steps, desc=cfg.run.name, unit="step",
                disable=(not sys.stderr.isatty()) if progress is None else (not progress), mininterval=1.0,
            )
            for frame in bar:
                log.add_truth(frame)
                blind = frame.without_truth()
                for est in estimators:
                    t0 = time.perf_counter()
                    if est.name in KNOWN_ASSOCIATION_METHODS:
                        # The bound is told the true association, by the runner, never from the frame.
                        res = est.step_with_association(blind, frame.truth.v2f_feature)
                    else:
                        res = est.step(blind)
                    seconds[est.name] += time.perf_counter() - t0
                    log.add(est.name, res)
                    log.add_features(est.name, frame, res)
        wall = time.perf_counter() - t_start
        traffic = pd.DataFrame(coupler.traffic.stats.rows)
        estimates = log.table(cfg.run.name)
        provenance = {"sumo_version": version, "git": git_revision(), "config_source": str(cfg.path)}
        (tmp / "config.toml").write_text(config_to_toml(cfg, provenance))
        write_parquet(estimates, tmp / "estimates.parquet")
        write_parquet(traffic, tmp / "traffic.parquet")
        # Association scoring (correct / wrong / discarded V2F rows per method and step) is
        # filled by methods that associate; a GNSS-only run writes the schema with no rows.
        write_parquet(empty_association_table(), tmp / "association.parquet")
        features = log.feature_table()
        if len(features):
            write_parquet(features, tmp / "features.parquet")
        summary = {
            "config": str(cfg.path),
            "seed": cfg.run.seed,
            "sumo_version": version,
            "git": provenance["git"],
            "methods": {},
            "association": {},
            "traffic": traffic_summary(traffic),
            "wall_seconds": wall,
        }
        for method in cfg.run.methods:
            block = method_summary(estimates[estimates["method"] == method])
            block["seconds"] = seconds[method]
            feat = features[features["method"] == method]["err_pos"].to_numpy()
            if feat.size:
                block["features"] = feature_summary(feat)
            summary["methods"][method] = block
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2, sort_keys=False) + "\n")
        if write_report and cfg.report.figures:
            from experiments.report import write_run_report

            write_run_report(tmp)
        _commit_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return summary
