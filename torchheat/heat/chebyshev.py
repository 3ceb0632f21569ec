"""Chebyshev expansion of the heat operator ``exp(-t S)`` (``S = A^-1/2 W A^-1/2``, spectrum in
``[0, lambda_max]``): coefficients, degrees for a target accuracy, the spectral bound, and the
three-term recurrence applied to a block of sources at all times at once.

``exp(-t lambda) = e^-c [I_0(c) + 2 sum_k (-1)^k I_k(c) T_k(x)]`` with ``x = 2 lambda /
lambda_max - 1`` and ``c = t lambda_max / 2`` (Jacobi–Anger; ``I_k`` modified Bessel functions,
``scipy.special.ive``). The coefficient tail ``sum_{k>K} |a_k|`` bounds the operator-norm error of
the degree-``K`` truncation; about ``3.6 sqrt(t lambda_max)`` terms reach 1e-6.
"""

from __future__ import annotations

import math
from contextlib import contextmanager

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla
import torch
from scipy.special import ive

__all__ = ["chebyshev_coefficients", "chebyshev_degree", "chebyshev_tail", "chebyshev_columns",
           "lambda_max_bound", "CHEBYSHEV_BYTES"]


def chebyshev_coefficients(c: float, degree: int) -> np.ndarray:
    """Chebyshev coefficients of ``exp(-c (x + 1))`` on ``[-1, 1]``.

    ``exp(-t lambda)`` with ``x = 2 lambda / lambda_max - 1`` is this function for
    ``c = t lambda_max / 2``.

    Parameters
    ----------
    c : float
        Non-negative scale.
    degree : int
        Highest degree K.

    Returns
    -------
    numpy.ndarray
        Shape (K + 1,): ``a_0 = ive(0, c)``, ``a_k = 2 (-1)^k ive(k, c)``.

    Examples
    --------
    >>> a = chebyshev_coefficients(3.0, 40)
    >>> bool(abs(np.polynomial.chebyshev.chebval(0.2, a) - np.exp(-3.0 * 1.2)) < 1e-14)
    True
    """
    k = np.arange(degree + 1)
    a = 2.0 * ive(k, c) * np.where(k % 2 == 0, 1.0, -1.0)
    a[0] *= 0.5
    return a


def chebyshev_degree(c: float, tail: float) -> int:
    """Smallest degree K whose coefficient tail ``sum_{k>K} |a_k|`` is at most ``tail``.

    The tail bounds the uniform error of the truncated series on ``[-1, 1]`` and hence the
    operator-norm error of ``exp(-tS)``.

    Parameters
    ----------
    c : float
        ``t lambda_max / 2``.
    tail : float
        Target bound.

    Returns
    -------
    int

    Examples
    --------
    >>> chebyshev_degree(0.0, 1e-6)
    0
    >>> chebyshev_degree(100.0, 1e-6) > chebyshev_degree(10.0, 1e-6)
    True
    """
    kmax = int(c + 12.0 * math.sqrt(c + 1.0) + 40)
    a = np.abs(chebyshev_coefficients(c, kmax))
    tails = np.cumsum(a[::-1])[::-1]  # tails[K] = sum_{k >= K}
    ok = np.flatnonzero(np.append(tails[1:], 0.0) <= tail)
    return int(ok[0])


def lambda_max_bound(S: sp.spmatrix, tol: float = 1e-4) -> float:
    """An upper bound of the largest eigenvalue of a symmetric PSD sparse matrix.

    One Lanczos run (``eigsh(k=1)``, about 10 ms on 10k vertices) with a 1 % safety margin,
    capped by the Gershgorin bound (free and always safe but 1.1–1.7x loose on meshes).

    Parameters
    ----------
    S : scipy.sparse matrix, shape (n, n)
    tol : float
        Relative Lanczos tolerance.

    Returns
    -------
    float

    Examples
    --------
    >>> import scipy.sparse as sp
    >>> round(lambda_max_bound(sp.diags([1.0, 2.0, 3.0])), 2)  # Gershgorin is exact here
    3.0
    """
    S = sp.csr_matrix(S)
    gersh = float(np.max(np.asarray(abs(S).sum(axis=1)).ravel()))
    n = S.shape[0]
    if n <= 3:
        return min(gersh, float(np.linalg.eigvalsh(S.toarray())[-1]) * 1.01 + 1e-300)
    try:
        theta = float(
            sla.eigsh(S, k=1, which="LA", tol=tol, return_eigenvectors=False,
                      v0=np.ones(n))[0]
        )
    except sla.ArpackNoConvergence:  # pragma: no cover - extremely rare
        return gersh
    return min(gersh, theta * (1.0 + 100 * tol))


@contextmanager
def _flush_denormal(enabled: bool):
    if not enabled:
        yield
        return
    # torch.set_flush_denormal returns whether the CPU supports it, not the previous state, and
    # torch has no getter: restore the default (off). Left on (as this once did), it changed
    # later float64 work in the process: scipy's cKDTree then crashed on heat-kernel
    # descriptors whose tiny entries the flag turns into zeros.
    supported = torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if supported:
            torch.set_flush_denormal(False)


# Working-set budget (bytes) of one Chebyshev block: the recurrence's staging buffer, its
# weighted sums and their result, ``m (steps + 2 Jc + 1)`` elements per source (m vertices,
# Jc Chebyshev times, ``steps`` = :func:`_staged_steps`). The default block of 64 sources fits
# up to ~40k vertices (float64, 10 times, 32 steps); larger meshes get proportionally fewer
# sources per block, so that memory grows linearly with the mesh (64 sources of a 300k-vertex
# mesh would hold 7.6 GiB). Columns do not depend on the block they are computed in (tested).
CHEBYSHEV_BYTES = 1 << 30


