"""numpy Generators drawn from inside numba kernels, the same numbers in the same order (the realistic frames).

Every effect of the coupler has its own ``numpy.random.Generator`` (``couplers.sensing.perception.effect_rng``). A
kernel that needs the draws of an effect could take the Generator itself as an argument, but numba unboxes
a Generator through ctypes at every call (about 5 us here), more than most draws cost. :func:`handle` reads,
once, the addresses numba's own unboxing reads (the bit generator's state and its ``next_uint64`` /
``next_uint32`` / ``next_double`` functions, ``BitGenerator.ctypes``), and :func:`stream` turns them into
numba's Generator inside the kernel: the draws then run numba's ports of numpy's distributions (ziggurat
normal and exponential, ``next_double`` uniforms, numpy's Poisson) on the Python object's own state, so a
draw in a kernel advances the Generator exactly as the same draw in numpy would.

numba's distributions are ports of numpy's C code, not numpy itself: :func:`available` is True only when
a self-test (every distribution the coupler draws in kernels, on a scratch generator, byte comparison with
numpy and the state after it) passes; callers run their numpy path otherwise. ``tests/couplers`` compare
the two as well. A handle holds raw addresses: the Generator must outlive it (the owners below keep both),
and it is never pickled (:class:`StreamHandles` recomputes them in another process).
"""

from __future__ import annotations

import ctypes
import functools

import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

_GENERATOR = types.NumPyRandomGeneratorType("generator")
_BIT_GENERATOR = types.NumPyRandomBitGeneratorType("bit_generator")


def handle(rng: np.random.Generator) -> tuple[int, int, int, int]:
    """(state, next_uint64, next_uint32, next_double) addresses of ``rng``'s bit generator, as numba's
    unboxing of a Generator reads them."""
    c = rng.bit_generator.ctypes

    def address(f) -> int:
        return int(ctypes.cast(f, ctypes.c_void_p).value)

    return int(c.state.value), address(c.next_uint64), address(c.next_uint32), address(c.next_double)


@intrinsic
def stream(typingctx, h):
    """numba's Generator over the bit generator of a :func:`handle` (no Python object: the meminfo and
    parent are null, which the runtime's reference counting skips)."""

    def codegen(context, builder, sig, args):
        bit = cgutils.create_struct_proxy(_BIT_GENERATOR)(context, builder)
        bit.state = builder.extract_value(args[0], 0)
        bit.state_address = builder.extract_value(args[0], 0)
        bit.fnptr_next_uint64 = builder.extract_value(args[0], 1)
        bit.fnptr_next_uint32 = builder.extract_value(args[0], 2)
        bit.fnptr_next_double = builder.extract_value(args[0], 3)
        bit.bit_generator = context.get_constant(types.uintp, 0)
        bit.parent = cgutils.get_null_value(bit.parent.type)
        gen = cgutils.create_struct_proxy(_GENERATOR)(context, builder)
        gen.bit_generator = bit._getvalue()
        gen.meminfo = cgutils.get_null_value(gen.meminfo.type)
        gen.parent = cgutils.get_null_value(gen.parent.type)
        return gen._getvalue()

    return _GENERATOR(h), codegen


@njit(cache=True)
def _self_test_draws(h, n, lam):
    g = stream(h)
    counts = np.empty(lam.size * n, dtype=np.int64)
    for i in range(n):
        for s in range(lam.size):
            counts[i * lam.size + s] = g.poisson(lam[s])
    return (counts, g.random(n), g.standard_normal((n, 4)), g.exponential(10.0, n), g.uniform(-np.pi, np.pi, n),
            g.standard_normal(n))


@functools.cache
def available() -> bool:
    """numba's draws equal numpy's on this installation (module docstring): Poisson at rates below and above
    numpy's switch to its rejection method (10) and at 0, uniforms, normals, exponentials, uniform angles."""
    lam = np.array([0.0, 0.3, 1.0, 2.5, 12.0, 40.0])
    try:
        for seed in (1, 2):
            ours, ref = np.random.default_rng(seed), np.random.default_rng(seed)
            got = _self_test_draws(handle(ours), 2000, lam)
            want = (ref.poisson(np.broadcast_to(lam, (2000, lam.size))).ravel(), ref.random(2000),
                    ref.standard_normal((2000, 4)), ref.exponential(10.0, 2000), ref.uniform(-np.pi, np.pi, 2000),
                    ref.standard_normal(2000))
            if not all(g.dtype == w.dtype and g.tobytes() == w.tobytes() for g, w in zip(got, want)):
                return False
            if ours.bit_generator.state != ref.bit_generator.state:
                return False
    except Exception:  # noqa: BLE001 - any failure of the numba path means: use numpy
        return False
    return True


class StreamHandles:
    """The :func:`handle` of each named Generator attribute of ``owner``, computed on first use and again
    after unpickling (addresses are per process)."""

    def __init__(self, owner: object, names: tuple[str, ...]):
        self._owner, self._names, self._handles = owner, names, None

    def __getitem__(self, name: str) -> tuple[int, int, int, int]:
        if self._handles is None:
            self._handles = {n: handle(getattr(self._owner, n)) for n in self._names}
        return self._handles[name]

    def __getstate__(self):
        return {"_owner": self._owner, "_names": self._names, "_handles": None}
