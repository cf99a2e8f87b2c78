"""What ``joint_oracle`` is told of the world: the one estimator that reads the world's tables.

:func:`oracle_world` copies ``[gnss_error]`` (the GNSS error structure and its parameters) and
``[inertial]`` into :class:`coloc.methods.joint_oracle.OracleWorld` (``coloc`` does not import
``couplers``). Every other estimator keeps to its own tables (docs: DESIGN "Two models, never one").
"""

from __future__ import annotations

import gzip
import math
import xml.etree.ElementTree as ET
from pathlib import Path

from coloc.methods.registry import JOINT_ORACLE
from couplers.errors import InputError


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
    if ge.model == "satellites":
        return OracleWorld(**imu, **satellite_world(cfg))
    if ge.model not in GNSS_WORLDS:
        raise InputError(cfg.path, "gnss_error.model",
                         f"joint_oracle knows the models {', '.join(GNSS_WORLDS[1:])} only, got {ge.model!r}")
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


def oracle_sensors(cfg):
    """``cfg.sensors`` with ``[gnss_error] oracle_channel`` on for a run whose methods include ``joint_oracle`` under
    ``model = "satellites"`` (the frames then carry :class:`coloc.core.frame.OracleGnss`, what the oracle is told of
    the receivers); else ``cfg.sensors`` unchanged (frames byte-identical)."""
    ge = getattr(cfg.sensors, "gnss_error", None)
    if ge is None or ge.model != "satellites" or JOINT_ORACLE.name not in cfg.run.methods or ge.oracle_channel:
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
