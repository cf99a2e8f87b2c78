"""The estimator contract (docs/architecture.md "The frame contract" and "Reliability"), one test each, run over every
method of the registry that ``coloc run`` can build:

* truth-blind: identical output (to the byte) when the frame's truth fields are scrambled or absent;
* empty frames (no vehicles) before, between and after vehicles, and vehicles with no feature in range;
* vehicles entering and leaving between steps (and re-entering);
* rows in ``frame.vehicle_ids`` order, whatever the order of the vehicles in each frame;
* covariances symmetric positive definite.

Infrastructure methods run on :func:`scenes.infra_frames`, the others on :func:`scenes.road_frames`.
Known-association methods are driven through ``step_with_association`` with the truth's association
(taken here, as the runner does, never by the estimator).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from coloc.core.models import MotionParams
from coloc.core.protocol import Estimator, KnownAssociationEstimator
from coloc.inference.params import IcpParams
from coloc.methods.icp_da_lc import LcParams
from coloc.methods.icp_da_pf import PfParams
from coloc.methods.coop_fusion import CoopFusion, FusionParams
from coloc.methods.gnss_bias import GnssModelParams
from coloc.methods.infra import InfraMethodParams
from coloc.methods.joint_oracle import OracleWorld
from coloc.methods.registry import METHODS, MethodParams, build_method
from scenes import infra_frames, road_frames, scrambled, select_vehicles

# ``gnss+gnss_model``: ``gnss`` built with a [gnss_model] (coloc.methods.gnss_bias); ``joint_oracle+world``: the
# oracle told a correlated GNSS world, first fixes and an IMU (coloc.methods.joint_oracle.OracleWorld);
# ``X+fusion``: X with [fusion] (coloc.methods.coop_fusion, white receiver); ``X+fusion+gnss_model``: with both tables;
# ``+two_state``: [gnss_model] with bias_model = "two_state" (coloc.methods.gnss_bias2); ``+calibrated``: that model
# with the receiver's report calibrated (coloc.methods.report_calibration).
FUSED = [f"{m}+fusion{tail}" for m in ("icp_known_da", "icp_da_lc", "icp_da_pf", "icp_known_da_pf")
         for tail in ("", "+gnss_model", "+two_state")]
# Infrastructure methods with the receiver model (fg_topology_new, sme), sme with [fusion] (re-entry CI) and
# rsu_bp with [fusion] (the PF rule of coloc.methods.pf_fusion).
INFRA_VARIANTS = ["fg_topology_new+gnss_model", "sme+gnss_model", "sme+fusion", "sme+fusion+gnss_model",
                  "rsu_bp+fusion", "rsu_bp+fusion+gnss_model"]
RUNNABLE = ([m.name for m in METHODS.values() if m.runnable] + ["gnss+gnss_model", "gnss+two_state",
                                                                   "gnss+two_state+calibrated",
                                                                   "icp_da_lc+fusion+two_state+calibrated",
                                                                   "icp_known_da+fusion+two_state+calibrated",
                                                                   "joint_oracle+world", "joint_oracle+heading",
                                                                   "joint_oracle+heading+gate", "joint_oracle+fix"]
            + FUSED
            + INFRA_VARIANTS)
ORACLE_WORLD = OracleWorld(gnss="field", common_share=0.5, field_share=0.5, field_corr_length_m=50.0,
                           local_corr_length_m=20.0, nlos=True, accel_turn_on_sigma=0.196,
                           accel_bias_sigma=0.0735, accel_noise_density=0.004, front_lever_m=2.25)
# ``joint_oracle+heading``: that world with the heading and the gyroscope bias as states (the [inertial] defaults)
ORACLE_HEADING = replace(ORACLE_WORLD, gyro_turn_on_sigma=0.5, gyro_bias_sigma=0.0497,
                         gyro_noise_density=0.01944, heading_state=True)
# ``joint_oracle+heading+gate``: the heading state with the linearization gate (heading_row_max_std_deg)
ORACLE_HEADING_GATE = replace(ORACLE_HEADING, heading_row_max_std_deg=2.0)
# ``joint_oracle+fix``: the satellite world told at fix level ([oracle] gnss_channel = "fix"), every term on
ORACLE_FIX = OracleWorld(gnss="fix", fix_common_sigma_m=1.11, fix_local_above_m=2.0, fix_local_scale=2.0,
                         fix_local_below_scale=0.6, fix_noise_share=0.17, local_corr_length_m=35.0, tau_s=300.0,
                         common_tau_s=1800.0, fix_velocity_scale=1.35, nlos=True, accel_turn_on_sigma=0.196,
                         accel_bias_sigma=0.0735, accel_noise_density=0.004)


def _method(name: str):
    """The registry entry of a parametrization name (``gnss+gnss_model`` -> ``gnss``)."""
    return METHODS[name.split("+")[0]]
ROAD_MOTION = MotionParams(sigma_along=0.08, sigma_cross=0.08)
INFRA_MOTION = MotionParams(sigma_cross=0.1)


def _receiver(name: str):
    """[gnss_model] of a parametrization name: the single model, the two-state one, or None."""
    if name.endswith("+gnss_model"):
        return GnssModelParams()
    if name.endswith("+calibrated"):  # the calibrated report (coloc.methods.report_calibration)
        return GnssModelParams(bias_model="two_state", degraded_above_m=0.5, degraded_position_scale=2.0,
                               degraded_velocity_scale=3.0)
    return GnssModelParams(bias_model="two_state") if name.endswith("+two_state") else None


def build(name: str):
    method = _method(name)
    motion = INFRA_MOTION if method.infrastructure else ROAD_MOTION
    params = MethodParams(
        motion=motion, icp=IcpParams(motion=motion), lc=LcParams(),
        pf=PfParams(vehicle_particles=300, feature_particles=300, seed=3),
        infra=InfraMethodParams(motion=motion, rsu_bp_particles=60),
        gnss_model=_receiver(name),
        oracle_world=ORACLE_WORLD if name.endswith("+world") else ORACLE_HEADING if name.endswith("+heading")
        else ORACLE_HEADING_GATE if name.endswith("+heading+gate") else ORACLE_FIX if name.endswith("+fix") else None,
        fusion=CoopFusion.from_config(FusionParams(), _receiver(name)) if "+fusion" in name else None,
    )
    est = build_method(method.name, params)
    assert est.name == method.name
    protocol = KnownAssociationEstimator if method.known_association else Estimator
    assert isinstance(est, protocol)
    return est


def frames_for(name: str, **kw) -> list:
    if _method(name).infrastructure:
        return infra_frames(**{"n_steps": 20, "n_veh": 5, **kw})
    return road_frames(**{"steps": 8, "v2v_range": 25.0, **kw})


def step(name: str, est, frame, association=None):
    """One step as the runner drives it; ``association`` defaults to the frame's true one."""
    if _method(name).known_association:
        v2f = frame.truth.v2f_feature if association is None else association
        return est.step_with_association(frame, np.array(v2f, copy=True))
    return est.step(frame)


