"""Laplace–Beltrami eigenpairs with scipy (ARPACK), and solving them in background processes.

This module imports numpy and scipy only, never torch, so that a command can start the
eigensolves of its meshes in worker processes *before* it pays for ``import torch`` (about
1 s): on two cores the two k = 100 eigensolves of a matching job then run while the main
process imports torch (see :class:`EigenWorkers` and ``torchheat match``).

* :func:`cotmatrix_scipy`, :func:`massmatrix_scipy`: the cotangent stiffness and the lumped or
  consistent mass as scipy sparse matrices (:mod:`torchheat.operators` wraps them as torch
  tensors and adds boundary conditions and the robust variant).
* :func:`eigenpairs`: the ``k`` smallest eigenpairs of ``W phi = lambda A phi``.
* :func:`cotan_eigenpairs`: those of the default operator of a mesh given as arrays (cotangent
  stiffness, lumped mass at unit area, Neumann), the same numbers as
  ``HeatKernel(Mesh(V, F), k=k)`` computes.

Examples
--------
>>> import numpy as np, trimesh
>>> s = trimesh.creation.icosphere(3)
>>> lam, phi = cotan_eigenpairs(s.vertices, s.faces, k=4)
>>> lam.shape, phi.shape, bool(abs(lam[0]) < 1e-8)
((4,), (642, 4), True)
"""

from __future__ import annotations

import contextlib
import os
import queue
import sys
import threading
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as sla

from .geometry import face_areas

__all__ = [
    "cotmatrix_scipy",
    "massmatrix_scipy",
    "face_areas",
    "eigenpairs",
    "cotan_eigenpairs",
    "EigenWorkers",
    "DEFAULT_EIGENPAIRS",
    "FINE_MAX_SHARE",
    "fine_k_problem",
    "ARPACK_TOL",
    "SOLVER_TOL",
    "EigensolverError",
]

#: Relative tolerance of the ARPACK solves (:func:`eigenpairs`); given eigenpairs are
#: checked against it (:class:`torchheat.heat.HeatKernel`).
ARPACK_TOL = 1e-10

#: Backward error ``|S psi - lam psi| / |S|`` that every sparse path of :func:`eigenpairs`
#: guarantees (ARPACK: ``ARPACK_TOL``; its LOBPCG fallback stagnates near 1e-10, accepted
#: up to this); :class:`torchheat.heat.HeatKernel` refuses given eigenpairs above 10x it.
SOLVER_TOL = 1e-9

#: Eigenpairs per shape of the matching pipeline (:func:`torchheat.matching.prepare`).
DEFAULT_EIGENPAIRS = 100

#: A fine map's basis (``match(fine_k=K)``, ``--fine K``) may hold at most this share of the
#: vertices of the smaller shape. Linear finite elements get eigenvalue ``k`` wrong by a
#: relative ``O(k / n)``, so modes near ``n / 4`` describe the mesh more than the shape, and
#: the cost grows about as ``k^3`` (TOSCA 5k pair, one thread: 200 modes ~1.3 s, 400 modes 10 s,
#: 1000 modes 58 s; 5000 modes was a dense solve and a ZoomOut of hours).
FINE_MAX_SHARE = 0.25


def fine_k_problem(k: int, n: int) -> str | None:
    """Why a fine map of ``k`` modes cannot be asked of shapes whose smaller has ``n``
    vertices (None if it can); see :data:`FINE_MAX_SHARE`."""
    top = int(FINE_MAX_SHARE * n)
    if k <= top:
        return None
    return (f"{k} eigenmodes is more than a quarter of the {n} vertices of the smaller shape: "
            f"such modes describe the mesh more than the shape, and the cost grows quickly "
            f"(1000 modes take ~1 min at 5k vertices); ask for at most {top} (200 is the "
            "default of --fine)")


