"""The "field" GNSS error model (couplers.sensing.gnss_error.FieldErrorProcess) and the "gnss_fix" start:
shared errors, the correlation of two receivers' errors against their separation, each vehicle's marginal
variance, NLOS episodes per cell, and entering vehicles whose prior is their own receiver's fix."""

import math

import numpy as np
import pytest

from couplers.sensing.gnss_error import (
    FieldErrorProcess,
    GnssErrorParams,
    GnssErrorProcess,
    expected_correlation,
    exponential_kernel_frequencies,
    gnss_error_process,
)
from couplers.sensing.sensors import SensorNoise, SensorParams, synthesize_frame

NO_NLOS = dict(nlos_zones=(), nlos_rate_per_min=())
SP = {"A": 3.0, "C": 15.0}


def _ids(n):
    return np.array([f"v{i}" for i in range(n)], dtype=object)


def test_model_selects_the_process_and_per_vehicle_is_the_default():
    assert GnssErrorParams().model == "per_vehicle"
    assert type(gnss_error_process(GnssErrorParams(), 1, 0.75)) is GnssErrorProcess
    assert type(gnss_error_process(GnssErrorParams(model="field"), 1, 0.75)) is FieldErrorProcess


def test_common_share_one_gives_every_vehicle_of_a_zone_the_same_error():
    n = 30
    p = GnssErrorParams(model="field", common_share=1.0, **NO_NLOS)
    proc = FieldErrorProcess(p, 3, 0.75)
    rng = np.random.default_rng(0)
    zone = np.array(["A", "C"] * (n // 2), dtype=object)
    sp = np.array([SP[z] for z in zone])
    xy = rng.uniform(0, 2000, (n, 2))
    entered = np.ones(n, bool)
    for k in range(40):
        xy = xy + rng.normal(0, 8, (n, 2))
        e = proc.step(k * 0.75, _ids(n), entered, rng.standard_normal((n, 2)), sp, zone, xy)
        entered[:] = False
        for z in SP:
            sel = zone == z
            assert np.ptp(e[sel], axis=0).max() == 0.0
        assert np.allclose(e[zone == "C"][0], e[zone == "A"][0] * SP["C"] / SP["A"], rtol=1e-12)
        assert np.abs(e).max() > 0


def test_exponential_kernel_frequencies_give_the_exponential_correlation():
    omega = exponential_kernel_frequencies(np.random.default_rng(1), 200_000, 50.0)
    for d in (10.0, 50.0, 150.0):
        # mean of cos over 2e5 features: standard error < 1 / sqrt(2 * 2e5) ~ 0.0016
        assert np.cos(omega[:, 0] * d).mean() == pytest.approx(math.exp(-d / 50.0), abs=0.01)


def _ensemble(params, seeds, steps, separations, dt=0.75, speed=10.0):
    """Errors at the last of ``steps`` steps of one process per seed: vehicles in pairs (groups 100 km apart,
    so that only the common part links the groups), each pair ``separations[g]`` apart, all moving together
    along +x (the separation stays). Zone A for the first member of each pair, C for the second when
    ``mixed``... here one zone per pair: A for even groups, C for odd ones. Returns (seeds, 2 G, 2)."""
    g = len(separations)
    base = np.stack([np.arange(g) * 1e5, np.zeros(g)], axis=1)
    offset = np.stack([np.asarray(separations, dtype=float) / math.sqrt(2)] * 2, axis=1)
    xy0 = np.empty((2 * g, 2))
    xy0[0::2], xy0[1::2] = base, base + offset
    zone = np.array([("A" if i % 2 == 0 else "C") for i in range(g) for _ in (0, 1)], dtype=object)
    sp = np.array([SP[z] for z in zone])
    out = np.empty((len(seeds), 2 * g, 2))
    for s, seed in enumerate(seeds):
        proc = FieldErrorProcess(params, seed, dt)
        rng = np.random.default_rng(10_000 + seed)
        entered = np.ones(2 * g, bool)
        for k in range(steps):
            xy = xy0 + [speed * dt * k, 0.0]
            e = proc.step(k * dt, _ids(2 * g), entered, rng.standard_normal((2 * g, 2)), sp, zone, xy)
            entered[:] = False
        out[s] = e
    return out, sp


def _pair_correlation(a: np.ndarray, b: np.ndarray) -> float:
    """Pearson correlation of the pairs taken in both orders (over an ensemble of seeds, whose mean is ~0)."""
    a, b = a.ravel(), b.ravel()
    m = (a.sum() + b.sum()) / (2 * a.size)
    var = (a @ a + b @ b) / (2 * a.size) - m * m
    return float((a @ b / a.size - m * m) / var)


def test_correlation_against_separation_and_marginal_variance_per_zone():
    """One stationary sample per seed (the processes start stationary and stay so): 600 seeds, 12 steps of
    movement. Correlation per separation (both axes, both zones scaled to unit variance): 1200 samples per
    separation, standard error (1 - rho^2) / sqrt(1200) < 0.029; tolerance 0.1 (3.5 standard errors).
    Variance per zone: 600 seeds x 2 axes x 2 vehicles x 6 pairs, but the common part links all vehicles of
    one seed: counting one sample per seed and axis (1200), the relative standard error of a variance is
    sqrt(2 / 1200) = 0.041; tolerance 15 %."""
    p = GnssErrorParams(model="field", common_share=0.3, field_share=0.6, field_corr_length_m=50.0, **NO_NLOS)
    seps = [5.0, 25.0, 50.0, 100.0, 400.0, 2000.0]
    e, sp = _ensemble(p, range(600), 12, seps)
    u = e / sp[None, :, None]
    for g, d in enumerate(seps):
        rho = _pair_correlation(u[:, 2 * g], u[:, 2 * g + 1])
        assert rho == pytest.approx(float(expected_correlation(p, d)), abs=0.1), (d, rho)
    # far apart the receivers share the common part only; near, the field too
    assert float(expected_correlation(p, 2000.0)) == pytest.approx(0.3, abs=1e-9)
    for z, sigma in SP.items():
        sel = np.array([i % 2 == 0 for i in range(len(seps)) for _ in (0, 1)]) == (z == "A")
        var = float((e[:, sel] ** 2).mean())
        assert var == pytest.approx(sigma ** 2, rel=0.15), (z, var)


def test_own_part_is_kept_by_a_standing_vehicle_and_lost_over_distance():
    """common_share 0, field_share 0: the error is the receiver's own part alone. Standing still, the
    correlation per step is exp(-Ts / tau_s); moving d per step, exp(-d / L - Ts / tau_s)."""
    p = GnssErrorParams(model="field", common_share=0.0, field_share=0.0, tau_s=30.0, local_corr_length_m=20.0,
                        **NO_NLOS)
    n, steps, dt = 400, 200, 0.75
    for speed in (0.0, 10.0):
        proc = FieldErrorProcess(p, 7, dt)
        rng = np.random.default_rng(8)
        xy0 = np.stack([np.arange(n) * 1e4, np.zeros(n)], axis=1)
        e = np.empty((steps, n, 2))
        entered = np.ones(n, bool)
        for k in range(steps):
            e[k] = proc.step(k * dt, _ids(n), entered, rng.standard_normal((n, 2)), np.ones(n), np.full(n, "A"),
                             xy0 + [speed * dt * k, 0.0])
            entered[:] = False
        rho = float((e[1:] * e[:-1]).mean() / (e * e).mean())
        want = math.exp(-speed * dt / 20.0 - dt / 30.0)
        # 400 x 2 x 199 lag pairs, correlated over ~ (1 + a) / (1 - a) steps: > 1500 effective; se < 0.03
        assert rho == pytest.approx(want, abs=0.06), (speed, rho, want)


def test_nlos_episodes_belong_to_cells():
    """Every vehicle in a cell shares its episode's bias; vehicles of other cells do not."""
    p = GnssErrorParams(model="field", common_share=0.0, field_share=0.0, nlos_zones=("C",),
                        nlos_rate_per_min=(30.0,), nlos_mean_duration_s=20.0, nlos_bias_mean_m=10.0,
                        nlos_cell_m=50.0)
    proc = FieldErrorProcess(p, 2, 0.75)
    # three vehicles in cell (0, 0), three in cell (10, 0)
    xy = np.array([[5.0, 5.0], [20.0, 30.0], [45.0, 10.0], [505.0, 5.0], [520.0, 30.0], [545.0, 10.0]])
    n = len(xy)
    seen_active = False
    entered = np.ones(n, bool)
    for k in range(200):
        proc.step(k * 0.75, _ids(n), entered, np.zeros((n, 2)), np.ones(n), np.full(n, "C", dtype=object), xy)
        entered[:] = False
        b = proc._bias_now
        assert np.array_equal(b[0], b[1]) and np.array_equal(b[1], b[2])
        assert np.array_equal(b[3], b[4]) and np.array_equal(b[4], b[5])
        if proc.in_episode[0] and proc.in_episode[3]:
            seen_active = True
            assert not np.array_equal(b[0], b[3])
    assert seen_active
    assert len(proc._cells) == 2


@pytest.mark.filterwarnings("ignore:invalid value encountered in cast:RuntimeWarning")  # the NaN position's key
def test_cell_lookup_array_and_field_reuse_change_nothing():
    """The NLOS cells' lookup array and the field's reuse of a standing vehicle's cosines (speed only) change
    nothing: with both disabled (every vehicle through the dict, every phase's cosine computed: the reference)
    the rows, cells and errors are the same bit for bit; the vehicles roam far (the array grows), half of them
    stand still every other step, one jumps 1e13 m off the net (beyond the array: the dict answers), one is NaN."""
    p = GnssErrorParams(model="field", nlos_zones=("B", "C"), nlos_rate_per_min=(6.0, 30.0), nlos_cell_m=50.0)
    n, runs = 20, []
    for reference in (False, True):
        proc = FieldErrorProcess(p, 5, 0.75)
        if reference:
            proc._lut_rows = lambda keys: np.full(len(keys), -1, dtype=np.int64)
            proc.field_at = lambda xy, idx=None, proc=proc: FieldErrorProcess.field_at(proc, xy)
        rng = np.random.default_rng(9)
        zone = np.array(["A", "B", "C", "C"] * (n // 4), dtype=object)
        xy = rng.uniform(-300, 300, (n, 2))
        out = []
        for k in range(120):
            move = rng.normal(0, 40, (n, 2))
            if k % 2:
                move[: n // 2] = 0.0
            xy = xy + move
            step_xy = xy.copy()
            if k == 60:
                step_xy[0] = (1e13, -1e13)
            if k == 70:
                step_xy[1] = np.nan
            e = proc.step(k * 0.75, _ids(n), np.full(n, k == 0), rng.standard_normal((n, 2)), np.full(n, 8.0),
                          zone, step_xy)
            out.append(np.concatenate([e.ravel(), proc._bias_now.ravel()]))
        runs.append((np.stack(out), dict(proc._cells), proc._cell_p.copy()))
        if not reference:
            assert proc._lut.size > 0 and len(proc._cells) > 100
    assert runs[0][0].tobytes() == runs[1][0].tobytes()
    assert runs[0][1] == runs[1][1]
    assert runs[0][2].tobytes() == runs[1][2].tobytes()


def test_same_seed_same_errors_and_streams_per_effect():
    p = GnssErrorParams(model="field")
    n = 12
    xy = np.random.default_rng(0).uniform(0, 500, (n, 2))
    runs = []
    for _ in range(2):
        proc = FieldErrorProcess(p, 11, 0.75)
        rng = np.random.default_rng(4)
        zone = np.array(["B", "C"] * (n // 2), dtype=object)
        runs.append(np.stack([proc.step(k * 0.75, _ids(n), np.full(n, k == 0), rng.standard_normal((n, 2)),
                                        np.full(n, 8.0), zone, xy + k) for k in range(30)]))
    assert runs[0].tobytes() == runs[1].tobytes()


@pytest.mark.parametrize("model", ["per_vehicle", "field"])
def test_gnss_fix_prior_is_the_receiver_fix(model):
    """start = "gnss_fix": an entering vehicle's prior mean and covariance are the frame's GNSS row of that
    vehicle (correlated error included), whatever its truth; others carry no prior."""
    n, dt = 8, 0.75
    rng = np.random.default_rng(3)
    params = SensorParams(gnss_error=GnssErrorParams(model=model))
    proc = gnss_error_process(params.gnss_error, 1, dt)
    noise = SensorNoise(1)
    entered = np.array([True, False] * (n // 2))
    x_true = np.hstack([rng.uniform(0, 300, (n, 2)), rng.normal(0, 5, (n, 2))])
    frames = []
    for start in ("gnss_fix", "fast_start"):
        proc = gnss_error_process(params.gnss_error, 1, dt)
        noise = SensorNoise(1)
        frames.append(synthesize_frame(
            t=0.0, dt=dt, vehicle_ids=_ids(n), entered=entered, x_true=x_true, accel_true=np.zeros((n, 2)),
            heading=np.zeros(n), gnss_sigma_p=np.full(n, 8.0), gnss_sigma_v=np.full(n, 0.5),
            features_true=np.empty((0, 4)), feature_tree=None, params=params, noise=noise,
            zone=np.full(n, "B", dtype=object), area=np.full(n, "1", dtype=object), gnss_error=proc, start=start))
    fix, fast = frames
    assert np.array_equal(fix.prior_z[entered], fix.gnss_z[entered])
    assert np.array_equal(fix.prior_R[entered], fix.gnss_R[entered])
    assert np.isnan(fix.prior_z[~entered]).all()
    # the fix is not the truth: its error is the receiver's (several metres at 8 m per axis)
    assert np.abs(fix.prior_z[entered, :2] - x_true[entered, :2]).max() > 1.0
    # the measurements themselves do not depend on the start
    assert fix.gnss_z.tobytes() == fast.gnss_z.tobytes()
    assert np.allclose(fast.prior_R[entered][:, 0, 0], 4.0)  # fast start: N(truth, 2 m)


def test_estimators_start_from_the_receiver_fix(cross_net, tmp_path, monkeypatch):
    """A short SUMO run with the field model and start = "gnss_fix": the frame marks the prior as the fix
    (prior_has_fix), the gnss tracker's estimate of a vehicle at its entry step is its fix with the receiver's
    covariance (not updated by the same fix again), and icp_da_lc's first belief b^(0) of every fresh vehicle
    is its fix."""
    import coloc.methods.icp_da_lc as lc_module
    from coloc.core.vehicles import fresh_rows, match_ids
    from experiments.config import load_config
    from experiments.runner import build_estimators, frame_source

    seen = []
    original = lc_module.prior_pair

    def spy(state, frame, params, match, accel, fusion=None):
        out = original(state, frame, params, match, accel, fusion)
        fresh = fresh_rows(match, frame.entered, frame.prior_z)
        seen.append((fresh.sum(), np.abs(out[0][fresh] - frame.gnss_z[fresh]).max(initial=0.0)))
        return out

    monkeypatch.setattr(lc_module, "prior_pair", spy)
    cfg_path = tmp_path / "cfg.toml"
    cfg_path.write_text(f"""
[run]
name = "fix"
seed = 3
duration_s = 40.0
methods = ["gnss", "icp_da_lc"]

[scenario]
kind = "sumo"
net_dir = "{cross_net}"
control = "tlr"
start = "gnss_fix"

[report]
track_area = "3"

[gnss_error]
model = "field"
""")
    cfg = load_config(cfg_path, {})
    estimators = build_estimators(cfg)
    gnss = estimators[0]
    entries = 0
    prev_ids = np.empty(0, dtype=object)
    with frame_source(cfg) as source:
        for frame in source.frames():
            blind = frame.without_truth()
            fresh = (match_ids(prev_ids, frame.vehicle_ids) < 0) | frame.entered
            est = gnss.step(blind)
            estimators[1].step(blind)
            assert np.array_equal(frame.prior_z[frame.entered], frame.gnss_z[frame.entered])
            assert np.abs(est.mean[fresh] - frame.gnss_z[fresh]).max(initial=0.0) < 1e-9
            assert np.array_equal(frame.prior_has_fix, frame.entered)
            assert np.abs(est.cov[fresh] - frame.gnss_R[fresh]).max(initial=0.0) < 1e-9
            entries += int(fresh.sum())
            prev_ids = frame.vehicle_ids
    assert entries > 5
    assert sum(k for k, _ in seen) == entries
    assert max(err for _, err in seen) < 1e-9