def assert_valid(est, frame):
    """Rows in frame order (shapes), finite, covariances symmetric positive definite."""
    n = frame.n_vehicles
    assert est.mean.shape == (n, 4) and est.cov.shape == (n, 4, 4)
    assert np.all(np.isfinite(est.mean)) and np.all(np.isfinite(est.cov))
    np.testing.assert_allclose(est.cov, np.swapaxes(est.cov, -1, -2), rtol=0, atol=1e-9)
    if n:
        assert np.all(np.linalg.eigvalsh(est.cov) > 0)
    if est.covered is not None:
        assert est.covered.shape == (n,)
    if est.v2f_assignment is not None:
        assert est.v2f_assignment.shape == (frame.v2f_z.shape[0],)


@pytest.mark.parametrize("name", RUNNABLE)
def test_truth_blind(name):
    """Scrambled truth, no truth: the same bytes, the same pairing and feature tracks."""
    rng = np.random.default_rng(5)
    a, b, c = build(name), build(name), build(name)
    for f in frames_for(name):
        assoc = f.truth.v2f_feature.copy()
        ea = step(name, a, f, assoc)
        for e in (step(name, b, scrambled(f, rng), assoc), step(name, c, f.without_truth(), assoc)):
            assert ea.mean.tobytes() == e.mean.tobytes() and ea.cov.tobytes() == e.cov.tobytes()
            for field in ("covered", "v2f_assignment", "feature_mean", "feature_track_ids"):
                x, y = getattr(ea, field), getattr(e, field)
                assert (x is None) == (y is None), field
                if x is not None:
                    np.testing.assert_array_equal(x, y, err_msg=field)


