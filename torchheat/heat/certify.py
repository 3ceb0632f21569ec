"""A-posteriori error bounds of computed heat-kernel columns.

If the operator error on ``u = exp(-tS) e_p`` is at most ``eta`` in the 2-norm (Chebyshev: the
coefficient tail; spectral: ``exp(-t lambda_k)``), the column ``k_t(p, .) = A^-1/2 u /
sqrt(a_p)`` is off by at most ``eta / sqrt(a_min a_p)`` and its relative error is at most
``eta / (sqrt(a_min a_p) ||c_hat|| - eta)``, ``c_hat`` the computed column (exact arithmetic;
rounding adds about ``degree * eps``).
"""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["column_norms", "relative_bound"]


def column_norms(colr: torch.Tensor, a: np.ndarray, a_min: float, red: np.ndarray
                 ) -> np.ndarray:
    """``sqrt(a_min a_p) ||c_hat||`` per (source, time).

    Parameters
    ----------
    colr : torch.Tensor, shape (m, B, J)
        Computed ``exp(-t S) e_p / sqrt(a_p)`` (the columns times ``sqrt(a_x)``).
    a : numpy.ndarray, shape (m,)
        Lumped masses; ``a_min`` their minimum.
    red : numpy.ndarray, int64, shape (B,)
        Source rows.

    Returns
    -------
    numpy.ndarray, shape (B, J)
    """
    inv_sq = torch.as_tensor(1.0 / np.sqrt(a), dtype=colr.dtype, device=colr.device)
    cn = torch.linalg.vector_norm(colr * inv_sq[:, None, None], dim=0)  # [B, J]
    cn = cn.double().cpu().numpy()
    return np.sqrt(a_min * a[red])[:, None] * cn


def relative_bound(norms: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """``eta / (norms - eta)``: the relative error bound of each column (0 where ``eta`` is 0,
    ``inf`` where the bound says nothing, ``norms <= eta``).

    Examples
    --------
    >>> relative_bound(np.array([[1.0, 1.0, 1e-9]]), np.array([[1e-7, 0.0, 1e-7]])).round(9)
    array([[1.e-07, 0.e+00,    inf]])
    """
    den = norms - eta
    with np.errstate(divide="ignore", invalid="ignore"):
        b = np.where(den > 0, eta / den, np.inf)
    b[eta == 0] = 0.0
    return b
