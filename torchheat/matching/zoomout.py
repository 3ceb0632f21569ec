"""Spectral refinement of point maps: ZoomOut (Melzi, Ren, Rodolà, Sharma, Wonka, Ovsjanikov,
*ZoomOut: Spectral Upsampling for Efficient Shape Correspondence*, SIGGRAPH Asia 2019).

A point map ``T: M -> N`` pulls functions back, ``f -> f o T``; in the Laplace–Beltrami
eigenbases ``Phi_M`` (``n x k``) and ``Phi_N`` (``m x k``) this is the ``k x k`` functional map
``C`` with ``Phi_M C ~ Phi_N[T]`` (least squares over the source points, Melzi et al. eq. 1).
Conversely ``C`` gives a point map by nearest neighbour: ``T(x) = argmin_y |Phi_M[x] -
Phi_N[y] C^T|`` (eq. 3). ZoomOut alternates the two while the basis grows from ``k_start`` to
``k_end`` modes: each step adds frequencies the previous map already determines, so a coarse
map (here: a heat-kernel map from one point) becomes a fine one, and a map that is not close to
an isometry does not converge to a good alignment (its residual stays high), which
:mod:`.pipeline` uses to choose among hypotheses.

Cost per step: a ``k x k`` least-squares solve on ``s`` source samples and an exact
nearest-neighbour search of ``s`` queries among ``m`` targets in ``k`` dimensions (one GEMM,
``O(s m k)``); the dense map at the end is one exact search over all ``n`` source vertices
(:func:`dense_spectral_map`: float32 certified row by row, or cluster-pruned on large meshes).
:func:`fine_map` refines a chosen map further on a larger eigenbasis (``match(fine_k=...)``).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from ..heat import threads
from .nn import _argmin_certified, _blocked_argmin, _Factors, _nn_factors_pruned
from .prepared import PreparedShape, _basis, _cluster_centres, _fps

__all__ = ["functional_map", "spectral_map", "zoomout", "fine_map", "ZoomOutResult"]

_ZO_DTYPE = torch.float32  # the sample steps; the dense map is certified exact (float64's)


@dataclass
class ZoomOutResult:
    """The outcome of :func:`zoomout`.

    Attributes
    ----------
    rows : torch.Tensor, int64, shape (s,)
        Source samples the map was refined on.
    images : torch.Tensor, int64, shape (s,)
        Their images on the target after the last step.
    C : torch.Tensor, float64, shape (k, k)
        The functional map at the last size ``k`` (``Phi_M C ~ Phi_N[T]``).
    residual : float
        Mean squared spectral distance ``|Phi_M[x] - Phi_N[T x] C^T|^2`` of the samples at the
        last step, divided by ``k``: how well the map aligns the two eigenbases (lower is
        better; comparable between hypotheses refined to the same ``k``).
    """

    rows: torch.Tensor
    images: torch.Tensor
    C: torch.Tensor
    residual: float


def lstsq(A: torch.Tensor, B: torch.Tensor, *, full_rank: bool = True) -> torch.Tensor:
    """``argmin_X |A X - B|_F``, the same bits on every call.

    ``torch.linalg.lstsq``'s default CPU driver (LAPACK ``gelsy`` through MKL) is not
    reproducible: on one [500, 100] float64 system it returned 27 distinct solutions in 50
    calls on the same input (differences ~1e-15), enough to change a ZoomOut candidate's
    residual in the fifth digit and, on a few pairs, the chosen map between runs. Here:
    QR without pivoting (``gels``: reproducible and ~15 % faster), for the full-rank
    systems of farthest-point samples; a rank-deficient ``A`` falls back to the SVD
    (``gelsd``, also reproducible, minimum-norm solution). ``gels`` only notices an exactly
    singular ``A``: a caller that knows ``A`` is numerically rank-deficient passes
    ``full_rank=False`` and gets the SVD solution directly (``gels`` would return an
    inaccurate one, not a least-squares minimiser).

    Parameters
    ----------
    A : torch.Tensor, shape (s, k)
    B : torch.Tensor, shape (s, d)
    full_rank : bool
        False: solve by the SVD (minimum norm) without trying ``gels``.

    Returns
    -------
    torch.Tensor, shape (k, d)

    Examples
    --------
    >>> A = torch.tensor([[1.0, 0.0], [0.0, 2.0], [0.0, 0.0]], dtype=torch.float64)
    >>> lstsq(A, torch.tensor([[1.0], [4.0], [5.0]], dtype=torch.float64)).flatten().tolist()
    [1.0, 2.0]
    """
    if not full_rank:
        if A.device.type != "cpu":  # CUDA has gels only
            return torch.linalg.pinv(A) @ B
        return torch.linalg.lstsq(A, B, driver="gelsd").solution
    if A.device.type != "cpu":
        return torch.linalg.lstsq(A, B).solution  # CUDA: gels, the only driver there
    try:
        return torch.linalg.lstsq(A, B, driver="gels").solution
    except RuntimeError:  # not of full rank
        return torch.linalg.lstsq(A, B, driver="gelsd").solution


def functional_map(phi_s: torch.Tensor, phi_t: torch.Tensor, rows: torch.Tensor,
                   images: torch.Tensor, k: int) -> torch.Tensor:
    """The ``k x k`` functional map of a point map known on source samples.

    Least squares ``min_C |Phi_M[rows, :k] C - Phi_N[images, :k]|_F`` (Melzi et al. 2019,
    eq. 1 with the pseudo-inverse on the samples); needs ``len(rows) >= k`` well-spread
    samples (farthest-point samples are).

    Parameters
    ----------
    phi_s : torch.Tensor, shape (n, K)
        Source eigenbasis (columns mass-orthonormal), ``K >= k``.
    phi_t : torch.Tensor, shape (m, K)
        Target eigenbasis.
    rows : torch.Tensor, int64, shape (s,)
    images : torch.Tensor, int64, shape (s,)
        Target vertex of every source sample.
    k : int

    Returns
    -------
    torch.Tensor, shape (k, k), dtype of the bases

    Examples
    --------
    >>> phi = torch.linalg.qr(torch.randn(50, 6, dtype=torch.float64))[0]
    >>> C = functional_map(phi, phi, torch.arange(50), torch.arange(50), 6)
    >>> bool(torch.allclose(C, torch.eye(6, dtype=torch.float64)))  # the identity map
    True
    """
    return lstsq(phi_s[rows, :k], phi_t[images, :k])


def spectral_map(phi_s: torch.Tensor, phi_t: torch.Tensor, C: torch.Tensor,
                 rows: torch.Tensor | None = None, memory_bytes: int = 256 * 2**20
                 ) -> tuple[torch.Tensor, torch.Tensor]:
    """The point map of a functional map: nearest neighbour of ``Phi_M[x]`` among ``Phi_N C^T``.

    Exact brute force in blocks of at most ``memory_bytes`` (one GEMM per block).

    Parameters
    ----------
    phi_s : torch.Tensor, shape (n, K)
    phi_t : torch.Tensor, shape (m, K)
    C : torch.Tensor, shape (k, k), ``k <= K``
    rows : torch.Tensor, int64, shape (s,), optional
        Source vertices to map (default: all).

    Returns
    -------
    d2 : torch.Tensor, shape (s,)
        Squared spectral distances to the images.
    images : torch.Tensor, int64, shape (s,)

    Examples
    --------
    >>> phi = torch.linalg.qr(torch.randn(40, 5, dtype=torch.float64))[0]
    >>> spectral_map(phi, phi, torch.eye(5, dtype=torch.float64))[1].tolist() == list(range(40))
    True
    """
    k = C.shape[0]
    X = phi_s[:, :k] if rows is None else phi_s[rows, :k]
    Y = phi_t[:, :k] @ C.T.to(phi_t.dtype)
    return _blocked_argmin(X, Y, (X * X).sum(1), (Y * Y).sum(1), memory_bytes)


def _sizes(k_start: int, k_end: int, step: int) -> list[int]:
    sizes = list(range(k_start, k_end, max(1, step)))
    return [*sizes, k_end]


class _RowBasis:
    """The source basis on ZoomOut's rows, factored once for every step of a ZoomOut.

    Every step solves ``min_C |Phi_M[rows, :k] C - B|`` for a growing ``k``; the Householder
    QR of ``Phi_M[rows, :k_end]`` serves them all (the QR of the first ``k`` columns is the
    first ``k`` columns of ``Q`` and the leading block of ``R``), so a step costs one
    ``(s x k) x (k x k)`` product and a triangular solve instead of a factorisation. The
    squared row norms of every prefix come from one cumulative sum. A basis that is not of
    full rank on the rows (a diagonal entry of ``R`` below ``1e-6`` of the largest) falls
    back to :func:`lstsq`.
    """

    def __init__(self, phi: torch.Tensor, rows: torch.Tensor, k: int) -> None:
        self.X = phi[rows, :k].contiguous()
        self.Q, self.R = torch.linalg.qr(self.X)
        d = self.R.diagonal().abs()
        self.full_rank = bool(d.min() > 1e-6 * d.max()) if d.numel() else False
        self.xx = (self.X * self.X).cumsum(dim=1)

    def functional_map(self, B: torch.Tensor) -> torch.Tensor:
        """``argmin_C |X[:, :k] C - B|``, ``k = B.shape[1]``."""
        k = B.shape[1]
        if not self.full_rank:
            return lstsq(self.X[:, :k], B, full_rank=False)
        return torch.linalg.solve_triangular(self.R[:k, :k], self.Q[:, :k].T @ B, upper=True)

    def spectral_map(self, phi_t: torch.Tensor, C: torch.Tensor,
                     memory_bytes: int = 256 * 2**20) -> tuple[torch.Tensor, torch.Tensor]:
        """:func:`spectral_map` of the rows (squared distances, target indices)."""
        k = C.shape[0]
        Y = phi_t[:, :k] @ C.T.to(phi_t.dtype)
        return _blocked_argmin(self.X[:, :k], Y, self.xx[:, k - 1], (Y * Y).sum(1),
                               memory_bytes)


def zoomout(phi_s: torch.Tensor, phi_t: torch.Tensor, seed_rows: torch.Tensor,
            seed_images: torch.Tensor, rows: torch.Tensor, *, k_start: int = 16,
            k_end: int = 100, step: int = 6, targets: torch.Tensor | None = None
            ) -> ZoomOutResult:
    """ZoomOut from a sparse map: the functional map of ``seed_rows -> seed_images`` at
    ``k_start`` modes, then point map on ``rows`` / functional map, growing by ``step`` modes
    to ``k_end`` (Melzi et al. 2019, Alg. 1, on source samples).

    Parameters
    ----------
    phi_s, phi_t : torch.Tensor, shapes (n, K) and (m, K)
        Eigenbases (mass-orthonormal columns, ascending eigenvalues); ``k_end <= K``.
    seed_rows, seed_images : torch.Tensor, int64, shape (s0,)
        The starting map on a few source samples; ``s0 >= k_start``.
    rows : torch.Tensor, int64, shape (s,)
        Source samples the map is refined on (``s >= k_end``, farthest-point samples).
    k_start, k_end, step : int
    targets : torch.Tensor, int64, shape (t,), optional
        Target vertices the samples may map to (default: all; a few thousand
        farthest-point samples cut the cost of each step in proportion).

    Returns
    -------
    ZoomOutResult

    Notes
    -----
    Cost: ``sum_k O(s m k + s k^2)`` over the sizes, about ``s m (k_end^2 - k_start^2) /
    (2 step)`` multiply-adds: 0.1 s for ``s = 1000``, ``m = 5000``, 16 -> 100 by 6 (one
    thread, float32).

    Examples
    --------
    >>> phi = torch.linalg.qr(torch.randn(300, 30, dtype=torch.float64))[0]
    >>> perm = torch.randperm(300)
    >>> r = zoomout(phi[perm], phi, torch.arange(40), perm[:40], torch.arange(300),
    ...             k_start=8, k_end=30, step=4)
    >>> bool((r.images == perm).all())  # a permutation is recovered from 40 samples
    True
    """
    k_end = int(min(k_end, phi_s.shape[1], phi_t.shape[1], rows.numel()))
    k_start = int(max(1, min(k_start, k_end, seed_rows.numel())))
    Ps, Pt = phi_s.to(_ZO_DTYPE), phi_t.to(_ZO_DTYPE)
    tmap = torch.arange(phi_t.shape[0]) if targets is None else targets
    Pt_sub = Pt if targets is None else Pt[targets]
    rb = _RowBasis(Ps, rows, k_end)
    C = functional_map(Ps, Pt, seed_rows, seed_images, k_start)
    d2, j = rb.spectral_map(Pt_sub, C)
    images = tmap[j]
    for k in _sizes(k_start, k_end, step)[1:]:
        C = rb.functional_map(Pt[images, :k])
        d2, j = rb.spectral_map(Pt_sub, C)
        images = tmap[j]
    C = functional_map(phi_s, phi_t, rows, images, k_end)  # float64, of the final images
    return ZoomOutResult(rows, images, C, float(d2.double().mean()) / k_end)


#: :func:`dense_spectral_map`: searches of at most this many (source, target) pairs run as one
#: certified float32 product (:func:`~.nn._argmin_certified`), larger ones as the cluster-pruned
#: float64 search (:func:`~.nn._nn_factors_pruned`), whose pruning pays off on larger meshes.
#: Both find the float64 nearest neighbour (the same maps on 24 TOSCA and 3 SCAPE pairs).
#: Measured at 100 modes, one thread: TOSCA 5k x 5k 0.12-0.18 s certified against 0.29 s
#: pruned; SCAPE 12.5k x 12.5k 1.2-1.3 s against 0.57-0.59 s (BENCHMARKS.md, forty-second
#: session); the ratio crosses 1 near 66 million pairs (near 108 million at 200 modes, where
#: ``fine_map`` searches: 0.25 / 1.52 s on TOSCA, 2.31 / 1.46 s on SCAPE).
CERTIFIED_MAX_PAIRS = 50_000_000


def dense_spectral_map(src: PreparedShape, tgt: PreparedShape, C: torch.Tensor,
                       num_threads: int | None = None) -> torch.Tensor:
    """The dense point map of a functional map: ``T(x) = argmin_y |Phi_M[x] - Phi_N[y] C^T|``
    for every source vertex, exactly as a float64 brute force finds it.

    Up to ``CERTIFIED_MAX_PAIRS`` source-target pairs, one float32 product in cache-sized
    blocks, certified row by row (:func:`~.nn._argmin_certified`: rows whose two nearest lie
    within the float32 error bound, exact ties included, are searched again in float64);
    beyond, the exact cluster-pruned search (:func:`~.nn._nn_factors_pruned`, ``4 sqrt(m)``
    target clusters). Cost: ``O(n m k)`` float32, or ``O((n + m) sqrt(m) k)`` plus the
    searched pairs.

    Parameters
    ----------
    src, tgt : PreparedShape
        Source (n vertices) and target (m vertices).
    C : torch.Tensor, shape (k, k)
        Functional map in their heat kernels' eigenbases (``Phi_M C ~ Phi_N[T]``).
    num_threads : int, optional
        Torch threads for the search.

    Returns
    -------
    torch.Tensor, int64, shape (n,)

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> from torchheat.matching import prepare
    >>> ico = trimesh.creation.icosphere(3)
    >>> s = prepare(Mesh(ico.vertices, ico.faces), k=20)
    >>> bool((dense_spectral_map(s, s, torch.eye(20)) == torch.arange(s.n)).all())
    True
    """
    k = C.shape[0]
    with threads(num_threads):
        return _dense_argmin(src.hk.eigenvectors[:, :k], tgt.hk.eigenvectors[:, :k], C, tgt)


def _dense_argmin(phi_s: torch.Tensor, phi_t: torch.Tensor, C: torch.Tensor,
                  tgt: PreparedShape) -> torch.Tensor:
    """``argmin_y |phi_s[x] - phi_t[y] C^T|`` for every row of ``phi_s`` (float64's nearest
    neighbour): certified float32 up to ``CERTIFIED_MAX_PAIRS`` pairs, else cluster-pruned
    around ``4 sqrt(m)`` farthest-point centres of ``tgt`` (whose vertices ``phi_t`` rows are)."""
    k, m = C.shape[0], phi_t.shape[0]
    phi_s, phi_t, Ct = phi_s.to(torch.float64), phi_t.to(torch.float64), C.T.to(torch.float64)
    if phi_s.shape[0] * m <= CERTIFIED_MAX_PAIRS:
        return _argmin_certified(phi_s, phi_t @ Ct)
    return _nn_factors_pruned(_Factors(phi_s, torch.eye(k, dtype=torch.float64)), None,
                              _Factors(phi_t, Ct), _cluster_centres(tgt))[1]


#: ``fine_map``: source rows per mode of the largest basis (farthest-point samples). Measured on
#: 16 TOSCA 5k pairs (two per class), k = 100 -> 200: 1000 rows (5 per mode) mean eps 0.0121,
#: 2000 rows 0.0118, all 5000 vertices 0.0119 (from 0.0144 at k = 100).
FINE_ROWS_PER_MODE = 10
FINE_STEP = 20  # modes added per step of the fine ZoomOut


def fine_map(src: PreparedShape, tgt: PreparedShape, C: torch.Tensor, k: int,
             num_threads: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Upsample a chosen functional map to a larger eigenbasis and make it dense: ZoomOut from
    ``C``'s size to ``k`` modes by ``FINE_STEP``, on ``FINE_ROWS_PER_MODE * k`` farthest-point
    source rows mapped to every target vertex, then the exact dense map of the last ``C``.

    The bases of ``k`` modes come from :func:`~.prepared._basis` (a new eigensolve per shape when
    its heat kernel holds fewer, kept on the shape). The seed is ``C``'s own point map on the
    rows (``C`` in the heat-kernel eigenbases), so the larger bases' signs and rotations within
    eigenspaces do not matter.

    Parameters
    ----------
    src, tgt : PreparedShape
    C : torch.Tensor, shape (k0, k0)
        Functional map in the heat-kernel eigenbases (``Phi_M C ~ Phi_N[T]``).
    k : int
        Size of the last functional map; ``k <= k0`` only makes the map dense again at ``k0``.

    Returns
    -------
    images : torch.Tensor, int64, shape (n,)
        Target vertex of every source vertex.
    C : torch.Tensor, float64, shape (k', k')
        The last functional map, in the bases of :func:`~.prepared._basis`; ``k' = min(k, n, m)``.

    Notes
    -----
    Cost beyond the two eigensolves (each solves only the modes beyond the heat kernel's, which
    it keeps: :func:`torchheat.eigen.eigenpairs`' ``known``): ``sum_k O(s m k)`` for
    ``s = FINE_ROWS_PER_MODE * k`` rows and the final exact ``n x m`` search in ``k``
    dimensions (as :func:`dense_spectral_map`'s: float32 certified up to
    ``CERTIFIED_MAX_PAIRS`` pairs, cluster-pruned beyond). Timings of both parts:
    ``scripts/bench.py fine``, BENCHMARKS.md.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> from torchheat.matching import prepare
    >>> s = trimesh.creation.icosphere(3)
    >>> shape = prepare(Mesh(s.vertices, s.faces), k=20)
    >>> images, C = fine_map(shape, shape, torch.eye(20, dtype=torch.float64), 40)
    >>> C.shape, bool((images == torch.arange(shape.n)).all())  # the identity stays
    (torch.Size([40, 40]), True)
    """
    k0 = C.shape[0]
    k = int(min(max(k, k0), src.n, tgt.n))
    phi_s, phi_t = _basis(src, k), _basis(tgt, k)
    k = min(phi_s.shape[1], phi_t.shape[1])
    rows = _fps(src, min(src.n, max(k, FINE_ROWS_PER_MODE * k)))
    with threads(num_threads):
        _, seed = spectral_map(src.hk.eigenvectors.to(_ZO_DTYPE), tgt.hk.eigenvectors.to(_ZO_DTYPE),
                               C.to(_ZO_DTYPE), rows)
        if k > k0:
            C = zoomout(phi_s, phi_t, rows, seed, rows, k_start=k0, k_end=k,
                        step=FINE_STEP).C
        else:
            C = functional_map(phi_s, phi_t, rows, seed, k0)
        images = _dense_argmin(phi_s[:, :C.shape[0]], phi_t[:, :C.shape[0]], C, tgt)
    return images, C