@pytest.mark.parametrize("name", RUNNABLE)
def test_empty_frames_and_no_features(name):
    """No vehicles at the start, in the middle (all left) and at the end; vehicles entering after
    an empty frame start afresh; a run whose vehicles have no feature in range."""
    frames = frames_for(name, **({"n_steps": 8} if _method(name).infrastructure else {"steps": 6}))
    none = lambda f: select_vehicles(f, [])  # noqa: E731
    everyone = lambda f: select_vehicles(f, np.arange(f.n_vehicles), entered=np.ones(f.n_vehicles, bool))  # noqa: E731
    seq = [none(frames[0]), everyone(frames[1]), frames[2], none(frames[3]), everyone(frames[4]), *frames[5:],
           none(frames[-1])]
    est = build(name)
    for f in seq:
        assert_valid(step(name, est, f), f)
    est = build(name)
    no_features = (infra_frames(n_steps=8, n_veh=4, features=False) if _method(name).infrastructure
                   else road_frames(steps=6, n_feat=0))
    for f in no_features:
        assert f.v2f_z.shape[0] == 0
        assert_valid(step(name, est, f), f)


def _nearest_truth(est, frame) -> np.ndarray:
    d = np.linalg.norm(est.mean[:, None, :] - frame.truth.x_true[None, :, :], axis=2)
    return np.argmin(d, axis=1)


@pytest.mark.parametrize("name", RUNNABLE)
def test_vehicles_enter_and_leave(name):
    """Vehicle 1 leaves at step 3, vehicle 2 enters at step 2, vehicle 0 leaves at step 4 and
    comes back (entered) at step 6: every row stays with its vehicle and every output is valid."""
    kw = {"n_steps": 10, "n_veh": 5} if _method(name).infrastructure else {"steps": 9, "spacing": 40.0}
    est = build(name)
    for k, f in enumerate(frames_for(name, **kw)):
        present = [i for i in range(f.n_vehicles)
                   if not (i == 1 and k >= 3) and not (i == 2 and k < 2) and not (i == 0 and 4 <= k < 6)]
        entered = np.array([f.entered[i] or (i == 2 and k == 2) or (i == 0 and k == 6) for i in present])
        g = select_vehicles(f, present, entered=entered)
        e = step(name, est, g)
        assert_valid(e, g)
        np.testing.assert_array_equal(_nearest_truth(e, g), np.arange(g.n_vehicles))


@pytest.mark.parametrize("name", RUNNABLE)
def test_rows_in_frame_order(name):
    """The vehicles come in a different order at every step: row i is always vehicle_ids[i]."""
    kw = {"n_steps": 10, "n_veh": 5} if _method(name).infrastructure else {"steps": 8, "spacing": 40.0}
    rng = np.random.default_rng(11)
    est = build(name)
    for f in frames_for(name, **kw):
        g = select_vehicles(f, rng.permutation(f.n_vehicles))
        e = step(name, est, g)
        assert_valid(e, g)
        np.testing.assert_array_equal(_nearest_truth(e, g), np.arange(g.n_vehicles))


