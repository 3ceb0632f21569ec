"""The heat kernel solver :class:`HeatKernel`: set-up (operator, eigenbasis, spectral bound),
the plan (which times the eigenbasis serves, the Chebyshev degree of the others), and the
dispatch of :meth:`HeatKernel.columns` to :mod:`.spectral`, :mod:`.chebyshev` and
:mod:`.certify`. See :mod:`torchheat.heat` for the conventions.
"""

from __future__ import annotations

import copy
import math
import threading
import time
import warnings
from collections.abc import Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
import torch

from .._arrays import integral, to_numpy
from ..eigen import EigensolverError, eigenpairs
from ..mesh import Mesh
from ..operators import Boundary, Kind, Laplacian, laplacian, scipy_to_torch
from . import chebyshev
from .certify import column_norms, relative_bound
from .chebyshev import (
    _chebyshev_block,
    _flush_denormal,
    chebyshev_columns,
    chebyshev_degree,
    chebyshev_tail,
    lambda_max_bound,
)
from .spectral import _check_eigenpairs, spectral_columns

__all__ = ["HeatKernel", "default_times", "threads"]


def default_times(n: int = 10, t_min: float = 1e-3, t_max: float = 2.0) -> torch.Tensor:
    """Log-spaced time samples (the paper's default: 10 in [0.001, 2] at unit area).

    Parameters
    ----------
    n : int
        Number of samples J.
    t_min, t_max : float
        Range, in units of the unit-area shape.

    Returns
    -------
    torch.Tensor
        float64 tensor of shape (n,), ascending.

    Examples
    --------
    >>> default_times()[[0, -1]].tolist()
    [0.001, 2.0]
    """
    return torch.logspace(math.log10(t_min), math.log10(t_max), n, dtype=torch.float64)


@contextmanager
def threads(n: int | None):
    """Temporarily set torch's intra-op thread count (``None`` leaves it unchanged).

    With another process busy, two threads on a 2-core machine ran 3x slower than one, so the
    thread count is exposed on every solver.

    Examples
    --------
    >>> with threads(1):
    ...     torch.get_num_threads()
    1
    """
    if n is None:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(int(n))
    try:
        yield
    finally:
        torch.set_num_threads(old)


_BLAS_LOCK = threading.Lock()
_BLAS_HELD: dict = {"depth": 0, "limiter": None}  # blas_threads: users in the process


@contextmanager
def blas_threads(n: int | None):
    """Temporarily limit numpy's and scipy's BLAS (OpenBLAS, MKL) to ``n`` threads (``None``
    leaves them unchanged), through ``threadpoolctl``; torch's own threads are :func:`threads`.

    The matching stages run their heavy work in torch and call BLAS from numpy on small
    matrices only; there, BLAS threads that busy-wait between calls take the cores from
    torch's threads and from the background thread (:func:`torchheat.match`, ``background``;
    measured in BENCHMARKS.md, "One BLAS thread inside match"). BLAS's thread count is one
    setting for the whole process: nested and concurrent uses (a match's background thread,
    matches run from several threads) share the first one's limit, and the original counts
    come back when the last one leaves.

    Examples
    --------
    >>> import numpy as np
    >>> with blas_threads(1):
    ...     float(np.ones((2, 2)) @ np.ones(2) @ np.ones(2))
    4.0
    """
    if n is None:
        yield
        return
    from threadpoolctl import threadpool_limits

    with _BLAS_LOCK:
        if _BLAS_HELD["depth"] == 0:
            _BLAS_HELD["limiter"] = threadpool_limits(limits=int(n), user_api="blas")
        _BLAS_HELD["depth"] += 1
    try:
        yield
    finally:
        with _BLAS_LOCK:
            _BLAS_HELD["depth"] -= 1
            if _BLAS_HELD["depth"] == 0:
                _BLAS_HELD["limiter"].restore_original_limits()
                _BLAS_HELD["limiter"] = None


@dataclass
class _Plan:
    spectral: np.ndarray  # bool [J]
    degree: np.ndarray  # int [J] Chebyshev degree (0 for spectral times)
    timings: dict = field(default_factory=dict)


def _checked_times(times: Sequence[float] | torch.Tensor) -> torch.Tensor:
    """``times`` as a flat float64 tensor, refused unless non-empty, positive and finite
    (a NaN passed the positivity test and failed later as "cannot convert float NaN")."""
    t = torch.as_tensor(times, dtype=torch.float64).reshape(-1)
    if t.numel() == 0 or not bool((torch.isfinite(t) & (t > 0)).all()):
        raise ValueError(f"times must be a non-empty list of positive finite numbers, got "
                         f"{t[:5].tolist()}{' ...' if t.numel() > 5 else ''}")
    return t


