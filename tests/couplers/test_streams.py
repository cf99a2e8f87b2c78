"""numpy Generators drawn inside numba kernels (couplers.sensing.streams): the same numbers in the same order
as numpy, the Generator's state in step with them, handles per process, and the realistic frames with the
kernels' draws equal to the frames with numpy's."""

import pickle
from pathlib import Path

import numpy as np
import pytest
from numba import njit

from couplers.sensing import streams
from couplers.sensing.streams import StreamHandles, handle, stream

ROOT = Path(__file__).resolve().parents[2]


@njit(cache=True)
def _mixed(h, n, lam):
    g = stream(h)
    counts = np.empty(lam.size * n, dtype=np.int64)
    for i in range(n):
        for s in range(lam.size):
            counts[i * lam.size + s] = g.poisson(lam[s])
    return counts, g.standard_normal((n, 4)), g.random(n), g.exponential(3.5, n), g.uniform(-np.pi, np.pi, n)


def test_this_installation_draws_as_numpy():
    """The self-test passes here, so the coupler's kernels draw (the fast path is on, as the benchmarks assume)."""
    assert streams.available()


@pytest.mark.parametrize("seed", [0, 11, 2026])
def test_kernel_draws_equal_numpy_draws_interleaved_with_numpy(seed):
    """Kernel draws, then numpy draws on the same Generator, then kernel draws again: byte for byte the
    sequence of numpy alone, at Poisson rates on both sides of numpy's switch (10) and at sizes 0 and 1."""
    lam = np.array([0.0, 0.05, 1.0, 9.99, 10.0, 55.0])
    ours, ref = np.random.default_rng(seed), np.random.default_rng(seed)
    h = handle(ours)
    for n in (0, 1, 517):
        got = _mixed(h, n, lam)
        want = (ref.poisson(np.broadcast_to(lam, (n, lam.size))).ravel(), ref.standard_normal((n, 4)),
                ref.random(n), ref.exponential(3.5, n), ref.uniform(-np.pi, np.pi, n))
        for g, w in zip(got, want):
            assert g.dtype == w.dtype and g.shape == w.shape
            assert g.tobytes() == w.tobytes()
        np.testing.assert_array_equal(ours.standard_normal(7), ref.standard_normal(7))  # numpy in between
    assert ours.bit_generator.state == ref.bit_generator.state


class _Owner:
    def __init__(self):
        self.a, self.b = np.random.default_rng(1), np.random.default_rng(2)
        self.handles = StreamHandles(self, ("a", "b"))


def test_handles_are_per_generator_and_recomputed_after_unpickling():
    owner = _Owner()
    assert owner.handles["a"] == handle(owner.a) and owner.handles["a"][0] != owner.handles["b"][0]
    copy = pickle.loads(pickle.dumps(owner))
    assert copy.handles._handles is None  # addresses are not carried over
    assert copy.handles["a"] == handle(copy.a) != owner.handles["a"]
    ref = np.random.default_rng(1)  # the state the copy carries: owner.a's, untouched
    ref.poisson(1.0, 5)
    np.testing.assert_array_equal(_mixed(copy.handles["a"], 5, np.array([1.0]))[1], ref.standard_normal((5, 4)))
    assert owner.a.random() == np.random.default_rng(1).random()  # the copy's draws left owner.a alone


def test_realistic_frames_equal_with_numpy_draws(monkeypatch):
    """90 s of experiments/arterial_tlr_realistic.toml (perception with occlusion by vehicles and buildings,
    correlated GNSS error with NLOS episodes, the body-frame IMU): every frame array byte for byte the same
    with the kernels' draws and with the numpy reference paths (streams.available() False)."""
    from experiments.config import load_config
    from experiments.runner import frame_source

    def frames(fast: bool) -> list:
        monkeypatch.setattr(streams, "available", lambda: fast)
        cfg = load_config(ROOT / "experiments" / "arterial_tlr_realistic.toml",
                          {"run.duration_s": 90.0, "run.methods": ["gnss"]})
        with frame_source(cfg) as src:
            return [(f.gnss_z, f.v2f_z, f.v2f_owner, f.v2f_R, f.truth.v2f_feature, f.imu.accel_body, f.imu.yaw_rate)
                    for f in src.frames()]

    fast, ref = frames(True), frames(False)
    assert len(fast) == len(ref) == 120
    for a, b in zip(fast, ref):
        for x, y in zip(a, b):
            assert x.dtype == y.dtype and x.tobytes() == y.tobytes()
    assert sum(int((f[4] == -1).sum()) for f in fast) > 120  # clutter was drawn