@pytest.mark.parametrize("name", RUNNABLE)
def test_covariances_stay_spd(name):
    """A longer run with features: every vehicle covariance symmetric positive definite, every step."""
    kw = {"n_steps": 30, "n_veh": 6} if _method(name).infrastructure else {"steps": 15}
    est = build(name)
    for f in frames_for(name, **kw):
        e = step(name, est, f)
        assert_valid(e, f)
        if e.feature_cov is not None and e.feature_cov.shape[0]:
            assert np.all(np.isfinite(e.feature_cov))


ROAD_METHODS = [m for m in RUNNABLE if not _method(m).infrastructure]


@pytest.mark.parametrize("name", ROAD_METHODS)
def test_inertial_input_contract(name):
    """With the body-frame IMU (``[inertial]``; ``frame.accel`` NaN): truth-blind to the byte, vehicles
    entering, leaving and coming back in another row order, covariances SPD and every output finite."""
    from couplers.sensing.inertial import InertialParams

    rng = np.random.default_rng(7)
    frames = road_frames(steps=9, spacing=40.0, v2v_range=25.0, inertial=InertialParams())
    assert all(f.imu is not None and np.all(np.isnan(f.accel)) for f in frames)
    a, b = build(name), build(name)
    for k, f in enumerate(frames):
        present = [i for i in range(f.n_vehicles)
                   if not (i == 1 and k >= 3) and not (i == 2 and k < 2) and not (i == 0 and 4 <= k < 6)]
        entered = np.array([f.entered[i] or (i == 2 and k == 2) or (i == 0 and k == 6) for i in present])
        g = select_vehicles(f, present, entered=entered) if k % 2 == 0 else select_vehicles(
            f, np.array(present)[::-1], entered=entered[::-1])
        assoc = g.truth.v2f_feature.copy()
        ea = step(name, a, g, assoc)
        eb = step(name, b, scrambled(g, rng), assoc)
        assert ea.mean.tobytes() == eb.mean.tobytes() and ea.cov.tobytes() == eb.cov.tobytes()
        assert_valid(ea, g)
        np.testing.assert_array_equal(_nearest_truth(ea, g), np.arange(g.n_vehicles))


def with_clutter_and_pedestrians(frame, rng):
    """The frame with one false detection per vehicle (a static-looking object within 30 m, truth -1,
    reported static) and feature 1 labelled a pedestrian, its rows class 1 (Frame.v2f_class)."""
    from dataclasses import replace

    n = frame.n_vehicles
    tr = frame.truth
    off = rng.uniform(-30.0, 30.0, (n, 2))
    cz = np.c_[off, -tr.x_true[:, 2:]] + rng.normal(0.0, 0.1, (n, 4))
    owner = np.concatenate([frame.v2f_owner, np.arange(n)])
    order = np.argsort(owner, kind="stable")
    feat = np.concatenate([tr.v2f_feature, np.full(n, -1)])[order]
    klass = np.zeros(tr.features_true.shape[0], np.int8)
    klass[1] = 1
    row_class = np.where(feat >= 0, klass[np.maximum(feat, 0)], 0).astype(np.int8)
    cr = np.broadcast_to(np.diag([0.01, 0.01, 0.01, 0.01]), (n, 4, 4))  # 0.1 m, 0.1 m/s as the V2F rows
    return replace(frame, v2f_z=np.concatenate([frame.v2f_z, cz])[order], v2f_owner=owner[order],
                   v2f_R=np.concatenate([frame.v2f_R, cr])[order], v2f_class=row_class,
                   truth=replace(tr, v2f_feature=feat, feature_class=klass))


@pytest.mark.parametrize("name", ["icp_known_da", "icp_da_lc", "icp_known_da+fusion+gnss_model",
                                  "icp_da_lc+fusion+gnss_model", "icp_da_lc+fusion+gnss_model+reloc",
                                  "icp_da_lc+fusion+gnss_model+reloc+gain+arbiter+anchor"])