def cotmatrix_scipy(V: np.ndarray, F: np.ndarray) -> sp.csr_matrix:
    """Cotangent stiffness matrix (positive semidefinite), scipy CSR.

    Parameters
    ----------
    V : numpy.ndarray of float64, shape (n, 3)
    F : numpy.ndarray of int64, shape (m, 3)

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, n)
        ``W[i, j] = -(cot a_ij + cot b_ij) / 2`` on edges, ``W[i, i] = -sum_j W[i, j]``.

    Examples
    --------
    >>> import numpy as np
    >>> W = cotmatrix_scipy(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    >>> round(float(W[1, 2]), 6)  # right angle at vertex 0: cot 90 = 0
    0.0
    """
    n = V.shape[0]
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j, o = F[:, (k + 1) % 3], F[:, (k + 2) % 3], F[:, k]
        e1 = V[i] - V[o]
        e2 = V[j] - V[o]
        cross = np.linalg.norm(np.cross(e1, e2), axis=1)
        cot = np.einsum("ij,ij->i", e1, e2) / np.maximum(cross, 1e-300)
        rows += [i, j]
        cols += [j, i]
        vals += [-0.5 * cot, -0.5 * cot]
    r = np.concatenate(rows)
    c = np.concatenate(cols)
    v = np.concatenate(vals)
    W = sp.csr_matrix((v, (r, c)), shape=(n, n))
    W = W - sp.diags(np.asarray(W.sum(axis=1)).ravel())
    W.sum_duplicates()
    return W.tocsr()


def massmatrix_scipy(V: np.ndarray, F: np.ndarray, kind: str) -> sp.csr_matrix:
    """Mass matrix, scipy CSR: ``"lumped"`` (a third of each incident area) or ``"consistent"``.

    Parameters
    ----------
    V : numpy.ndarray of float64, shape (n, 3)
    F : numpy.ndarray of int64, shape (m, 3)
    kind : {"lumped", "consistent"}

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, n)

    Examples
    --------
    >>> import numpy as np
    >>> M = massmatrix_scipy(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]),
    ...                      np.array([[0, 1, 2]]), "lumped")
    >>> M.diagonal().round(4).tolist()
    [0.1667, 0.1667, 0.1667]
    """
    n = V.shape[0]
    fa = face_areas(V, F)
    if kind == "lumped":
        # float64 even when F is empty (bincount then returns int64, and scipy warns)
        d = np.bincount(F.ravel(), weights=np.repeat(fa / 3.0, 3), minlength=n).astype(float)
        return sp.diags(d).tocsr()
    if kind == "consistent":
        r = np.concatenate([F[:, a] for a in range(3) for _ in range(3)])
        c = np.concatenate([F[:, b] for _ in range(3) for b in range(3)])
        w = np.concatenate(
            [fa / 6.0 if a == b else fa / 12.0 for a in range(3) for b in range(3)]
        )
        return sp.csr_matrix((w, (r, c)), shape=(n, n))
    raise ValueError(f"unknown mass kind {kind!r}; use 'lumped' or 'consistent'")


class EigensolverError(ValueError):
    """The eigensolve failed on every path (see :func:`eigenpairs`); the message says why.

    A ``ValueError`` so that the command line reports it in one line, like a bad mesh: in
    practice it is one (coincident vertices, slivers, non-finite coordinates).
    """


#: Largest matrix solved densely when the sparse solvers fail (about 20 s and 0.6 GB at 6k).
DENSE_FALLBACK = 6000

_SHIFTS = (0.01, 1.0)  # shift-invert about -shift: the default, then a safer factorisation
_DETECT_TOL = 1e-3  # tolerance of the cheap run that looks for missed modes (_complete)


