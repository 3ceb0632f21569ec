"""Heat kernel of a triangle mesh: batched columns and the Heat Kernel Signature.

A package in the order a query flows: ``kernel.py`` (:class:`HeatKernel`: set-up, plan,
dispatch; :func:`default_times`, :func:`threads`, :func:`blas_threads`), ``spectral.py`` (the
eigenbasis path, checks of given eigenpairs), ``chebyshev.py`` (the Chebyshev expansion and
recurrence, the spectral bound), ``certify.py`` (a-posteriori error bounds).

The paper defines the heat kernel matrix ``K_t = exp(-t L) A^-1`` with ``L = A^-1 W`` (lumped
mass ``A``, stiffness ``W``), so that ``k_t(p, x) = K_t[x, p]`` is the heat at ``x`` at time ``t``
after a unit of heat was placed at ``p``. With the symmetric form ``S = A^-1/2 W A^-1/2``,

    K_t = A^-1/2 exp(-t S) A^-1/2,   column p:  k_t(p, .) = A^-1/2 exp(-t S) e_p / sqrt(a_p).

Two ways to apply ``exp(-t S)`` are combined:

* **Eigenbasis** (spectral): ``exp(-tS) ~ Psi_k exp(-t Lambda_k) Psi_k^T`` with the ``k`` smallest
  eigenpairs (shift-invert Lanczos). Exact up to the truncation ``exp(-t lambda_{k+1})`` in
  operator norm: good for large ``t``, useless for small ``t``.
* **Chebyshev**: ``exp(-t lambda) = e^-c [I_0(c) + 2 sum_k (-1)^k I_k(c) T_k(x)]`` with
  ``x = 2 lambda / lambda_max - 1`` and ``c = t lambda_max / 2`` (Jacobi–Anger; ``I_k``
  modified Bessel functions, ``scipy.special.ive``). One three-term recurrence on torch sparse
  tensors serves a whole block of sources and all times at once; the degree per ``t`` is the
  first whose coefficient tail is below the target, about ``3.6 sqrt(t lambda_max)`` for 1e-6.

The **hybrid** plan (default) uses the eigenbasis for every time whose truncation bound meets
``rtol`` and Chebyshev for the rest (the small times). Every value returned by
:meth:`HeatKernel.columns` carries an a-posteriori bound on its relative L2 error (per source
and time, see :attr:`HeatKernel.error_bound`); any (source, time) whose bound exceeds ``rtol`` is
recomputed with a higher Chebyshev degree, so the guarantee holds at every time, including
``t = 0.001`` where a truncated spectrum is several percent wrong.

Bound used (exact arithmetic; rounding adds about ``degree * eps``): if the operator error on
``u = exp(-tS) e_p`` is at most ``eta`` in the 2-norm (Chebyshev: the coefficient tail; spectral:
``exp(-t lambda_k)``), the column error is at most ``eta / sqrt(a_min a_p)`` and the relative
error at most ``eta / (sqrt(a_min a_p) ||c_hat|| - eta)`` where ``c_hat`` is the computed column.
"""

from .chebyshev import (
    CHEBYSHEV_BYTES,
    chebyshev_coefficients,
    chebyshev_degree,
    chebyshev_tail,
    lambda_max_bound,
)
from .kernel import HeatKernel, blas_threads, default_times, threads
from .spectral import _check_eigenpairs  # noqa: F401 - not public API (tests, operators)

__all__ = [
    "HeatKernel",
    "default_times",
    "chebyshev_coefficients",
    "chebyshev_degree",
    "chebyshev_tail",
    "lambda_max_bound",
    "threads",
    "blas_threads",
    "CHEBYSHEV_BYTES",
]