def test_truth_blind_with_clutter_and_pedestrians(name):
    """Clutter rows (truth -1), pedestrian rows (class 1) and the existence / clutter model of ICP-DA-LC
    (``+reloc``: with the relocalization of lost vehicles, ``[lc] relocalize_radius_m``; ``+gain+arbiter``: also of
    vehicles partly on the map, ``relocalize_min_gain``, and the map's veto of the reset, ``reset_map_margin``;
    ``+anchor``: the fix's arbitration and the map-anchored position, ``fix_map_margin``, ``anchor_margin``):
    scrambled truth or none gives the same bytes, pairings and tracks."""
    from coloc.methods.icp_da_lc import IcpDaLc
    from coloc.methods.icp_known_da import IcpKnownDA

    lc = LcParams(clutter_intensity=3e-4, track_existence=True,
                  relocalize_radius_m=10.0 if "+reloc" in name else 0.0,
                  relocalize_min_gain=1 if "+gain" in name else 0,
                  own_consistency_gate=0.99 if "+arbiter" in name else 0.0,
                  reset_map_margin=1 if "+arbiter" in name else 0,
                  fix_map_margin=1 if "+anchor" in name else 0,
                  anchor_margin=1 if "+anchor" in name else 0)
    params = IcpParams(motion=ROAD_MOTION)

    def make():
        fusion = CoopFusion.from_config(FusionParams(), GnssModelParams()) if "+fusion" in name else None
        return (IcpDaLc(params=params, lc=lc, fusion=fusion) if name.startswith("icp_da_lc")
                else IcpKnownDA(params, fusion=fusion))

    rng = np.random.default_rng(11)
    frames = [with_clutter_and_pedestrians(f, rng) for f in road_frames(steps=8, v2v_range=25.0)]
    a, b, c = make(), make(), make()
    srng = np.random.default_rng(5)
    for f in frames:
        assert (f.truth.v2f_feature < 0).any() and (f.v2f_class == 1).any()
        assoc = f.truth.v2f_feature.copy()
        ea = step(name, a, f, assoc)
        assert_valid(ea, f)
        for e in (step(name, b, scrambled(f, srng), assoc), step(name, c, f.without_truth(), assoc)):
            assert ea.mean.tobytes() == e.mean.tobytes() and ea.cov.tobytes() == e.cov.tobytes()
            for field in ("v2f_assignment", "feature_mean", "feature_track_ids"):
                x, y = getattr(ea, field), getattr(e, field)
                assert (x is None) == (y is None), field
                if x is not None:
                    np.testing.assert_array_equal(x, y, err_msg=field)


def sensor_frame(frame, rng: np.random.Generator):
    """``frame`` with its V2F rows as range-bearing detections (``[perception] detections = "range_bearing"``):
    the coupler's geometry from the truth (the true heading: the velocity's direction here), noise from
    ``rng``, and NaN net-frame rows."""
    from dataclasses import replace

    from coloc.core.detections import SensorDetections
    from couplers.sensing.sensor_frame import sensor_frame_rows

    tr = frame.truth
    owner = np.asarray(frame.v2f_owner, dtype=np.int64)
    o = owner.size
    heading = np.arctan2(tr.x_true[:, 3], tr.x_true[:, 2])[owner]
    real = tr.v2f_feature >= 0
    rel = np.array(frame.v2f_z, dtype=float, copy=True)  # clutter rows: their drawn points
    rel[real] = tr.features_true[tr.v2f_feature[real]] - tr.x_true[owner[real]]
    mount, yaw = np.full(o, 1.0), np.zeros(o)
    sig = (0.1, np.deg2rad(0.3), 0.028)
    r, b, rdot = sensor_frame_rows(rel, heading, mount, yaw, rng.standard_normal((o, 3)), *sig)
    det = SensorDetections(range=r, bearing=b, range_rate=rdot, mount_x=mount, yaw=yaw, sigma_range=np.full(o, sig[0]),
                           sigma_bearing=np.full(o, sig[1]), sigma_range_rate=np.full(o, sig[2]))
    return replace(frame, v2f_sensor=det, v2f_z=np.full_like(frame.v2f_z, np.nan),
                   v2f_R=np.full_like(frame.v2f_R, np.nan))


