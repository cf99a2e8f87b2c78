"""What ``joint_oracle`` is told of the world: the one estimator that reads the world's tables.

:func:`oracle_world` copies ``[gnss_error]`` (the GNSS error structure and its parameters) and
``[inertial]`` into :class:`coloc.methods.joint_oracle.OracleWorld` (``coloc`` does not import
``couplers``). Every other estimator keeps to its own tables (docs: DESIGN "Two models, never one").
"""

from __future__ import annotations

import gzip
import math
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

from coloc.methods.registry import JOINT_ORACLE
from couplers.errors import InputError


#: [oracle] gnss_channel: what the oracle sees of the receivers in the satellite world
GNSS_CHANNELS = ("receiver", "fix")


@dataclass(frozen=True)
class OracleSection:
    """[oracle], optional: the oracle's own settings. ``gnss_channel`` (``[gnss_error] model = "satellites"``):
    "receiver" (each receiver's WLS gain, satellites and reflections, ``Frame.oracle_gnss``) or "fix" (the fixes
    and their reports only, as every method; told the world's fix-level error structure, :func:`fix_world`)."""

    gnss_channel: str = "receiver"


def validate_oracle(cfg) -> None:
    """A known ``gnss_channel``; "fix" only in the satellite world."""
    jo = getattr(cfg, "oracle", None)
    if jo is None:
        return
    if jo.gnss_channel not in GNSS_CHANNELS:
        raise InputError(cfg.path, "oracle.gnss_channel",
                         f"unknown value {jo.gnss_channel!r} (available: {', '.join(GNSS_CHANNELS)})")
    ge = cfg.gnss_error
    if jo.gnss_channel == "fix" and (ge is None or ge.model != "satellites"):
        raise InputError(cfg.path, "oracle.gnss_channel",
                         '"fix" needs [gnss_error] model = "satellites" (the other worlds are told at fix level '
                         'already)')


def _fix_channel(cfg) -> bool:
    jo = getattr(cfg, "oracle", None)
    return jo is not None and jo.gnss_channel == "fix"


def oracle_world(cfg):
    """The oracle's world of a config, an :class:`OracleWorld` (None when ``joint_oracle`` is not among
    ``run.methods``: the oracle's module is imported only for a run that has it)."""
    if JOINT_ORACLE.name not in cfg.run.methods:
        return None
    from coloc.methods.joint_oracle import GNSS_WORLDS, OracleWorld

    imu = {}
    if getattr(cfg, "inertial", None) is not None:
        i = cfg.inertial
        imu = dict(accel_turn_on_sigma=i.accel_turn_on_sigma, accel_bias_sigma=i.accel_bias_sigma,
                   accel_bias_tau_s=i.accel_bias_tau_s, accel_noise_density=i.accel_noise_density,
                   gyro_turn_on_sigma=i.gyro_turn_on_sigma, gyro_bias_sigma=i.gyro_bias_sigma,
                   gyro_bias_tau_s=i.gyro_bias_tau_s, gyro_noise_density=i.gyro_noise_density)
    imu["front_lever_m"] = front_lever(cfg)
    ge = cfg.gnss_error
    if ge is None:
        return OracleWorld(**imu)
    if ge.model == "satellites" and _fix_channel(cfg):
        return OracleWorld(**imu, **fix_world(cfg))
    if ge.model == "satellites":
        return OracleWorld(**imu, **satellite_world(cfg))
    models = tuple(m for m in GNSS_WORLDS[1:] if m != "fix")  # "fix": the satellite world told at fix level
    if ge.model not in models:
        raise InputError(cfg.path, "gnss_error.model",
                         f"joint_oracle knows the models {', '.join(models)} only, got {ge.model!r}")
    field = ge.model == "field"
    omega = None
    if field and ge.field_share > 0:
        # the world's draw of the field's frequencies (the field's structure; its values stay unknown states)
        from couplers.sensing.gnss_error import GNSS_ERROR_STREAM_TAG, exponential_kernel_frequencies
        from couplers.sensing.perception import effect_rng

        om = exponential_kernel_frequencies(effect_rng(cfg.run.seed, GNSS_ERROR_STREAM_TAG, "field_features"),
                                            ge.field_features, ge.field_corr_length_m)
        omega = tuple(map(tuple, om.tolist()))
    rates = any(r > 0 for r in ge.nlos_rate_per_min) or ge.nlos_rate_per_density_per_min > 0
    return OracleWorld(
        gnss=ge.model, tau_s=ge.tau_s,
        common_share=ge.common_share if field else 0.0, common_tau_s=ge.common_tau_s,
        field_share=ge.field_share if field else 0.0, field_corr_length_m=ge.field_corr_length_m,
        field_tau_s=ge.field_tau_s, local_corr_length_m=ge.local_corr_length_m if field else math.inf,
        nlos=bool(rates and ge.nlos_bias_mean_m > 0), field_omega=omega, **imu,
    )