class HeatKernel:
    """Heat kernel solver for one shape: precompute once, query many sources.

    Parameters
    ----------
    mesh : Mesh or Laplacian
        The shape (an operator is built with ``kind`` / ``boundary``) or a ready operator.
    times : sequence of float, optional
        Time samples ``t_j`` on the unit-area shape; default :func:`default_times` (10
        log-spaced in [0.001, 2]).
    rtol : float
        Relative L2 error allowed per column and time (default 1e-6); guaranteed by an
        a-posteriori bound for every returned column.
    method : {"auto", "hybrid", "chebyshev", "spectral"}
        ``"hybrid"``: eigenbasis where its truncation meets ``rtol``, Chebyshev elsewhere.
        ``"chebyshev"``: Chebyshev for every time. ``"spectral"``: eigenbasis only, **no**
        accuracy guarantee (truncation error reported in :attr:`error_bound`). ``"auto"`` is
        ``"hybrid"`` (``"spectral"`` for ``kind="fem"``, whose mass is not diagonal).
    k : int, optional
        Number of eigenpairs (default ``min(n - 1, 40)``; the eigenbasis also serves
        :meth:`hks`). More eigenpairs move more times to the cheap spectral path but cost a
        longer eigensolve.
    kind, boundary : str
        Passed to :func:`torchheat.laplacian` when ``mesh`` is a Mesh.
    dtype : torch.dtype
        ``torch.float64`` (default) or ``torch.float32``. In float32 the Chebyshev recurrence
        loses about ``degree * 6e-8`` (1e-5 to 1e-4 at t = 2 on 10k–40k meshes), so ``rtol``
        below 1e-4 cannot be honoured and a warning is raised; denormals are flushed during
        the recurrence (they slowed one float32 run 14x).
    device : str or torch.device
        Where the recurrence and products run (``"cpu"`` default; ``"cuda"`` works too).
    block : int
        Sources per Chebyshev block (default 64; 256 columns cost 5–12x what 64 do on CPU
        because of cache misses); fewer on large meshes, so that a block's working set stays
        within ``CHEBYSHEV_BYTES`` (1 GiB; 8 sources of a 300k-vertex mesh at 10 times).
    num_threads : int, optional
        torch intra-op threads during queries (default: torch's setting).
    eigenpairs : tuple (eigenvalues [k], eigenvectors [n, k]), optional
        Precomputed mass-orthonormal eigenpairs of this operator (e.g. from a disk cache,
        :attr:`eigenvalues` / :attr:`eigenvectors` of an earlier solver); skips the eigensolve.
    lambda_max : float, optional
        Precomputed upper bound of the spectrum (:attr:`lambda_max`); skips the Lanczos run.

    Attributes
    ----------
    times : torch.Tensor, shape (J,)
    laplacian : Laplacian
    lambda_max : float
        Upper bound of the spectrum of ``S`` used by Chebyshev.
    eigenvalues : torch.Tensor, shape (k,)
    eigenvectors : torch.Tensor, shape (n, k)
        Mass-orthonormal eigenfunctions ``phi`` (``phi^T A phi = I``), zero on Dirichlet
        boundary vertices.
    error_bound : torch.Tensor, shape (B, J)
        Relative error bound of each column of the last :meth:`columns` call.

    Notes
    -----
    Cost on a 10k-vertex unit-area mesh (2 cores): set-up (operator, ``lambda_max``, 40
    eigenpairs) about 0.4 s; 64 columns for 10 times about 0.3 s in float64 at 1e-6. The
    Chebyshev-only path costs ``O(nnz * B * sqrt(t_max lambda_max))``.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> sphere = trimesh.creation.icosphere(3)
    >>> hk = HeatKernel(Mesh(sphere.vertices, sphere.faces))
    >>> hk.columns([0, 5]).shape
    torch.Size([2, 642, 10])
    >>> bool(hk.error_bound.max() <= 1e-6)
    True
    """

    def __init__(
        self,
        mesh: Mesh | Laplacian,
        times: Sequence[float] | torch.Tensor | None = None,
        rtol: float = 1e-6,
        *,
        method: str = "auto",
        k: int | None = None,
        kind: Kind = "cotan",
        boundary: Boundary = "neumann",
        dtype: torch.dtype = torch.float64,
        device: str | torch.device = "cpu",
        block: int = 64,
        num_threads: int | None = None,
        eigenpairs: tuple | None = None,
        lambda_max: float | None = None,
    ) -> None:
        t0 = time.perf_counter()
        if isinstance(mesh, Laplacian):
            self.laplacian = mesh
            self.mesh = None
        else:
            self.laplacian = laplacian(mesh, kind=kind, boundary=boundary)
            self.mesh = mesh
        lap = self.laplacian
        if not lap.normalized:
            raise ValueError("HeatKernel expects a unit-area operator (laplacian(normalize=True))")
        self.times = _checked_times(default_times() if times is None else times)
        if rtol <= 0:
            raise ValueError("rtol must be positive")
        if method == "auto":
            method = "hybrid" if lap.lumped else "spectral"
        if method not in ("hybrid", "chebyshev", "spectral"):
            raise ValueError(
                f"unknown method {method!r}; use 'auto', 'hybrid', 'chebyshev' or 'spectral'"
            )
        if not lap.lumped and method != "spectral":
            raise ValueError(
                "kind='fem' has a consistent mass: only method='spectral' applies "
                "(use kind='cotan' for the certified Chebyshev/hybrid paths)"
            )
        if dtype not in (torch.float32, torch.float64):
            raise ValueError("dtype must be torch.float32 or torch.float64")
        if dtype == torch.float32 and rtol < 1e-4:
            import warnings

            warnings.warn(
                f"float32 Chebyshev recurrences reach about 1e-5..1e-4, not rtol={rtol:g}; "
                "the error bound reported ignores rounding",
                stacklevel=2,
            )
        self.rtol = float(rtol)
        self.method = method
        self.dtype = dtype
        self.device = torch.device(device)
        self.block = int(block)
        self.num_threads = num_threads
        self.error_bound: torch.Tensor | None = None

        self._idx = np.flatnonzero(lap.active)  # active vertices (reduced system)
        self.n = lap.n_vertices
        m = self._idx.size
        timings: dict[str, float] = {"operator": time.perf_counter() - t0}

        # --- eigenbasis -----------------------------------------------------------------
        t1 = time.perf_counter()
        if k is None:
            k = 40
        self.k = int(max(1, min(k, m)))
        if lap.lumped:
            self._a = lap.mass_diagonal()  # reduced lumped mass
            S = lap.symmetric_scipy()
            self._S_scipy = S
        else:
            self._a = np.asarray(lap.reduced()[1].sum(axis=1)).ravel()
            S = None
        if eigenpairs is not None:
            lam = np.asarray(torch.as_tensor(eigenpairs[0]).cpu().numpy(), dtype=np.float64)
            phi = np.asarray(torch.as_tensor(eigenpairs[1]).cpu().numpy(), dtype=np.float64)
            if phi.shape != (self.n, lam.size):
                raise ValueError(
                    f"eigenpairs have shape {tuple(phi.shape)}, expected ({self.n}, {lam.size})"
                )
            phi = phi[self._idx]
            self.k = int(lam.size)
            _check_eigenpairs(*lap.reduced(), lam, phi, mesh)
        elif method != "chebyshev":
            lam, phi = self._eigensolve(self.k)
        else:
            lam, phi = np.zeros(0), np.zeros((m, 0))
        self._lam = lam
        self._phi_red = phi  # mass-orthonormal on active vertices
        timings["eigenbasis"] = time.perf_counter() - t1

        # --- Chebyshev set-up -------------------------------------------------------------
        t2 = time.perf_counter()
        if lambda_max is not None:
            self.lambda_max = float(lambda_max)
        else:
            self.lambda_max = lambda_max_bound(S) if S is not None else float("nan")
        self._a_min = float(self._a.min())
        if S is not None:
            # 2X = (4 / lambda_max) S - 2 I, the recurrence matrix, as torch sparse CSR
            X2 = (4.0 / self.lambda_max) * S - 2.0 * sp.identity(m, format="csr")
            self._X2 = scipy_to_torch(X2.tocsr(), dtype).to(self.device)
        timings["lambda_max"] = time.perf_counter() - t2
        self._plan = self._make_plan()
        self._plan.timings.update(timings)

    # ---------------------------------------------------------------------------------
    def _eigensolve(self, k: int, known: tuple[np.ndarray, np.ndarray] | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
        W, A = self.laplacian.reduced()
        try:
            return eigenpairs(W, A, k, known=known)
        except EigensolverError as exc:  # name the mesh: the CLI prints this one line
            name = getattr(self.mesh, "name", None)
            if name is None:
                raise
            raise EigensolverError(f"{name}: {exc}") from exc

    def _phi_torch(self, dt: torch.dtype, dev: torch.device, lo: int = 0,
                   hi: int | None = None) -> torch.Tensor:
        """Eigenvector columns ``lo:hi`` (reduced) as a contiguous tensor, cached."""
        hi = self._phi_red.shape[1] if hi is None else hi
        key = (dt, dev, lo, hi)
        cache = self.__dict__.setdefault("_phi_cache", {})
        phi = cache.get(key)
        if phi is None:  # (returned from the local: another thread may clear the cache)
            if len(cache) >= 4:
                cache.clear()
            phi = cache[key] = torch.as_tensor(self._phi_red[:, lo:hi], dtype=dt,
                                               device=dev).contiguous()
        return phi

    def _spectral_eta(self) -> np.ndarray:
        """Operator-norm truncation bound of the eigenbasis per time, shape (J,)."""
        t = self.times.numpy()
        if self._lam.size == 0 or self._lam.size >= self._idx.size:
            return np.zeros_like(t) if self._lam.size else np.full_like(t, np.inf)
        return np.exp(-t * self._lam[-1])

    def _prior_factor(self) -> np.ndarray:
        """A-priori estimate of ``1 / (sqrt(a_min a_p) ||c||)`` per time (plans the degree)."""
        t = self.times.numpy()
        n_eff = self._idx.size
        # ||c||^2 ~ n (1 + 1/(8 pi t)) at unit area, a_p ~ a_min in the worst case
        return 1.0 / (self._a_min * np.sqrt(n_eff * (1.0 + 1.0 / (8 * np.pi * t))))

    def _make_plan(self) -> _Plan:
        J = self.times.numel()
        fac = self._prior_factor()
        spectral = np.zeros(J, dtype=bool)
        if self.method == "spectral":
            spectral[:] = True
        elif self.method == "hybrid":
            spectral = self._spectral_eta() * fac <= 0.5 * self.rtol
        degree = np.zeros(J, dtype=np.int64)
        for j in np.flatnonzero(~spectral):
            c = float(self.times[j]) * self.lambda_max / 2.0
            degree[j] = chebyshev_degree(c, 0.5 * self.rtol / fac[j])
        return _Plan(spectral, degree)

    def with_times(self, times: Sequence[float] | torch.Tensor) -> HeatKernel:
        """A solver for other time samples that shares this one's eigenbasis and operator.

        Nothing is recomputed but the plan (which times take the spectral path, Chebyshev
        degrees: microseconds); this solver is left as it is, so a shape prepared once can be
        matched at the times of many sources.

        Parameters
        ----------
        times : sequence of float, shape (J,)
            Positive time samples.

        Returns
        -------
        HeatKernel
            A new solver; its eigenpairs, operators and caches are this one's (not copied).

        Examples
        --------
        >>> import trimesh
        >>> from torchheat import Mesh
        >>> s = trimesh.creation.icosphere(2)
        >>> hk = HeatKernel(Mesh(s.vertices, s.faces))
        >>> hk2 = hk.with_times([0.1, 0.2])
        >>> hk2.times.numel(), hk.times.numel()
        (2, 10)
        """
        new = copy.copy(self)
        new._retime(times)
        return new

    def set_times(self, times: Sequence[float] | torch.Tensor) -> None:
        """Change the time samples of this solver in place (deprecated: use :meth:`with_times`).

        Every holder of the solver (e.g. a prepared shape shared between matches) sees the new
        times; :meth:`with_times` returns a new solver instead and leaves this one alone.

        Parameters
        ----------
        times : sequence of float, shape (J,)
        """
        warnings.warn("HeatKernel.set_times changes a solver others may hold; use "
                      "hk = hk.with_times(times)", DeprecationWarning, stacklevel=2)
        self._retime(times)

    def _retime(self, times: Sequence[float] | torch.Tensor) -> None:
        self.times = _checked_times(times)
        setup = self._plan.timings  # the eigenbasis and lambda_max are the same
        self._plan = self._make_plan()
        self._plan.timings.update(setup)
        self.error_bound = None  # bounds of the last columns() call at the old times

    def adaptive_times(self, n: int = 10, decay: float = 4 * math.log(10)) -> torch.Tensor:
        """Time samples adapted to the spectrum: ``decay / lambda_k ... decay / lambda_1``.

        At ``t = decay / lambda_k`` the truncated eigenbasis is accurate to ``exp(-decay)``
        (1e-4 by default) and at ``t = decay / lambda_1`` every non-constant mode has decayed
        by that factor, so the range holds all the information the eigenbasis carries
        (Sun, Ovsjanikov, Guibas 2009).

        Parameters
        ----------
        n : int
            Number of log-spaced samples.
        decay : float
            ``-ln`` of the relative decay at the ends (default ``4 ln 10``).

        Returns
        -------
        torch.Tensor
            float64, shape (n,).

        Examples
        --------
        >>> import trimesh
        >>> from torchheat import Mesh
        >>> s = trimesh.creation.icosphere(3)
        >>> HeatKernel(Mesh(s.vertices, s.faces)).adaptive_times().shape
        torch.Size([10])
        """
        lam = self._lam[self._lam > 1e-8 * max(float(self._lam[-1]), 1e-300)]
        if lam.size == 0:
            raise ValueError("adaptive times need a computed eigenbasis with nonzero eigenvalues")
        return default_times(n, decay / float(lam[-1]), decay / float(lam[0]))

    @property
    def plan(self) -> dict:
        """How each time is computed: ``{"spectral": bool[J], "degree": int[J], "timings"}``."""
        return {
            "spectral": self._plan.spectral.copy(),
            "degree": self._plan.degree.copy(),
            "timings": dict(self._plan.timings),
        }

    @property
    def eigenvalues(self) -> torch.Tensor:
        """Smallest eigenvalues of ``L`` (unit-area scale), shape (k,)."""
        return torch.from_numpy(self._lam.copy())

    @property
    def eigenvectors(self) -> torch.Tensor:
        """Mass-orthonormal eigenfunctions on all vertices, shape (n, k)."""
        return self._on_all_vertices(self._phi_red)

    def _on_all_vertices(self, phi_red: np.ndarray) -> torch.Tensor:
        """Reduced eigenvectors (free vertices) on all vertices, zero on Dirichlet ones."""
        phi = np.zeros((self.n, phi_red.shape[1]))
        phi[self._idx] = phi_red
        return torch.from_numpy(phi)

    def eigenpairs(self, k: int) -> tuple[torch.Tensor, torch.Tensor]:
        """The ``k`` smallest eigenpairs of ``L``, from the held basis if it has them, else by a
        new eigensolve of the same operator (not kept on the solver: its times, HKS and plans
        stay those of its own ``k``).

        Cost: free for ``k <= self.k``; otherwise one sparse eigensolve (shift-invert Lanczos,
        :func:`torchheat.eigen.eigenpairs`) of the pairs beyond the held ones, which it keeps
        as they are and projects out (its ``known``; a lumped mass); timings in
        BENCHMARKS.md ("Fine maps"). Accuracy: as :attr:`eigenvectors`.

        Parameters
        ----------
        k : int
            Number of eigenpairs (clamped to the number of free vertices).

        Returns
        -------
        lam : torch.Tensor, float64, shape (k,)
            Ascending eigenvalues (unit-area scale).
        phi : torch.Tensor, float64, shape (n, k)
            Mass-orthonormal eigenfunctions on all vertices (zero on Dirichlet boundaries).

        Examples
        --------
        >>> import trimesh
        >>> from torchheat import Mesh
        >>> s = trimesh.creation.icosphere(2)
        >>> hk = HeatKernel(Mesh(s.vertices, s.faces), k=10)
        >>> lam, phi = hk.eigenpairs(20)
        >>> phi.shape, bool(torch.allclose(lam[:10], hk.eigenvalues, rtol=1e-6, atol=1e-9))
        (torch.Size([162, 20]), True)
        """
        k = int(max(1, min(int(k), self._idx.size)))
        if k <= self._lam.size:
            return torch.from_numpy(self._lam[:k].copy()), self.eigenvectors[:, :k]
        lam, phi_red = self._eigensolve(k, known=(self._lam, self._phi_red))
        return (torch.from_numpy(np.asarray(lam, dtype=np.float64)),
                self._on_all_vertices(phi_red))

    @property
    def vertex_mass(self) -> torch.Tensor:
        """Lumped vertex masses of the unit-area shape, shape (n,): the weights of the
        eigenvectors' inner product (exactly, for the default lumped mass; the row sums of the
        consistent mass otherwise); zero at Dirichlet boundary vertices."""
        a = np.zeros(self.n)
        a[self._idx] = self._a
        return torch.from_numpy(a)

    # ---------------------------------------------------------------------------------
    def _reduced_sources(self, sources) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raw = to_numpy(sources)
        if not integral(raw):
            raise TypeError(f"source vertices must be integer indices, got {raw.dtype} values "
                            f"{raw.reshape(-1)[:5].tolist()}")  # 1.5 was read as vertex 1
        src = raw.astype(np.int64, copy=False).reshape(-1)
        if src.size and (src.min() < 0 or src.max() >= self.n):
            bad = src[(src < 0) | (src >= self.n)][:5].tolist()
            raise IndexError(f"source vertices {bad} out of range for a mesh of {self.n} vertices")
        pos = np.full(self.n, -1, dtype=np.int64)
        pos[self._idx] = np.arange(self._idx.size)
        red = pos[src]
        live = red >= 0  # Dirichlet: sources on the boundary have zero columns
        return src, red, live

    def _chebyshev(self, red: np.ndarray, tj: np.ndarray, degrees: np.ndarray) -> torch.Tensor:
        """exp(-t S) e_p / sqrt(a_p) for reduced sources ``red`` and times ``tj``: [m, B, Jc]."""
        return chebyshev_columns(self._X2, self._a, red, tj, degrees, self.lambda_max)

    def _chebyshev_blocked(self, red, tj, degrees) -> torch.Tensor:
        block = _chebyshev_block(self._idx.size, len(tj), int(np.max(degrees)),
                                 self.dtype.itemsize, self.block,
                                 chebyshev.CHEBYSHEV_BYTES)  # read now: tests lower it
        parts = []
        with _flush_denormal(self.dtype == torch.float32), threads(self.num_threads):
            for s in range(0, red.size, block):
                parts.append(self._chebyshev(red[s : s + block], tj, degrees))
        return torch.cat(parts, dim=1)

    def columns(
        self, sources: Sequence[int] | np.ndarray | torch.Tensor, *, certify: bool = True
    ) -> torch.Tensor:
        """Heat kernel columns ``k_t(p, x)`` for a batch of sources and every time.

        Parameters
        ----------
        sources : sequence of int, shape (B,)
            Source vertices ``p`` (0-based).
        certify : bool
            Compute :attr:`error_bound` (and refine what fails). ``False`` skips that work
            where only ``method="spectral"`` descriptors are needed; the hybrid and Chebyshev
            plans still meet ``rtol`` by their a-priori degree choice in practice, but no
            bound is then reported (``error_bound`` is None).

        Returns
        -------
        torch.Tensor
            Shape (B, n, J), dtype and device of the solver: ``out[b, x, j] = k_{t_j}(p_b, x)``
            with ``K_t = exp(-tL) A^-1`` on the unit-area shape. Zero at Dirichlet boundary
            vertices (and for sources on the boundary).

        Notes
        -----
        Accuracy: relative L2 error per (source, time) at most ``rtol`` (bound in
        :attr:`error_bound`), except with ``method="spectral"`` where the bound is only
        reported. Cost: one Chebyshev recurrence per block of ``block`` sources, of the degree
        of the largest Chebyshev time, plus one dense product with the eigenbasis.

        Examples
        --------
        >>> import trimesh
        >>> from torchheat import Mesh
        >>> s = trimesh.creation.icosphere(2)
        >>> HeatKernel(Mesh(s.vertices, s.faces), times=[0.01, 0.1]).columns([3]).shape
        torch.Size([1, 162, 2])
        """
        src, red, live = self._reduced_sources(sources)
        B, J = src.size, self.times.numel()
        m = self._idx.size
        dev, dt = self.device, self.dtype
        if (self._plan.spectral.all() and not certify and bool(live.all()) and m == self.n
                and B > 0):
            # fast path (descriptors): one GEMM, phi [n, k] x (phi[p] e^{-t lam}) [k, B J]
            self.error_bound = None
            with threads(self.num_threads):
                phi = self._phi_torch(dt, dev)
                E = torch.exp(-self.times.to(dt).to(dev)[None, :]
                              * torch.as_tensor(self._lam, dtype=dt, device=dev)[:, None])
                coeff = phi[torch.as_tensor(red, device=dev)].T[:, :, None] * E[:, None, :]
                out = (phi @ coeff.reshape(phi.shape[1], B * J)).reshape(m, B, J)
            return out.permute(1, 0, 2)
        red_live = red[live]
        Bl = red_live.size
        colr = torch.zeros((m, Bl, J), dtype=dt, device=dev)
        eta = np.zeros((Bl, J))
        spectral = self._plan.spectral
        t_all = self.times.numpy()
        with threads(self.num_threads):
            if spectral.any() and Bl:
                # in the S-space convention of the Chebyshev path (times sqrt(a_x))
                colr[:, :, torch.as_tensor(np.flatnonzero(spectral), device=dev)] = (
                    spectral_columns(self._phi_torch(dt, dev),
                                     torch.as_tensor(self._lam, dtype=dt, device=dev),
                                     torch.as_tensor(np.sqrt(self._a), dtype=dt, device=dev),
                                     red_live, torch.as_tensor(t_all[spectral], dtype=dt,
                                                               device=dev))
                )
                eta[:, spectral] = self._spectral_eta()[spectral][None, :]
        cheb = np.flatnonzero(~spectral)
        if cheb.size and Bl:
            colr[:, :, torch.as_tensor(cheb, device=dev)] = self._chebyshev_blocked(
                red_live, t_all[cheb], self._plan.degree[cheb]
            )
            eta[:, cheb] = self._tail(cheb, self._plan.degree[cheb])[None, :]

        # certify, and refine what fails (rarely needed: the plan is conservative)
        bound = self._certify(colr, red_live, eta) if certify else None
        if certify and self.method != "spectral":
            assert bound is not None  # (certify)
            norms = self._norms(colr, red_live)
            for attempt in range(4):
                bad = bound > self.rtol
                if not bad.any():
                    break
                bad_t = np.flatnonzero(bad.any(axis=0))
                sel = np.flatnonzero(bad.any(axis=1))
                deg = np.array([
                    chebyshev_degree(
                        float(t_all[j]) * self.lambda_max / 2.0,
                        0.5 * self.rtol * max(float(norms[sel, j].min()), 1e-300) / 4.0**attempt,
                    )
                    for j in bad_t
                ])
                sub = self._chebyshev_blocked(red_live[sel], t_all[bad_t], deg)
                sel_t = torch.as_tensor(sel, device=dev)
                for i, j in enumerate(bad_t):
                    colr[:, sel_t, int(j)] = sub[:, :, i]
                    eta[sel, j] = self._tail(np.array([j]), np.array([deg[i]]))[0]
                bound = self._certify(colr, red_live, eta)

        # back to vertex space: k_t(p, x) = colr[x] / sqrt(a_x), scatter to all vertices
        inv_sq = torch.as_tensor(1.0 / np.sqrt(self._a), dtype=dt, device=dev)
        colr.mul_(inv_sq[:, None, None])
        out = torch.zeros((B, self.n, J), dtype=dt, device=dev)
        live_t = torch.as_tensor(np.flatnonzero(live), device=dev)
        idx_t = torch.as_tensor(self._idx, device=dev)
        out[live_t[:, None], idx_t[None, :], :] = colr.permute(1, 0, 2)
        if certify:
            full_bound = np.zeros((B, J))
            full_bound[live] = bound
            self.error_bound = torch.from_numpy(full_bound)
        else:
            self.error_bound = None
        return out

    @property
    def has_constant_mode(self) -> bool:
        """Whether the eigenbasis starts with the constant mode (lambda_0 = 0, Neumann)."""
        return bool(self._lam.size > 1
                    and self._lam[0] <= 1e-9 * max(float(self._lam[-1]), 1.0))

    def spectral_basis(
        self,
        time_index: Sequence[int] | slice | None = None,
        scaled: bool = True,
        dtype: torch.dtype | None = None,
        drop_constant: bool = False,
        mode_tol: float = 0.0,
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(phi [n, k'], E [k', J'])``: eigenfunctions and time weights ``t_j e^{-t_j lam_i}``.

        ``t_j k_{t_j}(p, x) = sum_i phi[x, i] phi[p, i] E[i, j]`` for the times served by the
        eigenbasis. ``drop_constant`` leaves out the constant mode (see
        :meth:`spectral_factors`); ``mode_tol > 0`` also leaves out the fast tail: the modes
        whose weight ``exp(-t (lam_i - lam_first))`` relative to the slowest kept mode is
        below ``mode_tol`` at the smallest of these times (they change no descriptor by more
        than that fraction of its slowest term). None when some time is not served by the
        eigenbasis or there are Dirichlet vertices. Cost: ``O(k J')``; ``phi`` is cached.

        Examples
        --------
        >>> import trimesh
        >>> from torchheat import Mesh
        >>> s = trimesh.creation.icosphere(3)
        >>> hk = HeatKernel(Mesh(s.vertices, s.faces), method="spectral", k=40)
        >>> phi, E = hk.spectral_basis(drop_constant=True)
        >>> phi.shape, E.shape
        (torch.Size([642, 39]), torch.Size([39, 10]))
        """
        if not (self._plan.spectral.all() and self._idx.size == self.n):
            return None
        lo = 1 if (drop_constant and self.has_constant_mode) else 0
        hi = self._lam.size
        t_all = self.times.numpy()
        if time_index is not None:
            t_all = t_all[time_index]
        if mode_tol > 0 and hi > lo + 1:
            rel = np.exp(-float(t_all.min()) * (self._lam[lo:] - self._lam[lo]))
            hi = lo + max(1, int(np.count_nonzero(rel >= mode_tol)))
        dev, dt = self.device, self.dtype if dtype is None else dtype
        phi = self._phi_torch(dt, dev, lo, hi)
        t = torch.as_tensor(t_all, dtype=dt, device=dev)
        lam = torch.as_tensor(self._lam[lo:hi], dtype=dt, device=dev)
        E = torch.exp(-t[None, :] * lam[:, None])  # [k', J']
        if scaled:
            E = E * t[None, :]
        return phi, E

    def spectral_factors(
        self,
        sources: Sequence[int] | np.ndarray | torch.Tensor,
        time_index: Sequence[int] | slice | None = None,
        scaled: bool = True,
        dtype: torch.dtype | None = None,
        drop_constant: bool = False,
        mode_tol: float = 0.0,
    ) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(phi [n, k], coeff [k, B J'])`` with ``phi @ coeff`` = :meth:`spectral_map`.

        The heat kernel map of B sources has rank at most k: this factored form lets a
        nearest-neighbour search between two shapes work in k dimensions instead of B J'.
        None when some time is not served by the eigenbasis (see :meth:`spectral_map`).
        ``drop_constant`` leaves out the constant mode (lambda_0 = 0, Neumann): its term
        ``t_j / area`` is the same at every vertex of every unit-area shape, so distances
        between maps do not change, but it dominates their norm (measured: |x|^2 varies by
        2 % over a TOSCA mesh while neighbours differ by 1e-7 of it), which ruins
        ``|x|^2 + |y|^2 - 2 x.y`` searches in float32. ``mode_tol``: see
        :meth:`spectral_basis`.
        """
        basis = self.spectral_basis(time_index, scaled, dtype, drop_constant, mode_tol)
        if basis is None:
            return None
        phi, E = basis
        _, red, _ = self._reduced_sources(sources)
        coeff = phi[torch.as_tensor(red, device=phi.device)].T[:, :, None] * E[:, None, :]
        return phi, coeff.reshape(phi.shape[1], -1)

    def spectral_map(
        self,
        sources: Sequence[int] | np.ndarray | torch.Tensor,
        time_index: Sequence[int] | slice | None = None,
        scaled: bool = True,
        dtype: torch.dtype | None = None,
    ) -> torch.Tensor | None:
        """``t_j k_{t_j}(p_b, x)`` as one ``[n, B * J']`` matrix (source-major), or None.

        The descriptor layout of :func:`torchheat.descriptors.heat_kernel_map`, computed by a
        single product ``phi [n, k] x (phi[p] e^{-t lam} t) [k, B J']`` with no intermediate
        ``[B, n, J]`` tensor. Only when every time is served by the eigenbasis
        (``plan["spectral"]`` all true, no Dirichlet vertices); returns None otherwise, and
        the caller falls back to :meth:`columns`. Accuracy: that of the eigenbasis at these
        times (see :attr:`plan`), or float32 rounding (~1e-6 relative) with
        ``dtype=torch.float32``; cost ``2 n k B J'`` flops.
        """
        with threads(self.num_threads):
            f = self.spectral_factors(sources, time_index, scaled, dtype)
            return None if f is None else f[0] @ f[1]

    def _tail(self, js: np.ndarray, degrees: np.ndarray) -> np.ndarray:
        return np.array([chebyshev_tail(float(self.times[j]) * self.lambda_max / 2.0, int(d))
                         for j, d in zip(js, degrees, strict=True)])

    def _norms(self, colr: torch.Tensor, red: np.ndarray) -> np.ndarray:
        """``sqrt(a_min a_p) ||c_hat||`` per (source, time), shape (B, J)."""
        return column_norms(colr, self._a, self._a_min, red)

    def _certify(self, colr: torch.Tensor, red: np.ndarray, eta: np.ndarray) -> np.ndarray:
        return relative_bound(self._norms(colr, red), eta)

    # ---------------------------------------------------------------------------------
    def hks(self) -> torch.Tensor:
        """Heat Kernel Signature ``k_t(x, x)`` from the truncated eigenbasis.

        Returns
        -------
        torch.Tensor
            float64, shape (n, J). The truncation error is bounded per vertex by
            ``exp(-t lambda_k) / a_x`` (``sum_{i>k} exp(-t lambda_i) psi_i(x)^2 <=
            exp(-t lambda_k)``); its relative value is stored in :attr:`hks_error_bound`
            (shape (n, J)). At small ``t`` with few eigenpairs that bound exceeds 1: the
            truncated HKS there is a smoothed signature, not the kernel diagonal.

        Examples
        --------
        >>> import trimesh
        >>> from torchheat import Mesh
        >>> s = trimesh.creation.icosphere(2)
        >>> HeatKernel(Mesh(s.vertices, s.faces), times=[0.5]).hks().shape
        torch.Size([162, 1])
        """
        if self._lam.size == 0:
            self._lam, self._phi_red = self._eigensolve(self.k)
            self.__dict__.pop("_phi_cache", None)
        t = self.times.numpy()
        E = np.exp(-t[None, :] * self._lam[:, None])  # [k, J]
        h = (self._phi_red**2) @ E  # [m, J]
        out = np.zeros((self.n, t.size))
        out[self._idx] = h
        eta = self._spectral_eta()
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = eta[None, :] / (self._a[:, None] * h)
        bound = np.zeros_like(out)
        bound[self._idx] = rel
        self.hks_error_bound = torch.from_numpy(bound)
        return torch.from_numpy(out)