@pytest.mark.parametrize("name", RUNNABLE)
def test_truth_blind_with_sensor_frame_detections(name):
    """Range-bearing detections: every method converts them with its own heading (never the truth's), so
    scrambled or absent truth (true heading included) gives the same bytes; the output is valid."""
    rng = np.random.default_rng(6)
    a, b, c = build(name), build(name), build(name)
    for f in frames_for(name):
        if _method(name).infrastructure and f.truth.x_true.shape[0] == 0:
            continue
        f = sensor_frame(f, rng)
        assoc = f.truth.v2f_feature.copy()
        ea = step(name, a, f, assoc)
        assert_valid(ea, f)
        for e in (step(name, b, scrambled(f, rng), assoc), step(name, c, f.without_truth(), assoc)):
            assert ea.mean.tobytes() == e.mean.tobytes() and ea.cov.tobytes() == e.cov.tobytes()


def _enter_from_fix(frame, k: int, first: bool):
    """The frame with vehicle row ``k`` absent (``first`` False) or entering now from its receiver's fix
    (``first``: ``start = "gnss_fix"`` as the SUMO coupler makes it: prior = the step's fix,
    ``prior_has_fix``), with no V2F row and no radar detection of it, so its first belief has nothing
    but that fix."""
    n = frame.n_vehicles
    if not first:
        return select_vehicles(frame, np.delete(np.arange(n), k))
    ent = frame.entered.copy()
    ent[k] = True
    f = select_vehicles(frame, np.arange(n), entered=ent)
    f = replace(f, prior_z=np.where(ent[:, None], f.gnss_z, np.nan),
                prior_R=np.where(ent[:, None, None], f.gnss_R, np.nan), prior_has_fix=ent.copy())
    keep = np.flatnonzero(f.v2f_owner != k)
    truth = replace(f.truth, v2f_feature=f.truth.v2f_feature[keep])
    f = replace(f, v2f_z=f.v2f_z[keep], v2f_owner=f.v2f_owner[keep], v2f_R=f.v2f_R[keep], truth=truth)
    if f.infra is not None:
        seen = np.flatnonzero(f.truth.radar_vehicle != k)
        f = replace(f, infra=replace(f.infra, radar_z=f.infra.radar_z[seen], radar_owner=f.infra.radar_owner[seen]),
                    truth=replace(f.truth, radar_vehicle=f.truth.radar_vehicle[seen]))
    return f


@pytest.mark.parametrize("name", [n for n in RUNNABLE
                                  if n not in ("joint_oracle+world", "joint_oracle+heading",
                                               "joint_oracle+heading+gate", "joint_oracle+fix")])
def test_first_belief_is_the_receiver_fix(name):
    """The entry protocol (start = "gnss_fix"): a vehicle whose prior is its receiver's fix of the step has,
    as its belief written at that step, the fix and the covariance the receiver reports (position part),
    not that fix applied twice (covariance halved), and nothing of its truth. Particle methods: within
    their Monte Carlo error (300 particles). Not ``joint_oracle+world``: told that receivers share part of
    their error, the oracle corrects a first fix by what the other vehicles' fixes say of that part (its
    entry protocol is checked by the white ``joint_oracle`` case)."""
    frames = frames_for(name)
    k, s = 1, 3
    if _method(name).infrastructure:  # a vehicle inside the RSU's range at its entry step
        s = next(j for j in range(2, len(frames)) if frames[j].infra.v2i[:, k].nnz)
    est = build(name)
    for j, f in enumerate(frames[: s + 1]):
        f = _enter_from_fix(f, k, j == s)
        out = step(name, est, f)
    z, r = f.gnss_z[k, :2], f.gnss_R[k, :2, :2]
    assert np.abs(z - f.truth.x_true[k, :2]).max() > 0.5  # the fix is not the truth
    # The PF under [fusion]: its vehicles are the split-CI filters' (coloc.methods.pf_fusion), exact.
    if (name.startswith("icp_da_pf") or name.startswith("icp_known_da_pf") or name == "rsu_bp") and "+fusion" not in name:
        j_eff = 60 if name == "rsu_bp" else 300
        assert np.all(np.abs(out.mean[k, :2] - z) < 4.5 * np.sqrt(np.diag(r) / j_eff))
        ratio = np.diag(out.cov[k, :2, :2]) / np.diag(r)
        assert np.all((ratio > 0.6) & (ratio < 1.4)), ratio  # twice the fix would give 0.5
    else:
        np.testing.assert_allclose(out.mean[k, :2], z, rtol=0, atol=1e-9)
        np.testing.assert_allclose(out.cov[k, :2, :2], r, rtol=1e-9, atol=1e-9)


