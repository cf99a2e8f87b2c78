"""The registry of methods: the one place where a method is named.

Each :class:`Method` says how ``coloc run`` builds it (``build``, from the plain parameter
dataclasses of :class:`MethodParams`; ``experiments.runner`` fills them from a config), whether the
runner tells it the true association (``known_association``: the bounds, which implement
:class:`coloc.core.protocol.KnownAssociationEstimator`), whether it needs infrastructure frames
(``infrastructure``: config ``[infra]``), and how reports show it (``label``, ``color``). The order
of :data:`METHODS` is the order of the reports. Config validation, the runner, the report and the
estimator classes (their default ``name``) read it; the names are the public identifiers of
users' configs (``run.methods``) and of the Parquet ``method`` column, so they never change.

``fg_topology_old`` and ``kf_gps_odom`` are made only by the factor-graph study
(``experiments.studies.fg_topology``, which names its own methods): they have a style and no builder.

The builders import their estimator when called, so reading the registry (config validation,
reports) loads no numba kernel and no gtsam, and the method modules can take their names from here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from coloc.core.detection import DetectionModel
    from coloc.core.models import MotionParams
    from coloc.inference.params import IcpParams
    from coloc.methods.icp_da_lc import LcParams
    from coloc.methods.icp_da_pf import PfParams
    from coloc.methods.coop_fusion import CoopFusion
    from coloc.methods.gnss_bias import GnssModelParams
    from coloc.methods.infra import InfraMethodParams
    from coloc.methods.joint_oracle import OracleWorld


@dataclass(frozen=True)
class MethodParams:
    """Everything a builder may read: ``[motion]``, ``[icp]`` (with the motion), ``[lc]``, ``[pf]``
    (with the run's seed) and, for the infrastructure methods, the ``[infra]`` settings (None
    without an ``[infra]`` table)."""

    motion: MotionParams
    icp: IcpParams
    lc: LcParams
    pf: PfParams
    infra: InfraMethodParams | None = None
    detection: DetectionModel | None = None  # the vehicles' sensors, with lc.sensor_fov (from [perception])
    # The integrator's receiver error model ([gnss_model]): gnss with a bias state and fault exclusion;
    # None: the white tracker of the paper.
    gnss_model: GnssModelParams | None = None
    # What the joint_oracle is told of the world ([gnss_error], [scenario] start; the oracle only);
    # None: the paper's white GNSS and fast-start prior.
    oracle_world: OracleWorld | None = None
    # [fusion] with its receiver model: split-CI fusion in icp_known_da, icp_da_lc and icp_da_pf (and
    # icp_known_da_pf); None: the paper's BPA-L.
    fusion: CoopFusion | None = None


@dataclass(frozen=True)
class Method:
    """One method: its name, how reports show it, how ``coloc run`` builds it and what it needs."""

    name: str
    label: str  # display name in reports
    color: str  # matplotlib colour in reports (green is reserved for feature accuracy)
    build: Callable[[MethodParams], object] | None = None  # None: made by a study, not by ``coloc run``
    known_association: bool = False  # the runner calls step_with_association(frame, true association)
    infrastructure: bool = False  # reads frame.infra: the config needs an [infra] table
    # Handles frame.v2f_class (per-class feature model, class-gated association) or reads no V2F rows:
    # may run with [features] pedestrians.
    feature_classes: bool = False
    # Its step costs a small fraction of a frame's synthesis: with the estimators in worker processes
    # (``coloc run --workers N``, experiments.pipeline) it steps in the runner's process beside SUMO,
    # where sending it the frame and its results back would cost more than its step.
    light: bool = False
    # Relative cost of a step (icp_known_da = 1): where it steps with worker processes
    # (experiments.pipeline.assign_methods). Measured on the TLR hour (bench/coupled_vs_sumo.py,
    # 2026-11-26): gnss 0.07 ms, icp_known_da 1.04-1.06 ms, icp_da_lc 1.27-1.41 ms a step; icp_da_pf
    # 1.5-2 s a step at J = 1000. Not measured (the infrastructure methods): 1.
    cost: float = 1.0

    @property
    def runnable(self) -> bool:
        """``coloc run`` can build it (it may be listed in ``run.methods``)."""
        return self.build is not None


def _single(model):
    """The infrastructure methods take [gnss_model]'s single bias only (bias_share, bias_tau_s)."""
    return None if model is None else model.single_model()


def _gnss(p: MethodParams):
    if p.gnss_model is not None:
        from coloc.methods.gnss_bias import GnssBiasTracker

        return GnssBiasTracker(motion=p.motion, model=p.gnss_model)
    from coloc.methods.gnss import GnssTracker

    return GnssTracker(motion=p.motion)


def _icp_known_da(p: MethodParams):
    from coloc.methods.icp_known_da import IcpKnownDA

    return IcpKnownDA(params=p.icp, fusion=p.fusion)


