"""The eigenbasis side of the heat kernel: checks of given eigenpairs and the truncated-spectrum
columns ``exp(-t S) e_p`` (exact up to ``exp(-t lambda_k)`` in operator norm, so good for large
``t``).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from ..eigen import SOLVER_TOL

__all__ = ["spectral_columns"]


def _check_eigenpairs(W: sp.spmatrix, A: sp.spmatrix, lam: np.ndarray, phi: np.ndarray,
                      mesh: object) -> None:
    """Refuse given eigenpairs that are not this operator's (stale cache, another mesh).

    The test is the eigensolver's own backward error, so it is scale-aware: with ``D`` the
    (lumped) mass diagonal and ``S = D^-1/2 W D^-1/2``, the residual
    ``rho_i = |D^-1/2 (W phi_i - lam_i A phi_i)| / (|S|_G |D^1/2 phi_i|)``, where ``|S|_G`` is
    the Gershgorin bound of ``|S|`` (free, never below ``lambda_max``). ARPACK in shift-invert
    at relative tolerance ``tol`` guarantees ``rho <= tol`` (1e-10), every path of
    :func:`torchheat.eigen.eigenpairs` ``rho <= SOLVER_TOL`` (1e-9; dense: ~1e-16), so the
    limit ``10 SOLVER_TOL`` never refuses a correct solve, whatever the mesh size or
    eigenvalue (a residual relative to ``lam_i`` once refused the constant mode of every
    60k-vertex mesh). Another mesh's pairs read >= 1e-5; another pose of the same
    connectivity (KIDS 60k) reads 3e-7 at the median column, up to 3e-6.
    Checked on 8 spread columns (a wrong set fails on most): ``O(8 nnz)``, ~10 ms at 60k.
    """
    cols = np.unique(np.linspace(0, lam.size - 1, min(8, lam.size)).astype(np.int64))
    lam, phi = lam[cols], np.ascontiguousarray(phi[:, cols])
    d = np.asarray(A.sum(axis=1)).ravel()
    isq = 1.0 / np.sqrt(np.maximum(d, 1e-300))
    s_norm = float(np.max(isq * (abs(W) @ isq), initial=0.0))  # Gershgorin bound of |S|
    r = (W @ phi - (A @ phi) * lam) * isq[:, None]
    den = np.linalg.norm(phi / isq[:, None], axis=0) * max(s_norm, 1e-300)
    rel = np.linalg.norm(r, axis=0) / den
    if rel.size and not float(rel.max()) <= _EIGENPAIR_TOL:
        i = int(np.nanargmax(np.nan_to_num(rel, nan=np.inf)))
        name = getattr(mesh, "name", None) or "mesh"
        raise ValueError(
            f"{name}: the given eigenpairs are not those of this operator (eigenpair "
            f"{int(cols[i])} has backward error {float(rel[i]):.1e}, limit "
            f"{_EIGENPAIR_TOL:.0e}); recompute them (a stale cache or another mesh's "
            "eigenpairs?)"
        )


#: Largest backward error of given eigenpairs (:func:`_check_eigenpairs`): 10x the solver's.
_EIGENPAIR_TOL = 10 * SOLVER_TOL


def spectral_columns(phi: torch.Tensor, lam: torch.Tensor, sqrt_a: torch.Tensor,
                     red: np.ndarray, times: torch.Tensor) -> torch.Tensor:
    """``exp(-t S) e_p / sqrt(a_p)`` (the Chebyshev path's convention) from the truncated
    eigenbasis, for sources ``red`` and times ``times``.

    Parameters
    ----------
    phi : torch.Tensor, shape (m, k)
        Mass-orthonormal eigenvectors on the free vertices.
    lam : torch.Tensor, shape (k,)
    sqrt_a : torch.Tensor, shape (m,)
        Square roots of the lumped masses.
    red : numpy.ndarray, int64, shape (B,)
    times : torch.Tensor, shape (Js,)

    Returns
    -------
    torch.Tensor, shape (m, B, Js)

    Notes
    -----
    ``k_t(p, x) = sum_i phi_i(x) phi_i(p) e^{-t lam_i}``, times ``sqrt(a_x)``; cost
    ``2 m k B Js``; truncation error ``exp(-t lam_k)`` in operator norm.

    Examples
    --------
    >>> phi = torch.eye(3, dtype=torch.float64)
    >>> out = spectral_columns(phi, torch.tensor([0.0, 1.0, 2.0], dtype=torch.float64),
    ...                        torch.ones(3, dtype=torch.float64), np.array([1]),
    ...                        torch.tensor([0.5], dtype=torch.float64))
    >>> round(float(out[1, 0, 0]), 12) == round(float(np.exp(-0.5)), 12)
    True
    """
    E = torch.exp(-times[None, :] * lam[:, None])  # [k, Js]
    coeff = phi[torch.as_tensor(red, device=phi.device)][:, :, None] * E[None]
    spec = torch.einsum("mk,bkj->mbj", phi, coeff)  # k_t(p, x), [m, B, Js]
    return spec * sqrt_a[:, None, None]
