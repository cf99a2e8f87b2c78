"""What ``joint_oracle`` is told of the world: the one estimator that reads the world's tables.

:func:`oracle_world` copies ``[gnss_error]`` (the GNSS error structure and its parameters) and
``[inertial]`` into :class:`coloc.methods.joint_oracle.OracleWorld` (``coloc`` does not import
``couplers``). Every other estimator keeps to its own tables (docs: DESIGN "Two models, never one").
"""

from __future__ import annotations

import math

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
                   accel_bias_tau_s=i.accel_bias_tau_s, accel_noise_density=i.accel_noise_density)
    ge = cfg.gnss_error
    if ge is None:
        return OracleWorld(**imu)
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