#: A reflected signal's extra path is 2 cos(el) D (couplers/sensing/gnss_satellites.py, "reflect"): D = d cos(dphi),
#: the reflecting facade's perpendicular distance times the cosine of the satellite azimuth's angle to its normal. The
#: oracle is told D's mean and std, measured over the reflected signals used in the fixes of the realistic TLR preset,
#: tuning seed 101, 0-660 s (docs/validation/oracle.md, "Satellite world"), not a realisation.
NLOS_D_MEAN_M = 16.4  # 166 801 reflected signals: mean 16.4 m, median 15.5 m, p95 24.3 m
#: D's spread over those signals is 3.8 m, but a signal's D is the same over many steps (one facade, one satellite)
#: while the oracle takes it as white per step: the std it is told is twice the spread, chosen on tuning seed 101
#: (600-660 s: zone C mean NEES 2.10 against 4.21 with 3.8 m; docs/validation/oracle.md, "Sixth round").
NLOS_D_STD_M = 7.6
#: The path rate of a reflected signal, -2 cos(el) cos(dphi) (n . v) (gnss_reflect.py), taken as zero-mean with std
#: 2 cos(el) |v| times this share (the same measurement).
NLOS_RATE_SHARE = 0.10  # RMS of -cos(dphi) (n . v) / |v| above 2 m/s: 0.097, mean 0.002


def satellite_world(cfg) -> dict:
    """The OracleWorld keys of ``[gnss_error] model = "satellites"``: the constellation's size, the satellites'
    common errors (correlation time, sigmas), the receiver's own errors, the Doppler noise, and the structure of a
    reflected signal's extra path (:data:`NLOS_D_MEAN_M`)."""
    from couplers.sensing.gnss_sky import Sky

    ge = cfg.gnss_error
    reflect = ge.nlos == "reflect"
    return dict(gnss="satellites", sv_count=Sky.build().size, sv_tau_s=ge.sv_tau_s,
                sv_clock_orbit_m=ge.sv_clock_orbit_m, iono_vertical_m=ge.iono_vertical_m,
                tropo_zenith_m=ge.tropo_zenith_m, code_noise_a_m=ge.code_noise_a_m, code_noise_b_m=ge.code_noise_b_m,
                multipath_m=ge.multipath_m, multipath_corr_length_m=ge.multipath_corr_length_m,
                doppler_noise_mps=ge.doppler_noise_mps,
                nlos_d_mean_m=NLOS_D_MEAN_M if reflect else 0.0, nlos_d_std_m=NLOS_D_STD_M if reflect else 0.0,
                nlos_rate_share=NLOS_RATE_SHARE if reflect else 0.0)


#: The fix-level world ([oracle] gnss_channel = "fix"), measured with tools/fix_error_stats.py on the realistic
#: TLR preset's tuning seed 101, 600-900 s (docs/validation/oracle.md, "Seventh round"), unless said otherwise.
#: The common error c_t (per step, the mean raw fix error over the zone-A vehicles): its per-axis RMS over the
#: thirty tuning seeds 101-130, 600-900 s (docs/validation/consistency.md, "The receiver's report calibrated");
#: its correlation time is the satellites' (sv_tau_s, copied from [gnss_error]: seed 101's c_t keeps 0.94 of its
#: correlation over 60 s and 0.91 over 150 s, exp(-150 / 1800) = 0.92).
FIX_COMMON_SIGMA_M = 1.11
#: The local error (the fix's error less c_t) against the report's per-axis std: 0.53-0.65 of it up to 2 m (the
#: report includes the common part), 2.0-2.1 times it from 2 to 6 m, 1.2-1.4 above (reflected signals absorbed).
FIX_LOCAL_ABOVE_M = 2.0
FIX_LOCAL_BELOW_SCALE = 0.6
FIX_LOCAL_SCALE = 2.0
FIX_LOCAL_COMMON_M2 = 0.0
FIX_LOCAL_FLOOR_M = 0.3
#: the local error's correlation between fixes of one vehicle: 0.83 at the same place (0.76 after 30 s standing),
#: 0.67 after 5-10 m, 0.53 after 10-20 m, 0.33 after 20-50 m: a white share 0.17 and 0.83 exp(-d / 35 m), the
#: standing decay exp(-t / 340 s)
FIX_LOCAL_WHITE_SHARE = 0.17
FIX_LOCAL_CORR_LENGTH_M = 35.0
FIX_LOCAL_TAU_S = 300.0
#: the velocity's mean NEES against the reported block: 1.8 up to a reported position std of 3 m, 3.4-4.9 above
#: (1.8x the variance: 1.35^2); its correlation between steps of a moving vehicle is below 0.06 (white)
FIX_VELOCITY_SCALE = 1.35


