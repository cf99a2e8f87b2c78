"""The fused numba path of the Gaussian ICP family (coloc/kernels/icp_fused.py) against the batched
numpy reference (``icp_fused.FUSED = False``): byte-identical estimates on real SUMO frames (the
arterial TLR, the realistic preset with clutter / existence / field of view, the lossy V2X config),
the kernels on their own against their numpy twins, and SPD covariances."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import coloc.inference.bpa as bpa
from coloc.inference.feature_store import FeatureStore
from coloc.inference.params import IcpParams
from coloc.kernels import icp_fused
from coloc.methods.icp_da_lc import LcParams, association_beliefs, association_weights, pairs_from_beliefs
from coloc.methods.registry import METHODS

ROOT = Path(__file__).resolve().parents[2]
METHOD_NAMES = ("icp_known_da", "icp_da_lc")


def _frames(config: str, duration_s: float):
    from experiments.config import load_config
    from experiments.runner import frame_source

    cfg = load_config(ROOT / "experiments" / config, {"run.duration_s": duration_s, "run.methods": list(METHOD_NAMES)})
    with frame_source(cfg) as src:
        frames = [(f.without_truth(), f.truth.v2f_feature) for f in src.frames()]
    return cfg, frames


def _run(cfg, frames, fused: bool, monkeypatch) -> dict[str, list]:
    from experiments.runner import build_estimators

    monkeypatch.setattr(icp_fused, "FUSED", fused)
    out = {}
    for est in build_estimators(cfg):
        known = METHODS[est.name].known_association
        out[est.name] = [est.step_with_association(f, a) if known else est.step(f) for f, a in frames]
    return out


def _same_bytes(a, b) -> None:
    for name in METHOD_NAMES:
        assert len(a[name]) == len(b[name])
        for ea, eb in zip(a[name], b[name]):
            for field in ("mean", "cov", "feature_mean", "feature_cov", "feature_track_ids", "v2f_assignment"):
                x, y = getattr(ea, field), getattr(eb, field)
                assert x.shape == y.shape and x.tobytes() == y.tobytes(), (name, field)


def _spd(runs) -> None:
    for name in METHOD_NAMES:
        for est in runs[name]:
            for cov in (est.cov, est.feature_cov):
                if cov.size:
                    assert np.allclose(cov, np.swapaxes(cov, 1, 2), rtol=1e-9, atol=1e-12)
                    assert np.linalg.eigvalsh(cov).min() > 0


@pytest.mark.slow
@pytest.mark.parametrize("config,duration_s", [
    ("arterial_tlr.toml", 300.0),  # 400 steps of the paper's arterial
    ("arterial_tlr_realistic.toml", 150.0),  # FOV, P_D(distance), clutter, track existence, correlated GNSS
    ("arterial_v2x.toml", 150.0),  # consensus over the lossy channel within a round budget
])
def test_fused_estimates_are_byte_identical_to_the_numpy_reference(config, duration_s, monkeypatch):
    cfg, frames = _frames(config, duration_s)
    assert sum(f.v2f_z.shape[0] for f, _ in frames) > 0
    fused = _run(cfg, frames, True, monkeypatch)
    _same_bytes(fused, _run(cfg, frames, False, monkeypatch))
    _spd(fused)


def test_fused_estimates_on_a_short_arterial_run(monkeypatch):
    """The quick version of the test above (75 s of the arterial TLR)."""
    cfg, frames = _frames("arterial_tlr.toml", 75.0)
    fused = _run(cfg, frames, True, monkeypatch)
    _same_bytes(fused, _run(cfg, frames, False, monkeypatch))
    _spd(fused)


def _scene(seed: int, n_v: int = 12, n_t: int = 15, rows_per_v: int = 4):
    rng = np.random.default_rng(seed)
    v_mean = np.c_[rng.uniform(0, 150, (n_v, 2)), rng.normal(0, 5, (n_v, 2))]
    t_mean = np.c_[rng.uniform(0, 150, (n_t, 2)), rng.normal(0, 0.3, (n_t, 2))]

    def spd(k, scale):
        a = rng.normal(size=(k, 4, 4)) * scale
        return a @ np.swapaxes(a, 1, 2) + np.eye(4) * scale**2

    owner = np.sort(rng.integers(0, n_v, n_v * rows_per_v))
    rng.shuffle(owner)  # rows of a vehicle not contiguous
    truth = rng.integers(0, n_t, owner.size)
    z = t_mean[truth] - v_mean[owner] + rng.normal(0, 0.5, (owner.size, 4))
    return v_mean, spd(n_v, 1.0), t_mean, spd(n_t, 0.7), owner, z, spd(owner.size, 0.3)


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("lc", [LcParams(sensing_range_m=40.0), LcParams(sensing_range_m=40.0, eta_threshold=1.0),
                                LcParams(sensing_range_m=60.0, clutter_intensity=1e-3, pairing="paper")])
def test_association_kernels_equal_the_numpy_reference(seed, lc, monkeypatch):
    scene = _scene(seed)
    n_v, o = scene[0].shape[0], scene[4].size
    out = {}
    for fused in (False, True):
        monkeypatch.setattr(icp_fused, "FUSED", fused)
        pv, pt, pr, w = association_weights(*scene, lc)
        # eta(alpha = 0) per pair, equal over the rows of one (vehicle, track) combo (step 9)
        missed = 0.05 + 0.01 * ((pv * 7 + pt) % 5) if seed % 2 else None
        ab = association_beliefs(pv, pt, pr, w, n_v, o, lc, missed)
        out[fused] = (pv, pt, pr, w, ab, pairs_from_beliefs(ab, o, lc))
    (pv0, pt0, pr0, w0, ab0, pair0), (pv1, pt1, pr1, w1, ab1, pair1) = out[False], out[True]
    for x, y in [(pv0, pv1), (pt0, pt1), (pr0, pr1), (w0, w1)]:
        assert x.tobytes() == y.tobytes()
    assert (w0 > 0).any()
    for field in ("belief", "combo_vehicle", "combo_track", "combo_start", "combo_rows", "row_first", "rows", "row_new"):
        assert getattr(ab0, field).tobytes() == getattr(ab1, field).tobytes(), field
    for x, y in zip(pair0, pair1):
        assert x.tobytes() == y.tobytes()


def _store(seed: int) -> tuple[FeatureStore, np.random.Generator]:
    rng = np.random.default_rng(seed)
    ids = np.sort(rng.choice(40, 12, replace=False)).astype(np.int64)
    n_msg = 30
    a = rng.normal(size=(n_msg, 4, 4))
    cov = a @ np.swapaxes(a, 1, 2) + np.eye(4)
    f = rng.normal(size=(ids.size, 4, 4))
    folded = np.where(rng.random(ids.size)[:, None, None] < 0.5, 0.0, f @ np.swapaxes(f, 1, 2))
    store = FeatureStore(
        ids=ids, last_seen=rng.uniform(0, 10, ids.size), folded_lam=folded, folded_eta=rng.normal(size=(ids.size, 4)),
        msg_track=rng.choice(ids, n_msg), msg_vehicle=np.array([f"v{k}" for k in rng.integers(0, 8, n_msg)], dtype=object),
        msg_mean=rng.normal(size=(n_msg, 4)), msg_cov=cov, msg_time=rng.uniform(0, 10, n_msg),
        klass=rng.integers(0, 2, ids.size).astype(np.int8) if seed % 2 else None,
    )
    return store, rng


@pytest.mark.parametrize("seed", range(6))
def test_feature_store_kernels_equal_the_numpy_reference(seed, monkeypatch):
    params = IcpParams(message_memory_s=3.0, feature_drop_after_s=4.0)
    res = {}
    for fused in (False, True):
        monkeypatch.setattr(icp_fused, "FUSED", fused)
        store, rng = _store(seed)
        n_rows = 9
        row_feature = np.concatenate([rng.choice(store.ids, 6), [41, 45, 41]]).astype(np.int64)
        row_vehicle = np.array([f"v{k}" for k in rng.integers(0, 8, n_rows)], dtype=object)
        a = rng.normal(size=(n_rows, 4, 4))
        lam = a @ np.swapaxes(a, 1, 2) + np.eye(4)
        eta = rng.normal(size=(n_rows, 4))
        row_class = rng.integers(0, 2, n_rows).astype(np.int8) if seed % 3 == 0 else None
        prior = store.prior_information(np.unique(row_feature), row_feature, row_vehicle, params, row_class=row_class)
        info = store.information(params)
        rec = store.record(row_feature, row_vehicle, lam, eta, 10.0, params, row_class=row_class)
        res[fused] = (prior, info, rec, rec.information(params), rec.lookup(np.arange(-1, 50)),
                      rec.merge(rec.ids[-1:], rec.ids[:1]) if rec.size > 1 else rec)
    (p0, i0, r0, ri0, l0, m0), (p1, i1, r1, ri1, l1, m1) = res[False], res[True]
    for x, y in [*zip(p0, p1), *zip(i0, i1), *zip(ri0, ri1), (l0, l1)]:
        assert x.tobytes() == y.tobytes()
    for s0, s1 in [(r0, r1), (m0, m1)]:
        for field in ("ids", "last_seen", "folded_lam", "folded_eta", "msg_track", "msg_mean", "msg_cov", "msg_time"):
            assert getattr(s0, field).tobytes() == getattr(s1, field).tobytes(), field
        assert list(s0.msg_vehicle) == list(s1.msg_vehicle)
        assert (s0.klass is None) == (s1.klass is None)
        if s0.klass is not None:
            assert s0.klass.tobytes() == s1.klass.tobytes()
        assert s0._message_information[0].tobytes() == s1._message_information[0].tobytes()
        assert s0._message_information[1].tobytes() == s1._message_information[1].tobytes()


def test_own_message_kernel_is_off_by_default_and_within_rounding(monkeypatch):
    """OWN_MESSAGE_KERNEL (opt-in) differs from the LAPACK reference by rounding only."""
    assert bpa.OWN_MESSAGE_KERNEL is False
    cfg, frames = _frames("arterial_tlr.toml", 45.0)
    ref = _run(cfg, frames, True, monkeypatch)
    monkeypatch.setattr(bpa, "OWN_MESSAGE_KERNEL", True)
    alt = _run(cfg, frames, True, monkeypatch)
    for name in METHOD_NAMES:
        for ea, eb in zip(ref[name], alt[name]):
            assert np.abs(ea.mean - eb.mean).max(initial=0.0) < 1e-9
            if ea.feature_mean.shape == eb.feature_mean.shape:
                assert np.abs(ea.feature_mean - eb.feature_mean).max(initial=0.0) < 1e-9


def _spd_rows(rng, k, scale=1.0):
    a = rng.normal(size=(k, 4, 4)) * scale
    return 0.5 * ((a @ np.swapaxes(a, 1, 2) + np.eye(4)) + np.swapaxes(a @ np.swapaxes(a, 1, 2) + np.eye(4), 1, 2))


@pytest.mark.parametrize("seed", range(4))
def test_row_kernels_across_rows_are_byte_identical_to_the_row_by_row_kernels(seed):
    """coloc.kernels.bpa_rows (SIMD across rows) against coloc.kernels.icp (row by row), including
    rows whose S = Lambda + R^-1 is not positive definite (the Gauss-Jordan fallback) and zero
    (uniform) beliefs."""
    from coloc.kernels import bpa_rows, icp

    rng = np.random.default_rng(seed)
    n, o = 7, 40
    owner = rng.integers(0, n, o)
    own_lam0, in_lam, v_lam0 = _spd_rows(rng, n), _spd_rows(rng, n, 0.3), _spd_rows(rng, n)
    own_eta0, in_eta, v_eta0 = rng.normal(size=(n, 4)), rng.normal(size=(n, 4)), rng.normal(size=(n, 4))
    m_fv_lam, m_fv_eta = _spd_rows(rng, o, 0.2), rng.normal(size=(o, 4))
    z, r_inv = rng.normal(size=(o, 4)) * 10, _spd_rows(rng, o, 2.0)
    a = icp.vehicle_to_feature_kernel(owner, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z, r_inv)
    b = bpa_rows.vehicle_to_feature_rows(owner, own_lam0, own_eta0, in_lam, in_eta, m_fv_lam, m_fv_eta, z, r_inv)
    assert all(x.tobytes() == y.tobytes() for x, y in zip(a, b))
    ext_lam, ext_eta = _spd_rows(rng, o, 0.5), rng.normal(size=(o, 4))
    ext_lam[:3] = 0.0  # uniform beliefs: the zero message
    ext_lam[3:6] = -r_inv[3:6] - np.eye(4)  # S not PD: the general inverse
    prev = rng.normal(size=(n, 4))
    a = icp.feature_to_vehicle_kernel(owner, ext_lam, ext_eta, z, r_inv, v_lam0, v_eta0, prev)
    b = bpa_rows.feature_to_vehicle_rows(owner, ext_lam, ext_eta, z, r_inv, v_lam0, v_eta0, prev)
    assert all(np.asarray(x).tobytes() == np.asarray(y).tobytes() for x, y in zip(a, b))
    cov = _spd_rows(rng, o)
    cov[:2] = np.diag([1.0, -1.0, 2.0, 3.0])  # not PD: the general inverse
    mean = rng.normal(size=(o, 4))
    assert all(x.tobytes() == y.tobytes() for x, y in zip(icp.information_kernel(mean, cov),
                                                          bpa_rows.information_rows(mean, cov)))
    assert icp.inverse_spd_kernel(cov).tobytes() == bpa_rows.inverse_rows(cov).tobytes()
    q = _spd_rows(rng, o, 0.1)
    assert all(x.tobytes() == y.tobytes() for x, y in zip(icp.predict_no_input_kernel(mean, cov, q, 0.75),
                                                          bpa_rows.predict_no_input_rows(mean, cov, q, 0.75)))