def _icp_da_lc(p: MethodParams):
    from coloc.methods.icp_da_lc import IcpDaLc

    return IcpDaLc(params=p.icp, lc=p.lc, detection=p.detection if p.lc.sensor_fov else None, fusion=p.fusion)


def _icp_da_pf(p: MethodParams):
    from coloc.methods.icp_da_pf import IcpDaPf

    return IcpDaPf(params=p.icp, lc=p.lc, pf=p.pf, detection=p.detection if p.lc.sensor_fov else None,
                   fusion=p.fusion)


def _icp_known_da_pf(p: MethodParams):
    from coloc.methods.icp_da_pf import IcpDaPf

    # The same estimator told the true association by the runner: it separates PF's Monte
    # Carlo error from its association.
    return IcpDaPf(params=p.icp, lc=p.lc, pf=p.pf, name=ICP_KNOWN_DA_PF.name, fusion=p.fusion)


def _joint_oracle(p: MethodParams):
    from coloc.methods.joint_oracle import JointOracle, OracleWorld

    return JointOracle(params=p.icp, world=p.oracle_world if p.oracle_world is not None else OracleWorld())


def _infra_params(p: MethodParams) -> InfraMethodParams:
    if p.infra is None:
        raise ValueError("an infrastructure method needs MethodParams.infra (config [infra])")
    return p.infra


def _rsu_bp(p: MethodParams):
    from coloc.methods.infra import RsuBpInfra

    return RsuBpInfra(_infra_params(p), fusion=p.fusion)


def _sme(p: MethodParams):
    from coloc.methods.infra import SmeInfra

    return SmeInfra(_infra_params(p), gnss_model=_single(p.gnss_model), fusion=p.fusion)


def _fg_topology_new(p: MethodParams):
    from coloc.methods.fg_topology import FgTopologyInfra

    return FgTopologyInfra(_infra_params(p), gnss_model=_single(p.gnss_model))


GNSS = Method("gnss", "GNSS", "tab:blue", _gnss, feature_classes=True, light=True, cost=0.1)
ICP_KNOWN_DA = Method("icp_known_da", "ICP known DA", "black", _icp_known_da, known_association=True,
                      feature_classes=True, cost=1.0)
ICP_DA_LC = Method("icp_da_lc", "ICP-DA-LC", "tab:red", _icp_da_lc, feature_classes=True, cost=1.3)
ICP_DA_PF = Method("icp_da_pf", "ICP-DA-PF", "tab:orange", _icp_da_pf, cost=1500.0)
ICP_KNOWN_DA_PF = Method("icp_known_da_pf", "ICP-PF known DA", "goldenrod", _icp_known_da_pf,
                         known_association=True, cost=1500.0)
# The oracle: centralized, told the association and the world's GNSS error structure (not a method a
# vehicle could run; coloc/methods/joint_oracle.py). Its step is O(d^3) in the joint dimension: ~1 s
# on the realistic arterial (docs/validation/oracle.md).
JOINT_ORACLE = Method("joint_oracle", "Joint oracle", "dimgray", _joint_oracle, known_association=True,
                      cost=500.0)
RSU_BP = Method("rsu_bp", "RSU-BP", "tab:purple", _rsu_bp, infrastructure=True)
SME = Method("sme", "SME", "tab:brown", _sme, infrastructure=True)
FG_TOPOLOGY_OLD = Method("fg_topology_old", "FG topology (old)", "tab:pink")
FG_TOPOLOGY_NEW = Method("fg_topology_new", "FG topology (new)", "tab:olive", _fg_topology_new,
                         infrastructure=True)
KF_GPS_ODOM = Method("kf_gps_odom", "KF GPS+odometry", "tab:cyan")

#: name -> method, in report order.
METHODS: dict[str, Method] = {
    m.name: m
    for m in (GNSS, ICP_KNOWN_DA, ICP_DA_LC, ICP_DA_PF, ICP_KNOWN_DA_PF, JOINT_ORACLE, RSU_BP, SME, FG_TOPOLOGY_OLD,
              FG_TOPOLOGY_NEW, KF_GPS_ODOM)
}


def runnable_methods() -> tuple[str, ...]:
    """Names ``coloc run`` can build, in registry order."""
    return tuple(m.name for m in METHODS.values() if m.runnable)


def build_method(name: str, params: MethodParams):
    """The estimator of method ``name`` (ValueError for a name the registry cannot build). Under a
    ``[gnss_model]`` with the receiver's report calibrated (``degraded_*``), every method but the joint oracle
    steps on the calibrated report (:func:`coloc.methods.report_calibration.report_calibrated`)."""
    method = METHODS.get(name)
    if method is None or not method.runnable:
        raise ValueError(f"no estimator for method {name!r} (available: {', '.join(runnable_methods())})")
    est = method.build(params)
    model = params.gnss_model
    if model is not None and model.calibrates_report and name != JOINT_ORACLE.name:
        from coloc.methods.report_calibration import report_calibrated

        return report_calibrated(est, model)
    return est
