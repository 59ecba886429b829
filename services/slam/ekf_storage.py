"""Storage of the EKF-SLAM covariance and its rank-k downdate (the numerical floor under
:mod:`slamlens.services.slam.ekf`'s kernels).

The covariance lives in a preallocated square buffer ``L`` of which only the **lower
triangle** of the leading N×N block is meaningful (``L[i, j]`` for ``j ≤ i``); the strict
upper triangle is scratch and is never read (docs/estimator.md, "Storage and cost").
:func:`symmetric` materialises the full matrix; :func:`downdate_lower` subtracts V Vᵀ from the
lower triangle in place, with BLAS ``dsyrk`` called on the strided view.
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable

import numpy as np

# ---------------------------------------------------------------------------------------
# lower-triangle storage
# ---------------------------------------------------------------------------------------


_SYM_BLOCK = 128  # a 128×128 tile (128 KB) stays in L2 while it is transposed


@functools.cache
def _lower_mask(size: int) -> np.ndarray:
    return np.tri(size, dtype=bool)


def symmetric(L: np.ndarray, N: int, *, out: np.ndarray | None = None) -> np.ndarray:
    """A full symmetric N×N matrix from the lower triangle of ``L[:N, :N]`` (into ``out``
    if given: an N×N float64 array, e.g. a view of a message buffer).

    One pass over ``out``, row block by row block of :data:`_SYM_BLOCK` rows: left of the
    diagonal tile the rows are copied, the diagonal tile is mirrored, and right of it each
    tile is the transpose of a cache-sized tile of the lower triangle below. The lower
    triangle is read twice and ``out`` written once (the copy-then-mirror it replaced wrote
    every entry, then half of them again): 1.14–1.25× faster at n = 1000
    (``benchmarks/bench_symmetric.py``).
    """
    if out is None:
        out = np.empty((N, N))
    B = _SYM_BLOCK
    for s in range(0, N, B):
        e = min(N, s + B)
        out[s:e, :s] = L[s:e, :s]
        tile = L[s:e, s:e]
        out[s:e, s:e] = np.where(_lower_mask(e - s), tile, tile.T)
        for c in range(e, N, B):
            f = min(N, c + B)
            out[s:e, c:f] = L[c:f, s:e].T
    return out


def symmetric_after_predict(L: np.ndarray, N: int, previous: np.ndarray, *,
                            out: np.ndarray) -> np.ndarray:
    """``symmetric(L, N)`` when only the robot rows/columns changed since ``previous``
    (= symmetric(L, N) before a :func:`predict`, which leaves P_mm untouched): a copy and
    3 rows and columns instead of a transpose of the whole matrix."""
    out[...] = previous
    return robot_rows_into(L, N, out)


def robot_rows_into(L: np.ndarray, N: int, out: np.ndarray) -> np.ndarray:
    """Write the robot's rows and columns of the symmetric P (from ``L``) into the full
    N×N ``out``, leaving the rest as it is: after a :func:`predict`, ``symmetric(L, N)``
    of the state before it becomes ``symmetric(L, N)`` now, in place (O(N))."""
    out[0:N, 0:3] = L[0:N, 0:3]
    out[0:3, 0:N] = L[0:N, 0:3].T
    pvv = out[0:3, 0:3]
    pvv[...] = np.where(_lower_mask(3), L[0:3, 0:3], L[0:3, 0:3].T)
    return out


def lower_from_symmetric(P: np.ndarray, *, capacity: int | None = None) -> np.ndarray:
    """Storage buffer (capacity × capacity) holding the symmetric ``P`` (for tests, resets)."""
    N = P.shape[0]
    cap = N if capacity is None else max(capacity, N)
    L = np.zeros((cap, cap))
    L[:N, :N] = P
    return L


def robot_columns(L: np.ndarray, N: int, out: np.ndarray) -> None:
    """out[0:3, :N] = the robot rows of the symmetric P (= its robot columns)."""
    out[0:3, 3:N] = L[3:N, 0:3].T  # strided gather of 3 values per row: O(N)
    p00, p10, p11 = L[0, 0], L[1, 0], L[1, 1]
    p20, p21, p22 = L[2, 0], L[2, 1], L[2, 2]
    out[0, 0:3] = (p00, p10, p20)
    out[1, 0:3] = (p10, p11, p21)
    out[2, 0:3] = (p20, p21, p22)


def landmark_columns(L: np.ndarray, N: int, a: int, out: np.ndarray) -> None:
    """out[0:2, :N] = rows a, a+1 of the symmetric P."""
    out[:, 0:a] = L[a:a + 2, 0:a]  # contiguous row prefixes
    out[:, a:N] = L[a:N, a:a + 2].T  # column below the diagonal, strided
    out[1, a] = L[a + 1, a]  # the line above read L[a, a+1], in the unused upper triangle


# ---------------------------------------------------------------------------------------
# the rank-2 downdate: BLAS dsyrk on the lower triangle, in place
# ---------------------------------------------------------------------------------------


@functools.cache
def _dsyrk() -> Callable[..., None] | None:
    """scipy's own BLAS ``dsyrk`` as a ctypes function, or None if it cannot be found.

    scipy.linalg.blas wrappers take no leading dimension and copy any non-contiguous
    operand, which would defeat in-place work on the view ``L[:N, :N]`` of a larger buffer;
    the raw BLAS symbol (exported by scipy.linalg.cython_blas as a PyCapsule) takes lda/ldc.
    """
    # void dsyrk(char *uplo, char *trans, int *n, int *k, double *alpha, double *a,
    #            int *lda, double *beta, double *c, int *ldc)
    return _blas("dsyrk", 10)


@functools.cache
def _dsyr2k() -> Callable[..., None] | None:
    """BLAS ``dsyr2k`` (C ← α(A Bᵀ + B Aᵀ) + βC) as :func:`_dsyrk` finds ``dsyrk``."""
    # void dsyr2k(char *uplo, char *trans, int *n, int *k, double *alpha, double *a,
    #             int *lda, double *b, int *ldb, double *beta, double *c, int *ldc)
    return _blas("dsyr2k", 12)


def _blas(name: str, nargs: int) -> Callable[..., None] | None:
    """The raw BLAS symbol ``name`` of scipy.linalg.cython_blas (all ``nargs`` arguments
    pointers), or None."""
    try:
        from scipy.linalg import cython_blas

        capsule = cython_blas.__pyx_capi__[name]
        get_name = ctypes.pythonapi.PyCapsule_GetName
        get_name.restype = ctypes.c_char_p
        get_name.argtypes = [ctypes.py_object]
        get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
        get_pointer.restype = ctypes.c_void_p
        get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        address = get_pointer(capsule, get_name(capsule))
    except (ImportError, AttributeError, KeyError, ValueError):
        return None
    if not address:
        return None
    proto = ctypes.CFUNCTYPE(None, *([ctypes.c_void_p] * nargs))
    return proto(address)


class SyrkArgs:
    """Preallocated ctypes scalars for dsyrk (building them per call costs microseconds)."""

    def __init__(self) -> None:
        self.uplo = ctypes.c_char(b"U")  # L's lower triangle, seen column-major, is upper
        self.trans = ctypes.c_char(b"N")
        self.n = ctypes.c_int(0)
        self.k = ctypes.c_int(2)
        self.alpha = ctypes.c_double(-1.0)
        self.beta = ctypes.c_double(1.0)
        self.lda = ctypes.c_int(0)
        self.ldb = ctypes.c_int(0)
        self.ldc = ctypes.c_int(0)
        self.one = ctypes.c_double(1.0)
        self.addr = {name: ctypes.addressof(getattr(self, name))
                     for name in ("uplo", "trans", "n", "k", "alpha", "beta", "lda", "ldb",
                                  "ldc", "one")}


def _in_place(N: int, *arrays: np.ndarray) -> bool:
    """Whether BLAS can work on ``arrays`` where they lie: float64 rows of unit stride, each
    row at least N long (a leading dimension ≥ N)."""
    return all(a.dtype == np.float64 and a.strides[1] == 8 and a.strides[0] >= 8 * N
               for a in arrays)


def _filled(args: SyrkArgs | None, N: int, k: int, L: np.ndarray, a: np.ndarray,
            b: np.ndarray | None = None) -> SyrkArgs:
    """``args`` (or new ones) set for an N×N result in ``L`` from N×k operands ``a``
    (and ``b``), each given by its rows."""
    out = SyrkArgs() if args is None else args
    out.n.value, out.k.value = N, k
    out.lda.value = a.strides[0] // 8
    out.ldb.value = (a if b is None else b).strides[0] // 8
    out.ldc.value = L.strides[0] // 8
    return out


def downdate_lower(L: np.ndarray, vt: np.ndarray, N: int, *, args: SyrkArgs | None = None,
                   use_blas: bool = True) -> None:
    """L[:N, :N] −= V Vᵀ on (at least) the lower triangle, in place; V = vt[:, :N]ᵀ (N×k,
    k = the rows of ``vt``: 2 for one observation, 2m for m deferred ones).

    ``args`` is reusable scratch (one per thread); ``use_blas=False`` forces the numpy
    fallback (tests compare the two).
    """
    k = vt.shape[0]
    fn = _dsyrk() if use_blas else None
    if not (k > 0 and fn is not None and _in_place(N, L, vt)):
        # Fallback: one full product and subtraction (3 passes, same result on the triangle).
        block = L[:N, :N]
        block -= vt[:, :N].T @ vt[:, :N]
        return
    assert fn is not None
    a = _filled(args, N, k, L, vt)  # held: its ctypes fields are what the pointers name
    ad = a.addr
    fn(ad["uplo"], ad["trans"], ad["n"], ad["k"], ad["alpha"], vt.ctypes.data, ad["lda"],
       ad["beta"], L.ctypes.data, ad["ldc"])


def rank2k_lower(L: np.ndarray, at: np.ndarray, bt: np.ndarray, N: int, *,
                 args: SyrkArgs | None = None, use_blas: bool = True) -> None:
    """L[:N, :N] += A Bᵀ + B Aᵀ on (at least) the lower triangle, in place; A = at[:, :N]ᵀ,
    B = bt[:, :N]ᵀ (N×k each, k = their rows): one pass over P, BLAS ``dsyr2k`` on the
    strided view (the invariant EKF's update, :mod:`slamlens.services.slam.ekf_invariant`).
    ``use_blas=False`` forces the numpy fallback (tests compare the two)."""
    k = at.shape[0]
    fn = _dsyr2k() if use_blas else None
    if not (k > 0 and bt.shape[0] == k and fn is not None and _in_place(N, L, at, bt)):
        product = at[:, :N].T @ bt[:, :N]
        block = L[:N, :N]
        block += product
        block += product.T
        return
    assert fn is not None
    a = _filled(args, N, k, L, at, bt)  # held: its ctypes fields are what the pointers name
    ad = a.addr
    fn(ad["uplo"], ad["trans"], ad["n"], ad["k"], ad["one"], at.ctypes.data, ad["lda"],
       bt.ctypes.data, ad["ldb"], ad["one"], L.ctypes.data, ad["ldc"])


# ---------------------------------------------------------------------------------------
# the invariant EKF's held-back step J = I + U eθᵀ (services/slam/ekf_invariant.py)
# ---------------------------------------------------------------------------------------


def turned_rows(rows: np.ndarray, U: np.ndarray, which: tuple[int, ...]) -> None:
    """``rows`` (rows ``which`` of L, row θ among them third) become those rows of
    J L Jᵀ, J = I + U eθᵀ: row c ← L_c + U_c L_θ + U (L_θc + U_c L_θθ) (U_θ = 0)."""
    theta = rows[2].copy()  # row θ of L
    uc = U[list(which)]
    t = rows[:, 2] + uc * theta[2]
    rows += np.outer(uc, theta)
    rows += np.outer(t, U)


def theta_row(L: np.ndarray, N: int) -> np.ndarray:
    """Row θ of the symmetric P stored in ``L`` (a new array, O(N))."""
    out = np.empty(N)
    out[0], out[1], out[2] = L[2, 0], L[2, 1], L[2, 2]
    out[3:] = L[3:N, 2]
    return out


def held_diagonal(L: np.ndarray, N: int, held: np.ndarray,
                  turn: np.ndarray | None = None) -> np.ndarray:
    """The diagonal of P = J L Jᵀ − Σ V Vᵀ, the steps a workspace holds back (V = the rows
    of ``held``; J = I + turn·eθᵀ, or I for None): L_ii + 2 U_i L_θi + U_i² L_θθ − ‖V_i‖²
    (O(mN)); a strided view of L's diagonal when nothing is held."""
    diag = np.diagonal(L)[:N]
    if turn is not None:
        theta = theta_row(L, N)
        diag = diag + turn * (2.0 * theta + turn * theta[2])
    if held.shape[0]:
        diag = diag - (held[:, :N] * held[:, :N]).sum(axis=0)
    return diag


def turn_lower(L: np.ndarray, U: np.ndarray, vt: np.ndarray, N: int, *,
               args: SyrkArgs | None = None) -> None:
    """L ← J L Jᵀ − V Vᵀ (J = I + U eθᵀ, V = vt[:, :N]ᵀ) on the lower triangle, in place,
    as one :func:`rank2k_lower` pass: J L Jᵀ = L + U wᵀ + w Uᵀ with w = L eθ + (L_θθ/2) U
    (U_θ = 0), and −V Vᵀ = (−V/2) Vᵀ + V (−V/2)ᵀ."""
    m = vt.shape[0]
    theta = theta_row(L, N)
    at, bt = np.empty((m + 1, N)), np.empty((m + 1, N))
    at[0] = U
    np.multiply(U, 0.5 * float(theta[2]), out=bt[0])
    bt[0] += theta
    np.multiply(vt[:, :N], -0.5, out=at[1:])
    bt[1:] = vt[:, :N]
    rank2k_lower(L, at, bt, N, args=args)