# --- the satellite receivers' channel for joint_oracle (Frame.oracle_gnss) ------------------------------------------

ORACLE_SATELLITES = OracleWorld(gnss="satellites", sv_count=6, nlos_d_mean_m=16.4, nlos_d_std_m=3.8,
                                nlos_rate_share=0.1)


def _with_channel(frames, rng, s=6):
    """The frames with a random :class:`coloc.core.frame.OracleGnss` of ``s`` satellites."""
    from coloc.core.frame import OracleGnss

    out = []
    for f in frames:
        n = f.n_vehicles
        used = rng.random((n, s)) < 0.9
        out.append(replace(f, oracle_gnss=OracleGnss(
            gain=rng.normal(0, 0.5, (n, 2, s)) * used[:, None], used=used, reflected=used & (rng.random((n, s)) < 0.3),
            elevation=rng.uniform(0.2, 1.4, s), fix=rng.random(n) < 0.9,
            velocity_gain=rng.normal(0, 0.5, (n, 2, s)) * used[:, None], velocity_used=used,
            velocity_solved=rng.random(n) < 0.9)))
    return out


@pytest.mark.parametrize("name", RUNNABLE)
def test_oracle_channel_is_read_by_the_oracle_alone(name):
    """Every estimator but joint_oracle in the satellite world gives the same bytes with or without the oracle's
    channel (it is the structure of the simulated receivers' errors, which no other estimator is told)."""
    frames = frames_for(name)
    told = _with_channel(frames, np.random.default_rng(2))
    a, b = build(name), build(name)
    for f, g in zip(frames, told):
        ea, eb = step(name, a, f), step(name, b, g)
        assert ea.mean.tobytes() == eb.mean.tobytes() and ea.cov.tobytes() == eb.cov.tobytes()


def test_satellite_oracle_reads_its_channel_and_no_truth():
    """joint_oracle in the satellite world: scrambled or absent truth, the same bytes; its channel changes its
    output (so the test above could fail)."""
    frames = _with_channel(frames_for("joint_oracle"), np.random.default_rng(4))

    def oracle():
        return build_method("joint_oracle", MethodParams(motion=ROAD_MOTION, icp=IcpParams(motion=ROAD_MOTION),
                                                         lc=LcParams(), pf=PfParams(), oracle_world=ORACLE_SATELLITES))

    rng = np.random.default_rng(5)
    a, b, c, d = oracle(), oracle(), oracle(), oracle()
    differs = False
    for f in frames:
        assoc = f.truth.v2f_feature.copy()
        ea = step("joint_oracle", a, f, assoc)
        assert_valid(ea, f)
        for e in (step("joint_oracle", b, scrambled(f, rng), assoc), step("joint_oracle", c, f.without_truth(), assoc)):
            assert ea.mean.tobytes() == e.mean.tobytes() and ea.cov.tobytes() == e.cov.tobytes()
        ed = step("joint_oracle", d, replace(f, oracle_gnss=None), assoc)
        differs |= ea.mean.tobytes() != ed.mean.tobytes()
    assert differs