def fix_world(cfg) -> dict:
    """The OracleWorld keys of ``[oracle] gnss_channel = "fix"`` in the satellite world: the fix-level error
    structure (:data:`FIX_COMMON_SIGMA_M` ..), the common error's correlation time the satellites' (sv_tau_s), the
    NLOS gate on (the world reflects signals)."""
    ge = cfg.gnss_error
    return dict(gnss="fix", common_tau_s=ge.sv_tau_s, fix_common_sigma_m=FIX_COMMON_SIGMA_M,
                fix_local_above_m=FIX_LOCAL_ABOVE_M, fix_local_scale=FIX_LOCAL_SCALE,
                fix_local_below_scale=FIX_LOCAL_BELOW_SCALE, fix_noise_share=FIX_LOCAL_WHITE_SHARE,
                fix_local_common_m2=FIX_LOCAL_COMMON_M2, fix_local_floor_m=FIX_LOCAL_FLOOR_M,
                local_corr_length_m=FIX_LOCAL_CORR_LENGTH_M, tau_s=FIX_LOCAL_TAU_S,
                fix_velocity_scale=FIX_VELOCITY_SCALE, nlos=ge.nlos in ("delay", "reflect"))


def oracle_sensors(cfg):
    """``cfg.sensors`` with ``[gnss_error] oracle_channel`` on for a run whose methods include ``joint_oracle`` under
    ``model = "satellites"`` (the frames then carry :class:`coloc.core.frame.OracleGnss`, what the oracle is told of
    the receivers); else ``cfg.sensors`` unchanged (frames byte-identical)."""
    ge = getattr(cfg.sensors, "gnss_error", None)
    if ge is None or ge.model != "satellites" or JOINT_ORACLE.name not in cfg.run.methods or ge.oracle_channel:
        return cfg.sensors
    if _fix_channel(cfg):  # the fix-level oracle sees what every method sees: frames byte-identical
        return cfg.sensors
    from dataclasses import replace

    return replace(cfg.sensors, gnss_error=replace(ge, oracle_channel=True))


#: SUMO's default vehicle length (m), vClass passenger (SUMO documentation, "Vehicle Type Parameter Defaults")
SUMO_DEFAULT_LENGTH_M = 5.0


def _route_vtype_lengths(path: Path) -> list[float]:
    """Lengths of the vehicle types (not pedestrians) declared in a SUMO route file before its first vehicle,
    trip, flow or person (where route files declare them)."""
    opener = gzip.open if path.suffix == ".gz" else open
    out = []
    with opener(path, "rb") as fh:
        for _, el in ET.iterparse(fh, events=("end",)):
            if el.tag == "vType" and el.get("vClass", "passenger") != "pedestrian":
                out.append(float(el.get("length", SUMO_DEFAULT_LENGTH_M)))
            elif el.tag in ("vehicle", "trip", "flow", "person", "personFlow"):
                break
    return out


def front_lever(cfg) -> float:
    """What the oracle is told of the world's kinematics (OracleWorld.front_lever_m): SUMO reports the front
    bumper's position and the body axis as the heading, so a turning vehicle's bumper moves sideways at about
    half its length times the yaw rate (docs/validation/oracle.md, "Kinematics of the world"). Half the mean
    length of the net folder's vehicle types (SUMO's default length without one); 0 for a scenario without
    SUMO (its trajectories are model (1)) and for a world that reports the vehicles' centres ([scenario]
    reference_point = "centre": no slip to model)."""
    if getattr(cfg.scenario, "kind", "sumo") != "sumo" or not cfg.scenario.net_dir:
        return 0.0
    if getattr(cfg.scenario, "reference_point", "front_bumper") == "centre":
        return 0.0
    from couplers.net.folder import load_net_folder

    lengths = []
    for f in load_net_folder(cfg.scenario.net_dir).route_files:
        lengths += _route_vtype_lengths(Path(f))
    return 0.5 * (sum(lengths) / len(lengths) if lengths else SUMO_DEFAULT_LENGTH_M)