def eigenpairs(W: sp.spmatrix, A: sp.spmatrix, k: int,
               known: tuple[np.ndarray, np.ndarray] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """The ``k`` smallest eigenpairs of ``W phi = lambda A phi`` (A-orthonormal ``phi``).

    Parameters
    ----------
    W : scipy.sparse matrix, shape (m, m)
        Symmetric positive semidefinite stiffness.
    A : scipy.sparse matrix, shape (m, m)
        Symmetric positive definite mass (diagonal or consistent).
    k : int
        Number of eigenpairs (clamped to ``1 .. m``).
    known : (lam, phi), optional
        The first ``k0 < k`` eigenpairs of the same problem, solved before (a larger basis
        for ``match(fine_k=K)``). On the sparse path with a lumped mass they are kept as given,
        and only the ``k - k0`` next ones are solved, with the known vectors deflated
        (:func:`_extend`; cheaper than solving all ``k``: ``scripts/bench.py fine``,
        BENCHMARKS.md). Otherwise (a problem small enough for the dense solve, a consistent
        mass), or if a new eigenvalue lies below the known ones, all ``k`` are solved again.

    Returns
    -------
    lam : numpy.ndarray, shape (k,)
        Ascending, clipped at 0.
    phi : numpy.ndarray, shape (m, k)
        ``phi.T @ A @ phi = I``.

    Raises
    ------
    EigensolverError
        Non-finite matrices, or every path below failed (the message lists why).

    Notes
    -----
    Small problems (``m <= max(300, 2k + 1)``) use dense ``scipy.linalg.eigh``. A diagonal
    mass uses the symmetric form ``S = A^-1/2 W A^-1/2`` in shift-invert about -0.01 with one
    sparse LU (``splu``) and ARPACK at relative tolerance :data:`ARPACK_TOL` with a Lanczos
    basis of ``max(1.5 k, k + 20)`` vectors: the backward error ``|S psi - lam psi|`` is at
    most ``ARPACK_TOL |S|``, eigenvalues agree with machine-precision ARPACK to ~4e-15 of
    ``lambda_k``. Cost for k = 100 on a 12.5k-vertex mesh: about 250 solves, 0.6 s with two
    BLAS threads, 0.9 s with one.

    Lanczos can miss copies of an eigenvalue of high multiplicity (an exactly symmetric mesh:
    8 copies on a flat torus, ``2l + 1`` on a round sphere), which would silently drop modes
    below ``lambda_k``. So the solve is completed: the largest eigenvalues of the shifted
    inverse *deflated* by the found vectors are computed (a second, small ARPACK run, ~10 %
    of the first); any above ``1 / (lambda_k + shift)`` is a missed mode, added, and the
    check repeated.

    Fallbacks, never a silently wrong result: a singular factorisation is retried about
    -1.0; ARPACK not converging is retried from a random start with a ``2k + 1`` basis,
    then by LOBPCG preconditioned with the factorisation; non-finite results count as a
    failure; the last resort for ``m <= DENSE_FALLBACK`` is the dense solve. A consistent
    mass uses the generalized shift-invert mode of ``eigsh`` (dense fallback only).

    Examples
    --------
    >>> import numpy as np, trimesh
    >>> s = trimesh.creation.icosphere(2)
    >>> V, F = s.vertices, s.faces
    >>> lam, phi = eigenpairs(cotmatrix_scipy(V, F), massmatrix_scipy(V, F, "lumped"), 3)
    >>> bool(np.allclose(phi.T @ massmatrix_scipy(V, F, "lumped") @ phi, np.eye(3)))
    True
    """
    m = W.shape[0]
    k = int(max(1, min(k, m)))
    W, A = sp.csr_matrix(W), sp.csr_matrix(A)
    if not (np.isfinite(W.data).all() and np.isfinite(A.data).all()):
        raise EigensolverError(
            "the Laplacian has non-finite entries (coincident vertices or zero-area triangles?)"
            "; remove degenerate faces and merge duplicate vertices first"
        )
    if m <= max(300, 2 * k + 1) or k >= m - 1:
        return _dense(W, A, k)
    failures: list[str] = []
    lumped = A.nnz == m and bool((A.diagonal() > 0).all())
    if known is not None and lumped and 0 < np.asarray(known[0]).size < k:
        extended = _extend(W, A, np.asarray(known[0], dtype=np.float64),
                           np.asarray(known[1], dtype=np.float64), k, failures)
        if extended is not None:
            return extended
    if lumped:
        result = _lumped(W, A, k, failures)
    else:
        result = None
        try:
            lam, phi = sla.eigsh(W, k=k, M=A, sigma=-0.01, which="LM", v0=np.ones(m))
            order = np.argsort(lam)
            result = _finite(lam[order], phi[:, order], failures, "generalized ARPACK")
        except (sla.ArpackError, RuntimeError, np.linalg.LinAlgError) as exc:
            failures.append(f"generalized ARPACK: {exc}")
    if result is None:
        if m > DENSE_FALLBACK:
            raise EigensolverError(
                f"the eigensolve failed ({'; '.join(failures)}); the mesh is probably badly "
                "conditioned (slivers or near-coincident vertices): remesh or clean it"
            )
        warnings.warn(f"sparse eigensolve failed ({'; '.join(failures)}); solved densely",
                      RuntimeWarning, stacklevel=2)
        return _dense(W, A, k)
    lam, phi = result
    return np.maximum(lam, 0.0), phi


def _dense(W: sp.spmatrix, A: sp.spmatrix, k: int) -> tuple[np.ndarray, np.ndarray]:
    import scipy.linalg

    try:
        lam, phi = scipy.linalg.eigh(W.toarray(), A.toarray(), subset_by_index=(0, k - 1))
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise EigensolverError(f"the dense eigensolve failed ({exc}); the mass matrix is not "
                               "positive definite (zero-area triangles?)") from exc
    if not (np.isfinite(lam).all() and np.isfinite(phi).all()):
        raise EigensolverError("the dense eigensolve returned non-finite values")
    return np.maximum(lam, 0.0), phi


def _finite(lam: np.ndarray, phi: np.ndarray, failures: list[str],
            what: str) -> tuple[np.ndarray, np.ndarray] | None:
    if np.isfinite(lam).all() and np.isfinite(phi).all():
        return lam, phi
    failures.append(f"{what}: non-finite result")
    return None


def _symmetric_form(W: sp.csr_matrix, A: sp.csr_matrix) -> tuple[sp.csc_matrix, np.ndarray]:
    """``S = A^-1/2 W A^-1/2`` of a lumped (diagonal) mass, and ``A^-1/2``'s diagonal: the
    eigenvectors ``psi`` of ``S`` are ``A^1/2 phi``."""
    isq = 1.0 / np.sqrt(A.diagonal())
    D = sp.diags(isq)
    return (D @ W @ D).tocsc(), isq


def _shifted_lu(S: sp.csc_matrix, shift: float) -> Any:
    """Sparse LU of ``S + shift I`` (``RuntimeError`` if singular). It is symmetric positive
    definite: a symmetric fill-reducing ordering with diagonal pivots (40 % less fill than the
    default column ordering, 25 % faster eigensolves on SCAPE's 12.5k vertices; eigenpairs
    equal to 4e-12)."""
    return sla.splu((S + shift * sp.eye(S.shape[0], format="csc")).tocsc(),
                    permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                    options={"SymmetricMode": True})


def _lumped(W: sp.csr_matrix, A: sp.csr_matrix, k: int,
            failures: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
    """Lumped mass: ARPACK on the symmetric form, with fallbacks; None if all failed."""
    # S = A^-1/2 W A^-1/2 in shift-invert about a small negative shift (S + shift I is
    # positive definite), one sparse LU, and phi = A^-1/2 psi. Same eigenpairs as the
    # generalized problem to rounding, and ~20 % faster: no mass products inside ARPACK.
    m = W.shape[0]
    S, isq = _symmetric_form(W, A)
    lu = None
    for shift in _SHIFTS:
        try:
            lu = _shifted_lu(S, shift)
            break
        except RuntimeError as exc:  # "Factor is exactly singular"
            failures.append(f"LU of S + {shift} I: {exc}")
    if lu is None:
        return None
    op = sla.LinearOperator((m, m), matvec=lu.solve, dtype=np.float64)
    attempts = (
        # tol ARPACK_TOL (relative, on 1 / (lambda + shift)) instead of machine precision
        # and a 1.5k Lanczos basis instead of 2k + 1: 25 % faster on 10k-vertex meshes, the
        # eigenvalues unchanged to 4e-15 of lambda_k (measured on SCAPE)
        ("ARPACK", np.ones(m), min(m, max(k + k // 2, k + 20))),
        ("ARPACK (random start, 2k+1 basis)",
         np.random.default_rng(0).standard_normal(m), min(m, 2 * k + 1)),
    )
    for what, v0, ncv in attempts:
        found = _shift_invert_arpack(op, k, v0, ncv, shift, what, failures)
        if found is not None:
            return found[0], found[1] * isq[:, None]
    # LOBPCG preconditioned with the factorisation (block inverse iteration, accelerated)
    try:
        x0 = np.random.default_rng(1).standard_normal((m, k))
        gersh = float(np.max(abs(S).sum(axis=1)))
        with warnings.catch_warnings():  # its own accuracy report; checked below
            warnings.simplefilter("ignore", UserWarning)
            lam, psi = sla.lobpcg(S, x0, M=op, largest=False, tol=0.1 * SOLVER_TOL * gersh,
                                  maxiter=200)
    except (np.linalg.LinAlgError, ValueError, RuntimeError) as exc:
        failures.append(f"LOBPCG: {exc}")
        return None
    if _finite(lam, psi, failures, "LOBPCG") is None:
        return None
    res = np.linalg.norm(S @ psi - psi * lam, axis=0)
    if float(res.max()) > SOLVER_TOL * gersh:
        failures.append(f"LOBPCG: not converged (residual {float(res.max()) / gersh:.1e} |S|)")
        return None
    order = np.argsort(lam)
    return lam[order], psi[:, order] * isq[:, None]


def _extend(W: sp.csr_matrix, A: sp.csr_matrix, lam0: np.ndarray, phi0: np.ndarray, k: int,
            failures: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
    """Lumped mass: the ``k`` smallest eigenpairs given the first ``k0`` (:func:`eigenpairs`'s
    ``known``), the next ``k - k0`` solved by ARPACK on the shifted inverse of the symmetric
    form with the known vectors projected out (the same factorisation, tolerance and
    completion as :func:`_lumped`, a Lanczos basis for ``k - k0`` vectors instead of ``k``).
    None (solve all again) when a step fails or a new eigenvalue lies below the known ones
    by more than ``1e-8`` of them: the known set was not the lowest."""
    if phi0.ndim != 2 or phi0.shape != (W.shape[0], lam0.size) or lam0.ndim != 1:
        return None  # not pairs of this problem: solve all
    m, k0 = phi0.shape
    S, isq = _symmetric_form(W, A)
    psi0 = phi0 / isq[:, None]  # orthonormal eigenvectors of S
    shift = _SHIFTS[0]
    try:
        lu = _shifted_lu(S, shift)
    except RuntimeError as exc:
        failures.append(f"LU of S + {shift} I (extension): {exc}")
        return None

    def deflated(x: np.ndarray) -> np.ndarray:
        x = x - psi0 @ (psi0.T @ x)
        y = lu.solve(x)
        return y - psi0 @ (psi0.T @ y)

    op = sla.LinearOperator((m, m), matvec=deflated, dtype=np.float64)
    kn = k - k0
    from threadpoolctl import threadpool_limits

    # one BLAS thread: each of the thousands of matrix-vector products projects twice
    # against k0 vectors, products too small to split (two threads: 4x slower on TOSCA 5k)
    with threadpool_limits(1, user_api="blas"):
        found = _shift_invert_arpack(op, kn, deflated(np.ones(m)),
                                     min(m, max(kn + kn // 2, kn + 20)), shift,
                                     "ARPACK (extension)", failures)
    if found is None:
        return None
    lam, psi = found
    top = float(lam0.max())
    if float(lam.min()) < top - 1e-8 * max(abs(top), 1e-12):
        failures.append("extension: a new eigenvalue below the known ones")
        return None
    return (np.concatenate([lam0, np.maximum(lam, 0.0)]),
            np.concatenate([phi0, psi * isq[:, None]], axis=1))


def _shift_invert_arpack(op: sla.LinearOperator, k: int, v0: np.ndarray, ncv: int,
                         shift: float, what: str, failures: list[str]
                         ) -> tuple[np.ndarray, np.ndarray] | None:
    """The ``k`` largest eigenpairs of ``op = (S + shift I)^-1`` by ARPACK, completed
    (:func:`_complete`), as eigenpairs of ``S`` in ascending order: ``(lam, psi)``; None (the
    reason appended to ``failures`` under ``what``) if ARPACK fails or returns non-finite
    values."""
    try:
        mu, psi = sla.eigsh(op, k=k, which="LM", v0=v0, tol=ARPACK_TOL, ncv=ncv)
    except (sla.ArpackError, RuntimeError) as exc:  # ArpackNoConvergence included
        failures.append(f"{what}: {exc}")
        return None
    if _finite(mu, psi, failures, what) is None:
        return None
    mu, psi = _complete(op, mu, psi)
    lam = 1.0 / mu - shift
    order = np.argsort(lam)
    return lam[order], psi[:, order]


def _complete(op: sla.LinearOperator, mu: np.ndarray, psi: np.ndarray,
              rounds: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """Add the modes Lanczos missed (copies of a multiple eigenvalue), see :func:`eigenpairs`.

    ``op`` is ``(S + shift I)^-1``; ``mu``/``psi`` its found eigenpairs (largest ``mu``). The
    largest eigenvalues of ``P op P`` (``P`` projects out ``psi``) above ``min(mu)`` are modes
    below ``lambda_k`` that were missed; they replace the smallest ``mu``.
    """
    m: int  # (numpy's stubs type shape entries as Any, and standard_normal(Any) as a float)
    m, k = psi.shape
    rng = np.random.default_rng(2)
    for _ in range(rounds):
        basis = psi

        def deflated(x: np.ndarray, basis: np.ndarray = basis) -> np.ndarray:
            x = x - basis @ (basis.T @ x)
            y = op.matvec(x)
            return y - basis @ (basis.T @ y)

        if m - k < 12:
            break
        v0 = deflated(rng.standard_normal(m))
        defl = sla.LinearOperator((m, m), matvec=deflated, dtype=np.float64)
        try:
            # detection: Ritz values never exceed the deflated spectrum's top, which is
            # 1 / (lambda_k+1 + shift) <= min(mu) when nothing was missed, so a loose
            # tolerance cannot raise a false alarm; a missed mode is then solved exactly
            nu, chi = sla.eigsh(defl, k=1, which="LA", v0=v0, tol=_DETECT_TOL, ncv=10)
            if float(nu.max()) <= float(mu.min()) * (1.0 + 1e-8):
                break
            nu, chi = sla.eigsh(defl, k=2, which="LA", v0=chi[:, 0], tol=ARPACK_TOL,
                                ncv=min(m, 12))
        except (sla.ArpackError, RuntimeError):
            break  # the main solve stands; the check is best effort
        new = nu > float(mu.min()) * (1.0 + 1e-8)
        if not new.any():
            break
        chi = chi[:, new] - psi @ (psi.T @ chi[:, new])
        chi, _ = np.linalg.qr(chi)
        mu = np.concatenate([mu, nu[new]])
        psi = np.concatenate([psi, chi], axis=1)
        keep = np.argsort(-mu)[:k]
        mu, psi = mu[keep], psi[:, keep]
    return mu, psi


def cotan_eigenpairs(V: Any, F: Any, k: int = 100,
                     known: tuple[np.ndarray, np.ndarray] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Eigenpairs of a mesh's default operator: cotangent, lumped mass at unit area, Neumann.

    The same operator as ``torchheat.laplacian(mesh)`` and the same solve as
    ``HeatKernel(mesh, k=k)``, from plain arrays and without torch (tested to be identical).
    The arrays are not validated: pass those of a valid mesh (:func:`torchheat.meshio.
    read_arrays` output is checked by :class:`~torchheat.mesh.Mesh`, and eigenpairs handed to
    :class:`~torchheat.heat.HeatKernel` are checked against its operator).

    Parameters
    ----------
    V : array_like of float, shape (n, 3)
    F : array_like of int, shape (m, 3)
    k : int
    known : (lam, phi), optional
        Fewer eigenpairs of the same mesh solved before: kept, and only the rest solved
        (:func:`eigenpairs`).

    Returns
    -------
    lam : numpy.ndarray, shape (k,)
    phi : numpy.ndarray, shape (n, k)

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(2)
    >>> lam, phi = cotan_eigenpairs(s.vertices, s.faces, k=4)  # smooth unit sphere: 8 pi = 25.1
    >>> lam.round(1).tolist()
    [0.0, 24.7, 24.7, 24.7]
    """
    V = np.ascontiguousarray(V, dtype=np.float64)
    F = np.ascontiguousarray(F, dtype=np.int64)
    W = cotmatrix_scipy(V, F)
    M = massmatrix_scipy(V, F, "lumped")
    M = (M / float(M.sum())).tocsr()
    return eigenpairs(W.tocsr(), M.tocsr(), k, known=known)


# ------------------------------------------------------------------------------------------
# background processes
# ------------------------------------------------------------------------------------------
def _available_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # not Linux
        return os.cpu_count() or 1


def _lenders(jobs: Sequence[tuple[int, np.ndarray, np.ndarray, int]]) -> dict[int, int]:
    """For each job, the earlier job of the same mesh with the most pairs below its own (the
    latest of equals): job -> lender; jobs with none are left out."""
    out: dict[int, int] = {}
    for j, (_, V, F, k) in enumerate(jobs):
        best = -1
        for j0 in range(j):
            _, V0, F0, k0 = jobs[j0]
            if (k0 < k and (best < 0 or k0 >= jobs[best][3]) and np.array_equal(V0, V)
                    and np.array_equal(F0, F)):
                best = j0
        if best >= 0:
            out[j] = best
    return out


def _solve_in_child(conn: Any, jobs: list[tuple[int, np.ndarray, np.ndarray, int]],
                    nice: int = 0) -> None:
    # one BLAS thread: the other core runs the parent (or another worker); two OpenBLAS
    # threads per process on two cores made eigensolves 5-10x slower (measured)
    if nice > 0:
        with contextlib.suppress(OSError):  # best effort: a scheduling hint, not a need
            os.nice(nice)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except Exception:  # pragma: no cover - threadpoolctl is a dependency
        pass
    # results go out from a thread of their own: a pipe holds 64 KB, so a send blocks until
    # the parent reads, and the parent reads only after ``import torch``; the next solve must
    # not wait for that
    outbox: queue.SimpleQueue = queue.SimpleQueue()
    gone = threading.Event()

    def send_all() -> None:
        try:
            while (item := outbox.get()) is not None:
                conn.send(item)
        except (OSError, EOFError):  # the parent has gone: nobody reads the rest
            gone.set()

    sender = threading.Thread(target=send_all, daemon=True, name="torchheat-eigen-send")
    sender.start()
    # a mesh this worker solved before (the command line's --fine: the default basis, then a
    # larger one of the same mesh) lends its pairs: only the rest are solved. A result is held
    # only while a later job of this worker is the same mesh with more pairs, so a long job
    # list does not keep every basis it solved
    lender = _lenders(jobs)
    last_use = {j0: j for j, j0 in lender.items()}  # ascending j: the last one stays
    held: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for j, (i, V, F, k) in enumerate(jobs):
        if gone.is_set():
            break
        try:
            known = held.get(lender.get(j, -1))
            lam, phi = cotan_eigenpairs(V, F, k, known=known)
            if j in last_use:
                held[j] = (lam, phi)
            outbox.put((i, "ok", lam, phi))
        except BaseException as exc:  # report, the parent solves it itself
            outbox.put((i, "error", repr(exc), None))
        for j0 in [j0 for j0 in held if last_use[j0] <= j]:
            del held[j0]
    outbox.put(None)
    sender.join()
    conn.close()


class EigenWorkers:
    """Eigenpairs of several meshes, solved in forked worker processes while you do other work.

    ``EigenWorkers([(V0, F0), (V1, F1)], k=100)`` starts up to ``processes`` workers (default:
    one per mesh, at most the number of usable CPUs) that compute :func:`cotan_eigenpairs`
    of each mesh; :meth:`get` waits for mesh ``i`` and returns ``(lam, phi)``, or None if
    no worker ran or it failed (the caller then solves in-process, so a result is never
    wrong, at worst late). Workers use one BLAS thread each.

    Workers are started with ``fork`` and only on Linux (elsewhere, or with one CPU, or with
    ``processes=0``, nothing is started and :meth:`get` returns None). Start them *before*
    importing torch: forking a process whose torch thread pools are running is unsafe, and
    the point is to overlap the ~1 s of ``import torch`` with the solves.

    Parameters
    ----------
    meshes : sequence of (V, F)
        Arrays of shape (n_i, 3) and (m_i, 3). A mesh may appear twice with different ``k``
        (the command line's ``--fine`` solves a larger basis after the default one).
    k : int or sequence of int
        Eigenpairs per mesh (one number for all, or one per mesh).
    processes : int, optional
        Worker processes (0: none).
    timeout : float, optional
        Seconds :meth:`get` waits for a worker's next result before it stops that worker and
        returns None (the caller then solves in-process): a guard against a worker stuck at
        fork, never expected to fire. Default ``120 + 1e-3 * n`` for the largest mesh (one
        60k-vertex solve takes ~7 s).
    nice : int, optional
        Added to the workers' nice value (``os.nice``; 0: as the parent). A caller whose own
        work meanwhile is what it waits on first (the command line's ``import torch``) gives
        its workers a lower priority: they still get every cycle it leaves (measured in
        BENCHMARKS.md, twenty-eighth session).

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(2)
    >>> with EigenWorkers([(s.vertices, s.faces)], k=5) as bg:
    ...     res = bg.get(0)
    >>> res is None or res[1].shape == (162, 5)
    True
    """

    def __init__(self, meshes: Sequence[tuple[Any, Any]], k: int | Sequence[int] = 100,
                 processes: int | None = None, timeout: float | None = None,
                 nice: int = 0) -> None:
        ks = [int(k)] * len(meshes) if isinstance(k, (int, np.integer)) else [int(x) for x in k]
        if len(ks) != len(meshes):
            raise ValueError(f"k has {len(ks)} entries for {len(meshes)} meshes")
        self.k = ks
        n_max = max((len(V) for V, _ in meshes), default=0)
        self.timeout = 120.0 + 1e-3 * n_max if timeout is None else float(timeout)
        self._results: dict[int, tuple[np.ndarray, np.ndarray] | None] = {}
        self._procs: list[Any] = []
        self._conns: list[Any] = []
        self._owner: dict[int, int] = {}
        self.errors: dict[int, str] = {}
        n = len(meshes)
        if processes is None:
            cpus = _available_cpus()
            processes = min(n, cpus) if cpus >= 2 else 0
        processes = max(0, min(int(processes), n))
        if processes == 0 or not sys.platform.startswith("linux"):
            return
        import multiprocessing as mp

        try:
            ctx = mp.get_context("fork")
        except ValueError:  # pragma: no cover - fork is always there on Linux
            return
        jobs: list[list[tuple[int, np.ndarray, np.ndarray, int]]] = [
            [] for _ in range(processes)]
        for i, (V, F) in enumerate(meshes):
            jobs[i % processes].append((i, np.asarray(V), np.asarray(F), ks[i]))
            self._owner[i] = i % processes
        with warnings.catch_warnings():
            # Python >= 3.12 warns on fork() in a process with threads (OpenBLAS's idle
            # pool, which registers its own fork handlers); torch is not imported yet
            warnings.simplefilter("ignore", DeprecationWarning)
            for w in range(processes):
                recv, send = ctx.Pipe(duplex=False)
                proc = ctx.Process(target=_solve_in_child, args=(send, jobs[w], int(nice)),
                                   daemon=True, name=f"torchheat-eigen-{w}")
                proc.start()
                send.close()
                self._procs.append(proc)
                self._conns.append(recv)

    @property
    def running(self) -> int:
        """Number of worker processes started."""
        return len(self._procs)

    def get(self, i: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Wait for mesh ``i``: ``(lam, phi)`` with shapes (k,), (n_i, k), or None.

        Parameters
        ----------
        i : int
            Index of the mesh in the list given to the constructor.
        """
        if i in self._results:
            return self._results[i]
        w = self._owner.get(i)
        if w is None:
            return None
        conn = self._conns[w]
        while i not in self._results:
            try:
                if not conn.poll(self.timeout):  # stuck (or far slower than expected)
                    self._procs[w].terminate()
                    raise EOFError
                j, status, a, b = conn.recv()
            except (EOFError, OSError):  # the worker died: solve in-process
                for m, owner in self._owner.items():
                    if owner == w:
                        self._results.setdefault(m, None)
                self.errors.setdefault(i, "worker stopped or timed out")
                break
            if status == "ok":
                self._results[j] = (a, b)
            else:
                self.errors[j] = a
                self._results[j] = None
        return self._results.get(i)

    def close(self) -> None:
        """Stop the workers (results not yet received are dropped)."""
        for conn in self._conns:
            conn.close()
        for proc in self._procs:
            if proc.is_alive():
                proc.terminate()
            proc.join(timeout=5)
        self._procs, self._conns = [], []

    def __enter__(self) -> EigenWorkers:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
