"""numpy's own LAPACK and BLAS called from numba: :func:`relative_message_numpy_blas` is
:func:`coloc.inference.gaussian.relative_message` (np.linalg.inv, stacked ``@``, ``einsum``)
row by row in one call, byte for byte.

numpy computes ``np.linalg.inv`` with LAPACK ``dgesv`` (A copied to column-major order, B the
identity) and a stacked ``a @ b`` of 4x4 float64 matrices with one CBLAS ``dgemm`` per matrix
(row-major, no transposes), both from the OpenBLAS library it ships with. The kernels here call the
same two functions of the same library, found by their symbol names in that library
(``scipy_dgesv_64_``, ``scipy_cblas_dgemm64_`` in numpy's wheels), so every product and inverse is
the one numpy computes. ``np.einsum("nij,nj->ni", a, x)`` sums a row's four products as
``0 + ((0 + a0 x0 + a2 x2) + (0 + a1 x1 + a3 x3))`` (numpy's two-lane SIMD loop, no fused
multiply-add): :func:`_einsum_row`. Elementwise operations are IEEE operations either way.

:func:`available` is False when the library or a symbol is not found, or when the self-test at
the first call (random inputs, byte comparison with numpy) fails, e.g. a numpy built against another
BLAS or with other SIMD loops; the caller then runs numpy. Tests compare the two as well.
"""

from __future__ import annotations

import ctypes
import glob
import os

import llvmlite.binding as ll
import numpy as np
from numba import njit, types

_DGESV = "coloc_numpy_dgesv"
_DGEMM = "coloc_numpy_cblas_dgemm"

# LAPACK dgesv(n, nrhs, a, lda, ipiv, b, ldb, info), every argument by address (64-bit integers);
# CBLAS dgemm(order, transa, transb, m, n, k, alpha, a, lda, b, ldb, beta, c, ldc). Addresses are
# passed as intp (the same registers as a pointer in the C calling convention).
_dgesv = types.ExternalFunction(_DGESV, types.void(*([types.intp] * 8)))
_dgemm = types.ExternalFunction(_DGEMM, types.void(
    types.int32, types.int32, types.int32, types.int64, types.int64, types.int64, types.float64, types.intp,
    types.int64, types.intp, types.int64, types.float64, types.intp, types.int64))

_ROW_MAJOR, _NO_TRANS = 101, 111


def _numpy_openblas() -> tuple[int, int] | None:
    """Addresses of dgesv and cblas_dgemm in the OpenBLAS of numpy's wheel (None if not found)."""
    libs = os.path.join(os.path.dirname(os.path.dirname(np.__file__)), "numpy.libs")
    for path in sorted(glob.glob(os.path.join(libs, "libscipy_openblas64_*.so"))):
        try:
            lib = ctypes.CDLL(path)
            gesv, gemm = lib.scipy_dgesv_64_, lib.scipy_cblas_dgemm64_
        except (OSError, AttributeError):
            continue
        return ctypes.cast(gesv, ctypes.c_void_p).value, ctypes.cast(gemm, ctypes.c_void_p).value
    return None


@njit(cache=True)
def _einsum_row(a, x, i):
    """``np.einsum("ij,j->i", a, x)[i]`` as numpy's loop sums it (module docstring)."""
    lane0 = (0.0 + a[i, 0] * x[0]) + a[i, 2] * x[2]
    lane1 = (0.0 + a[i, 1] * x[1]) + a[i, 3] * x[3]
    return 0.0 + (lane0 + lane1)


@njit(cache=True)
def _same_row(bits, r):
    """Row ``r`` of ``bits`` (O, 16) equals row ``r`` - 1."""
    for c in range(16):
        if bits[r, c] != bits[r - 1, c]:
            return False
    return True


