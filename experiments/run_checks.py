"""Checks of a run before anything is published: an estimate that is not finite, and a run with nothing to
estimate (no vehicle in the simulated window, or none equipped), each said in one line naming the config
field to change (:mod:`experiments.runner`)."""

from __future__ import annotations

import numpy as np

from coloc.core.frame import Frame, StepEstimate
from couplers.errors import InputError
from couplers.net.folder import load_net_folder
from couplers.net.importer.sumocfg import clock
from experiments.config import Config


def _empty_run(cfg: Config) -> InputError:
    """The error of a run without vehicles: for a SUMO run, where the demand's departures are against the
    simulated window (a demand on its own clock run from 0 is the usual cause), else "run longer"."""
    msg = f"no vehicle was in the network in the {cfg.run.duration_s:g} s simulated: nothing to estimate; run longer"
    if cfg.scenario.kind != "sumo":
        return InputError(cfg.path, "run.duration_s", msg)
    from couplers.net.importer.sumocfg import demand_departures

    begin = cfg.scenario.begin_s or 0.0
    end = begin + cfg.run.duration_s
    folder = load_net_folder(cfg.net_dir)
    dep = demand_departures(folder.route_files)
    window = f"[{begin:g}, {end:g}] s ({clock(begin)}-{clock(end)})"
    if dep.first is not None and dep.first >= end:
        own = folder.clock.begin if folder.clock.begin and folder.clock.begin != begin else None
        fix = (f"set [scenario] begin_s = {own:g} (the net folder's [sumo] begin) or leave it out" if own is not None
               else f"set [scenario] begin_s = {dep.first:g} (a .sumocfg imported with coloc net import --sumocfg "
                    "keeps its clock)")
        return InputError(cfg.path, "scenario.begin_s", f"no vehicle in the simulated window {window}: the demand "
                          f"departs from {dep.first:g} s ({clock(dep.first)}) on; {fix}")
    return InputError(cfg.path, "run.duration_s", f"no vehicle was in the network in the simulated window {window}: "
                      "nothing to estimate; run longer")


def check_finite_estimate(cfg: Config, method: str, frame: Frame, est: StepEstimate) -> None:
    """Refuse a NaN or infinite estimate mean or covariance (and so the whole run: nothing is published),
    naming the method, the step and the vehicle. A finite config within its ranges (experiments.ranges)
    keeps the estimators finite; this is the net under that."""
    ok_mean = np.isfinite(est.mean).all(axis=tuple(range(1, est.mean.ndim)))
    ok_cov = np.isfinite(est.cov).all(axis=tuple(range(1, est.cov.ndim)))
    bad = np.flatnonzero(~(ok_mean & ok_cov))
    if bad.size:
        i = int(bad[0])
        what = "mean" if not ok_mean[i] else "covariance"
        vid = frame.vehicle_ids[i] if i < len(frame.vehicle_ids) else i
        raise InputError(cfg.path, None, f"method {method}: non-finite estimate {what} at step t = {frame.t:g} s "
                                         f"(vehicle {vid}, {bad.size} of {len(ok_mean)} vehicles): nothing was "
                                         "written; a config value at the edge of its range?")


def _nothing_to_estimate(cfg: Config, traffic) -> InputError:
    """Why a run has no estimate: no vehicle in the network, or ([v2x]) vehicles but none equipped."""
    drove = traffic is not None and "vehicle_seconds" in traffic and float(traffic["vehicle_seconds"].sum()) > 0
    if drove and cfg.v2x is not None:
        return InputError(cfg.path, "v2x.penetration_rate",
                          f"vehicles were in the network but none of them was equipped with V2X in the "
                          f"{cfg.run.duration_s:g} s simulated (penetration_rate = {cfg.v2x.penetration_rate:g}): "
                          "nothing to estimate; raise v2x.penetration_rate or run longer")
    return _empty_run(cfg)