def _staged_steps(degree: int) -> int:
    """Recurrence steps staged per GEMM in :func:`chebyshev_columns`."""
    return max(3, min(32, int(degree) + 1))


def _chebyshev_block(m: int, n_times: int, degree: int, esize: int, block: int,
                     memory_bytes: int = CHEBYSHEV_BYTES) -> int:
    """Sources per Chebyshev block: at most ``block``, within ``memory_bytes``, at least 1.

    Examples
    --------
    >>> _chebyshev_block(10_000, 10, 300, 8, 64), _chebyshev_block(300_000, 10, 300, 8, 64)
    (64, 8)
    """
    per_source = m * (_staged_steps(degree) + 2 * n_times + 1) * esize
    return int(max(1, min(int(block), int(memory_bytes) // max(1, per_source))))


def chebyshev_tail(c: float, degree: int) -> float:
    """``sum_{k > degree} |a_k|`` of :func:`chebyshev_coefficients` (``c = t lambda_max / 2``):
    the operator-norm error of the degree-``degree`` truncation of ``exp(-t S)``.

    Examples
    --------
    >>> chebyshev_tail(10.0, chebyshev_degree(10.0, 1e-6)) <= 1e-6
    True
    """
    a = np.abs(chebyshev_coefficients(c, int(degree) + int(12 * math.sqrt(c + 1)) + 40))
    return float(a[int(degree) + 1 :].sum())


def chebyshev_columns(X2: torch.Tensor, a: np.ndarray, red: np.ndarray, tj: np.ndarray,
                      degrees: np.ndarray, lambda_max: float) -> torch.Tensor:
    """``exp(-t S) e_p / sqrt(a_p)`` for sources ``red`` and times ``tj`` by the Chebyshev
    recurrence, every time from one pass.

    Parameters
    ----------
    X2 : torch.Tensor, sparse CSR, shape (m, m)
        ``(4 / lambda_max) S - 2 I``: twice the operator mapped to ``[-1, 1]`` (dtype and
        device of the result).
    a : numpy.ndarray, shape (m,)
        Lumped masses.
    red : numpy.ndarray, int64, shape (B,)
        Source rows.
    tj : numpy.ndarray, shape (Jc,)
    degrees : numpy.ndarray, int, shape (Jc,)
        Truncation degree of each time.
    lambda_max : float

    Returns
    -------
    torch.Tensor, shape (m, B, Jc)

    Notes
    -----
    Cost: ``max(degrees)`` sparse products with ``B`` columns; the ``T_k`` are staged in a
    buffer of :func:`_staged_steps` steps and summed over all times by one GEMM per stage,
    ``[Jc, steps] x [steps, m B]``, instead of ``Jc`` axpys per step.

    Examples
    --------
    >>> from torchheat.operators import scipy_to_torch
    >>> S = sp.diags([0.0, 1.0, 2.0])  # lambda_max = 2
    >>> X2 = scipy_to_torch((2.0 * S - 2.0 * sp.identity(3)).tocsr(), torch.float64)
    >>> out = chebyshev_columns(X2, np.ones(3), np.array([1]), np.array([0.5]), np.array([30]),
    ...                         2.0)
    >>> abs(float(out[1, 0, 0]) - math.exp(-0.5)) < 1e-12  # e^{-t lambda} at lambda = 1
    True
    """
    m = X2.shape[0]
    B = red.size
    dev, dt = X2.device, X2.dtype
    K = int(degrees.max())
    coef = np.zeros((len(tj), K + 1))
    for i, (t, d) in enumerate(zip(tj, degrees, strict=True)):
        coef[i, : d + 1] = chebyshev_coefficients(float(t) * lambda_max / 2.0, int(d))
    order = np.argsort(-degrees, kind="stable")  # times active at step k form a prefix
    coef_t = torch.as_tensor(coef[order], dtype=dt, device=dev)  # [Jc, K + 1]
    last = degrees[order]
    v0 = torch.zeros((m, B), dtype=dt, device=dev)
    v0[torch.as_tensor(red, device=dev), torch.arange(B, device=dev)] = torch.as_tensor(
        1.0 / np.sqrt(a[red]), dtype=dt, device=dev
    )
    # T_k are staged in a buffer of `chunk` steps; the weighted sums over all times are
    # then one GEMM per chunk, [Jc, chunk] x [chunk, m B], instead of Jc axpys per step.
    chunk = _staged_steps(K)
    buf = torch.empty((chunk, m * B), dtype=dt, device=dev)
    acc = torch.zeros((len(tj), m * B), dtype=dt, device=dev)
    t_prev: torch.Tensor | None = None
    t_cur: torch.Tensor | None = None
    for kk in range(K + 1):
        slot = kk % chunk
        t_new = buf[slot].view(m, B)  # the recurrence writes straight into the buffer
        if kk == 0:
            t_new.copy_(v0)
        elif kk == 1:
            torch.addmm(v0, X2, v0, beta=0.0, alpha=0.5, out=t_new)  # X v0
        else:
            assert t_prev is not None and t_cur is not None  # T_{k-2}, T_{k-1}: set at k >= 2
            torch.addmm(t_prev, X2, t_cur, beta=-1.0, out=t_new)
        t_prev, t_cur = t_cur, t_new
        if slot == chunk - 1 or kk == K:
            k0 = kk - slot
            nact = int((last >= k0).sum())
            acc[:nact].addmm_(coef_t[:nact, k0 : kk + 1], buf[: slot + 1])
    out = torch.empty_like(acc)
    out[torch.as_tensor(order, device=dev)] = acc
    out = out.reshape(len(tj), m, B)
    return out.permute(1, 2, 0)  # [m, B, Jc]