@njit(cache=True)
def relative_message_numpy_blas(lam, eta, offset, r_inv):
    """:func:`coloc.inference.gaussian.relative_message` with ``r_inv`` given (C-contiguous float64
    (O, 4, 4), (O, 4)), byte for byte. Returns (lam_y, eta_y, ok); ``ok`` False when dgesv found
    a singular S = Lambda + R^-1 (numpy raises there: the caller runs numpy). A row whose Lambda and
    R^-1 are bit for bit those of the row before reuses its S^-1 products (the same calls on the same
    bits give the same bits)."""
    o = lam.shape[0]
    out_lam = np.empty((o, 4, 4))
    out_eta = np.empty((o, 4))
    s = np.empty((4, 4))
    a_f = np.empty(16)  # S in column-major order (numpy's linearised copy)
    b_f = np.empty(16)  # the identity, then S^-1 in column-major order
    s_inv = np.empty((4, 4))
    t = np.empty((4, 4))
    u = np.empty((4, 4))
    ints = np.empty(5, dtype=np.int64)  # n, nrhs, lda, ldb, info
    ipiv = np.empty(4, dtype=np.int64)
    p_int = ints.ctypes.data
    p_a, p_b, p_piv = a_f.ctypes.data, b_f.ctypes.data, ipiv.ctypes.data
    p_sinv, p_t, p_u = s_inv.ctypes.data, t.ctypes.data, u.ctypes.data
    lam_bits = lam.reshape((o, 16)).view(np.int64)
    r_bits = r_inv.reshape((o, 16)).view(np.int64)
    for r in range(o):
        if r > 0 and _same_row(lam_bits, r) and _same_row(r_bits, r):
            # the row before had the same Lambda and R^-1, bit for bit (a vehicle's rows when the sensor
            # noise is the same): S^-1, Lambda_y and R^-1 S^-1 are those numpy computes again for it
            for i in range(4):
                for j in range(4):
                    out_lam[r, i, j] = out_lam[r - 1, i, j]
            for i in range(4):
                out_eta[r, i] = _einsum_row(t, eta[r], i) + _einsum_row(out_lam[r], offset[r], i)
            continue
        for i in range(4):
            for j in range(4):
                s[i, j] = lam[r, i, j] + r_inv[r, i, j]
        for i in range(4):
            for j in range(4):
                a_f[j * 4 + i] = s[i, j]
                b_f[j * 4 + i] = 1.0 if i == j else 0.0
        ints[0], ints[1], ints[2], ints[3], ints[4] = 4, 4, 4, 4, 0
        _dgesv(p_int, p_int + 8, p_a, p_int + 16, p_piv, p_b, p_int + 24, p_int + 32)
        if ints[4] != 0:
            return out_lam, out_eta, False
        for i in range(4):  # symmetrize(inv(S))
            for j in range(4):
                s_inv[i, j] = 0.5 * (b_f[j * 4 + i] + b_f[i * 4 + j])
        # lam_y = symmetrize((lam @ s_inv) @ r_inv)
        _dgemm(_ROW_MAJOR, _NO_TRANS, _NO_TRANS, 4, 4, 4, 1.0, lam[r].ctypes.data, 4, p_sinv, 4, 0.0, p_t, 4)
        _dgemm(_ROW_MAJOR, _NO_TRANS, _NO_TRANS, 4, 4, 4, 1.0, p_t, 4, r_inv[r].ctypes.data, 4, 0.0, p_u, 4)
        for i in range(4):
            for j in range(4):
                out_lam[r, i, j] = 0.5 * (u[i, j] + u[j, i])
        # eta_y = einsum(r_inv @ s_inv, eta) + einsum(lam_y, offset)
        _dgemm(_ROW_MAJOR, _NO_TRANS, _NO_TRANS, 4, 4, 4, 1.0, r_inv[r].ctypes.data, 4, p_sinv, 4, 0.0, p_t, 4)
        for i in range(4):
            out_eta[r, i] = _einsum_row(t, eta[r], i) + _einsum_row(out_lam[r], offset[r], i)
    return out_lam, out_eta, True


def _self_test() -> bool:
    """The kernel against numpy on random inputs, byte for byte."""
    rng = np.random.default_rng(24)
    o = 64
    a = rng.standard_normal((o, 4, 4))
    lam = a @ np.swapaxes(a, 1, 2)
    lam = 0.5 * (lam + np.swapaxes(lam, 1, 2))
    lam[:4] = 0.0
    b = rng.standard_normal((o, 4, 4))
    r_inv = b @ np.swapaxes(b, 1, 2) + np.eye(4)
    r_inv = 0.5 * (r_inv + np.swapaxes(r_inv, 1, 2))
    eta = rng.standard_normal((o, 4)) * 10
    eta[4:8] = -0.0
    offset = rng.standard_normal((o, 4)) * 30
    s = lam + r_inv
    s_inv = np.linalg.inv(s)
    s_inv = 0.5 * (s_inv + np.swapaxes(s_inv, -1, -2))
    lam_y = lam @ s_inv @ r_inv
    lam_y = 0.5 * (lam_y + np.swapaxes(lam_y, -1, -2))
    eta_y = np.einsum("nij,nj->ni", r_inv @ s_inv, eta) + np.einsum("nij,nj->ni", lam_y, offset)
    got_lam, got_eta, ok = relative_message_numpy_blas(lam, eta, offset, r_inv)
    return bool(ok) and got_lam.tobytes() == lam_y.tobytes() and got_eta.tobytes() == eta_y.tobytes()


_AVAILABLE: list[bool] = []


def available() -> bool:
    """Whether the kernel may run: numpy's library and its symbols found, and the self-test passed
    (checked once, at the first call; False: callers run numpy)."""
    if not _AVAILABLE:
        found = _numpy_openblas()
        ok = False
        if found is not None:
            ll.add_symbol(_DGESV, found[0])
            ll.add_symbol(_DGEMM, found[1])
            try:
                ok = _self_test()
            except Exception:  # noqa: BLE001 (any failure: numpy runs instead)
                ok = False
        _AVAILABLE.append(ok)
    return _AVAILABLE[0]
