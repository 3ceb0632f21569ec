"""Exact nearest-neighbour engines: chunked ``torch.cdist``, k-d trees, factored L2 search
(with exact cluster pruning) of spectral descriptors.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

__all__ = ["nearest_neighbors"]


# ------------------------------------------------------------------------------------------
# nearest-neighbour engines
# ------------------------------------------------------------------------------------------
@dataclass
class CdistStats:
    """What one cdist search did (``nearest_neighbors(..., stats=CdistStats())`` fills it): its
    block plan and the largest working set of one block (bytes).

    A block of ``r`` query rows against ``c`` reference rows (dimension ``d``, element size
    ``e``) holds the distance block ``r c e``, the ``min`` outputs ``r (e + 8)`` and, for
    ``p = 2`` (where ``torch.cdist`` goes through a matrix product), the padded copies and
    their temporaries, at most ``(r + c)(2d + 4) e``.
    """

    peak_bytes: int = 0
    budget_bytes: int = 0
    block: tuple[int, int] = (0, 0)


_LAST_CDIST = CdistStats()  # what the deprecated LAST_CDIST_PEAK reads


def __getattr__(name: str) -> CdistStats:
    if name == "LAST_CDIST_PEAK":
        import warnings

        warnings.warn("LAST_CDIST_PEAK is deprecated (a module global every call rewrites, not "
                      "thread-safe): pass stats=CdistStats() to nearest_neighbors",
                      DeprecationWarning, stacklevel=2)
        return _LAST_CDIST
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

# Working-set budget (bytes) of one block of every blocked computation of matching: cdist
# blocks, the candidates' heat-kernel columns of the landmark score, the cluster blocks of
# the pruned dense search, the edge differences of the ambiguity test. Each block stays
# within it, so that memory grows linearly with the mesh size (a 300k-vertex pair was
# measured in BENCHMARKS.md "Big meshes"). Blocks that fit are never split: the results do
# not depend on it (tested against unblocked computations).
WORK_BYTES = 256 * 2**20

# Largest block of the certified float32 search (:func:`_argmin_certified`): a [rows, m]
# block reduced while it is still in the last-level cache. Measured on TOSCA 5k dense maps
# (one thread, AMD EPYC with 32 MiB of L3): blocks of 4-16 MiB took 0.11-0.13 s, one
# 100 MiB block 0.20 s.
CACHE_BYTES = 8 * 2**20


def _min_rows(G: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``G.min(dim=1)``: the least value of every row and its first index.

    On CPU (float32 / float64) through numpy's vectorised ``argmin`` and a gather: the same
    values and indices as torch's ``min`` (ties: the first index; a NaN row: its first
    NaN), about 8x faster on a [500, 2000] float32 block with one thread (torch's reduction
    with indices is not vectorised there); elsewhere torch's ``min``.

    Examples
    --------
    >>> v, i = _min_rows(torch.tensor([[1.0, 0.0, 0.0, 2.0], [3.0, 3.0, 3.0, 3.0]]))
    >>> v.tolist(), i.tolist()
    ([0.0, 3.0], [1, 0])
    """
    if (G.ndim == 2 and G.device.type == "cpu" and G.dtype in (torch.float32, torch.float64)
            and G.shape[1] > 0 and not G.requires_grad):
        i = torch.from_numpy(np.argmin(G.numpy(), axis=1).astype(np.int64, copy=False))
        return G.gather(1, i[:, None]).squeeze(1), i
    return G.min(dim=1)


def _rows_within(row_bytes: int, rows: int, memory_bytes: int) -> int:
    """Rows per block so that a block of ``rows_per_block * row_bytes`` bytes fits
    ``memory_bytes``: all ``rows`` when they fit, never fewer than one.

    Examples
    --------
    >>> _rows_within(100, 50, 10_000), _rows_within(100, 50, 1_000), _rows_within(100, 50, 1)
    (50, 10, 1)
    """
    return int(max(1, min(int(rows), int(memory_bytes) // max(1, int(row_bytes)))))


def _block_bytes(r: int, c: int, d: int, esize: int, euclid: bool) -> int:
    extra = (r + c) * (2 * d + 4) * esize if euclid else 0
    return r * c * esize + r * (esize + 8) + extra


def _plan_blocks(n: int, m: int, d: int, esize: int, euclid: bool,
                 memory_bytes: int) -> tuple[int, int]:
    """Largest (rows, cols) block whose working set fits ``memory_bytes`` (whole rows first)."""
    per_row = _block_bytes(1, m, d, esize, euclid) - _block_bytes(0, m, d, esize, euclid)
    rows = (memory_bytes - _block_bytes(0, m, d, esize, euclid)) // per_row
    if rows >= 1:
        return int(min(rows, n)), m
    per_col = _block_bytes(1, 1, d, esize, euclid) - _block_bytes(1, 0, d, esize, euclid)
    cols = (memory_bytes - _block_bytes(1, 0, d, esize, euclid)) // per_col
    return 1, int(max(1, min(cols, m)))  # below one element's working set: best effort


def _nn_cdist(
    X: torch.Tensor, Y: torch.Tensor, p: float, memory_bytes: int,
    stats: CdistStats | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Chunked exact NN with torch.cdist; a block's working set stays within ``memory_bytes``.

    Ties resolve to the lowest index (``min`` returns the first minimum of a block; a later
    block replaces the current best only when strictly closer).
    """
    n, m = X.shape[0], Y.shape[0]
    d = X.shape[1]
    esize = X.element_size()
    euclid = float(p) == 2.0
    rows, cols = _plan_blocks(n, m, d, esize, euclid, int(memory_bytes))
    best_d = torch.full((n,), math.inf, dtype=X.dtype, device=X.device)
    best_i = torch.zeros(n, dtype=torch.int64, device=X.device)
    peak = 0
    for r0 in range(0, n, rows):
        Xr = X[r0 : r0 + rows]
        bd, bi = best_d[r0 : r0 + rows], best_i[r0 : r0 + rows]  # views
        for c0 in range(0, m, cols):
            Yc = Y[c0 : c0 + cols]
            peak = max(peak, _block_bytes(Xr.shape[0], Yc.shape[0], d, esize, euclid))
            D = torch.cdist(Xr, Yc, p=p)
            dmin, i = _min_rows(D)  # first (lowest) index among ties
            del D
            if c0 == 0:
                bd.copy_(dmin)
                bi.copy_(i)
            else:
                better = dmin < bd
                bd.copy_(torch.where(better, dmin, bd))
                bi.copy_(torch.where(better, i + c0, bi))
    for st in (_LAST_CDIST, stats):
        if st is not None:
            st.peak_bytes, st.budget_bytes, st.block = peak, int(memory_bytes), (rows, cols)
    return best_d, best_i


def _kdtree(Y: np.ndarray, leafsize: int = 16) -> cKDTree:
    """A k-d tree of descriptor rows: sliding-midpoint splits with loose node boxes.

    The same (exact) neighbours as scipy's defaults, queries 40 % faster on heat-kernel
    descriptors (SCAPE, d = 20, L-inf: 4.8 -> 2.9 ms per 1000 queries against 12.5k points;
    the build is ~1 ms either way).
    """
    return cKDTree(Y, leafsize=leafsize, balanced_tree=False, compact_nodes=False)


# Leaf size of the landmark scores' trees (_TreeCache), which are asked for distances only: a
# nearest distance is the same float whatever the tree, so the scores keep their bits. 32
# instead of scipy's 16: builds + queries 6 % faster on the trees of real matches (SHREC'16
# holed pieces against 10k-vertex wholes 8.5 -> 7.9 ms, TOSCA 4.6 -> 4.4 ms per tree;
# BENCHMARKS.md, thirty-third session).
_SCORE_LEAFSIZE = 32


def _resolve_engine(engine: str, X: torch.Tensor) -> str:
    """``"auto"`` made concrete for queries ``X`` (see :func:`nearest_neighbors`)."""
    if engine == "auto":
        return "kdtree" if (X.device.type == "cpu" and X.shape[1] <= 40) else "cdist"
    return engine


def _tree_query(tree: cKDTree, X: torch.Tensor, p: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest neighbour in a k-d tree of every row of ``X`` (distances in ``X``'s dtype)."""
    # as many query threads as torch may use (1 in batch workers: no oversubscription)
    d, i = tree.query(X.detach().cpu().double().numpy(), k=1, p=p,
                      workers=torch.get_num_threads())
    return (torch.from_numpy(d).to(X.dtype).to(X.device),
            torch.from_numpy(i.astype(np.int64)).to(X.device))


class _TreeCache:
    """k-d trees of descriptor sets kept for reuse within a byte budget (a tree over ``n``
    rows of ``d`` columns is counted as ``8 n (d + 2)`` bytes: its data and index arrays);
    past the budget, trees are built and not kept. For distances only: the landmark scores
    (leaf size ``_SCORE_LEAFSIZE``; which of two equidistant rows a tree returns may differ)."""

    def __init__(self, budget_bytes: int = WORK_BYTES) -> None:
        self.budget = int(budget_bytes)
        self.used = 0
        self.trees: dict = {}

    def get(self, key: object, rows: Callable[[], np.ndarray]) -> cKDTree:
        """The tree cached under ``key``, else one of ``rows()`` (kept if it fits)."""
        tree = self.trees.get(key)
        if tree is None:
            Y = rows()
            tree = _kdtree(Y, _SCORE_LEAFSIZE)
            size = 8 * Y.shape[0] * (Y.shape[1] + 2)
            if self.used + size <= self.budget:
                self.trees[key] = tree
                self.used += size
        return tree


def nearest_neighbors(
    X: torch.Tensor,
    Y: torch.Tensor,
    p: float = math.inf,
    engine: str = "auto",
    memory_bytes: int = WORK_BYTES,
    stats: CdistStats | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact nearest neighbour in ``Y`` of every row of ``X`` under the Minkowski p-norm.

    Parameters
    ----------
    X : torch.Tensor, shape (n, d)
    Y : torch.Tensor, shape (m, d)
    p : float
        Norm (default ``inf``, the paper's L-infinity).
    engine : {"auto", "cdist", "kdtree"}
        ``"cdist"``: ``torch.cdist`` in chunks of at most ``memory_bytes`` (any device);
        ``"kdtree"``: ``scipy.spatial.cKDTree`` (CPU; 40-60x faster at d = 10-20).
        ``"auto"``: kdtree for CPU tensors with d <= 40, cdist otherwise.
    memory_bytes : int
        Budget of the cdist engine's distance blocks.
    stats : CdistStats, optional
        Filled by the cdist engine with its block plan and peak working set (untouched by
        the k-d tree).

    Returns
    -------
    dist : torch.Tensor, shape (n,)
    index : torch.Tensor, int64, shape (n,)
        Ties: cdist returns the lowest index; the k-d tree is deterministic for a given input.

    Examples
    --------
    >>> X = torch.tensor([[0.0, 0.0], [1.0, 1.0]])
    >>> nearest_neighbors(X, torch.tensor([[1.0, 0.9], [0.1, 0.0]]))[1].tolist()
    [1, 0]
    """
    if X.ndim != 2 or Y.ndim != 2 or X.shape[1] != Y.shape[1]:
        raise ValueError(f"descriptor shapes {tuple(X.shape)} and {tuple(Y.shape)} do not match")
    engine = _resolve_engine(engine, X)
    if engine == "cdist":
        return _nn_cdist(X, Y.to(X.dtype), p, memory_bytes, stats)
    if engine == "kdtree":
        return _tree_query(_kdtree(Y.detach().cpu().double().numpy()), X, p)
    raise ValueError(f"unknown engine {engine!r}; use 'auto', 'cdist' or 'kdtree'")


@dataclass
class _Factors:
    """A descriptor ``D = P @ C`` (``[n, d]``) kept in factored form; ``C`` None: ``D = P``."""

    P: torch.Tensor  # [n, k]
    C: torch.Tensor | None = None  # [k, d]

    def sqnorms(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """``|D[x]|^2`` of the rows (all when None), at ``O(n min(k, d) k)``."""
        P = self.P if rows is None else self.P[rows]
        if self.C is None:
            return (P * P).sum(dim=1)
        if self.C.shape[1] < self.C.shape[0]:  # d < k: the explicit rows are cheaper
            D = P @ self.C
            return (D * D).sum(dim=1)
        return ((P @ (self.C @ self.C.T)) * P).sum(dim=1)


def _blocked_argmin(X: torch.Tensor, Y: torch.Tensor, xx: torch.Tensor, yy: torch.Tensor,
                    memory_bytes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``min_y xx + yy - 2 x.y`` over the rows of Y, in row blocks of X within the budget."""
    m = Y.shape[0]
    rows = max(1, int(memory_bytes // max(1, X.element_size() * m)))  # one [rows, m] block
    best_d = torch.empty(X.shape[0], dtype=X.dtype, device=X.device)
    best_i = torch.empty(X.shape[0], dtype=torch.int64, device=X.device)
    for r0 in range(0, X.shape[0], rows):
        G = torch.addmm(yy[None, :], X[r0 : r0 + rows], Y.T, alpha=-2.0)
        d, i = _min_rows(G)
        best_d[r0 : r0 + rows] = (d + xx[r0 : r0 + rows]).clamp_min(0)
        best_i[r0 : r0 + rows] = i
    return best_d, best_i


def _argmin_certified(X: torch.Tensor, Y: torch.Tensor, memory_bytes: int = WORK_BYTES
                      ) -> torch.Tensor:
    """Nearest row of ``Y`` to every row of ``X`` (L2), exactly as a float64 search would find
    it, at the cost of a float32 one.

    The float32 search keeps each row's two smallest squared distances; its rounding error is
    bounded by ``(k + 4) u (2 |x| max|y| + max|y|^2)`` (``u = 2^-24``, a worst-case bound of a
    ``k``-term dot product, the conversions and the sums), so a row whose two smallest are
    farther apart than twice that bound has its float64 nearest neighbour; the other rows
    (exact ties included; measured: 0-5 % of the rows on TOSCA dense maps) are searched again
    in float64 (:func:`_blocked_argmin`, ties to the lowest index). The result is therefore
    the float64 brute force's, whatever the blocks. The ``[rows, m]`` float32 blocks are
    kept within ``min(memory_bytes, CACHE_BYTES)``, so each is reduced while it is still in
    the cache. Timings against the cluster-pruned search, the float64 brute force and scipy's
    ``cKDTree``: ``scripts/bench.py fine`` (BENCHMARKS.md).

    Parameters
    ----------
    X : torch.Tensor, float64, shape (n, k)
    Y : torch.Tensor, float64, shape (m, k)
    memory_bytes : int
        Working-set budget of one block.

    Returns
    -------
    torch.Tensor, int64, shape (n,)

    Examples
    --------
    >>> X = torch.tensor([[0.0, 0.0], [1.0, 1.0]], dtype=torch.float64)
    >>> _argmin_certified(X, torch.tensor([[1.0, 0.9], [0.1, 0.0]], dtype=torch.float64))
    tensor([1, 0])
    """
    n, k = X.shape
    m = Y.shape[0]
    xx, yy = (X * X).sum(1), (Y * Y).sum(1)
    X32, Y32, yy32 = X.float(), Y.float(), yy.float()
    ymax2 = float(yy.max()) if m else 0.0
    tol = (k + 4) * 2.0**-24 * (2.0 * xx.sqrt() * math.sqrt(ymax2) + ymax2)
    idx = torch.empty(n, dtype=torch.int64, device=X.device)
    unsure = torch.zeros(n, dtype=torch.bool, device=X.device)
    rows = max(1, int(min(memory_bytes, CACHE_BYTES) // max(1, 4 * m)))
    for r0 in range(0, n, rows):
        G = torch.addmm(yy32[None, :], X32[r0 : r0 + rows], Y32.T, alpha=-2.0)
        if m == 1:
            idx[r0 : r0 + rows] = 0
            continue
        v0, i0 = _min_rows(G)  # the smallest, then the second: the smallest left
        v1 = G.scatter_(1, i0[:, None], math.inf).amin(dim=1)
        idx[r0 : r0 + rows] = i0
        unsure[r0 : r0 + rows] = (v1 - v0).double() <= 2.0 * tol[r0 : r0 + rows]
    redo = unsure.nonzero().flatten()
    if redo.numel():
        idx[redo] = _blocked_argmin(X[redo], Y, xx[redo], yy, memory_bytes)[1]
    return idx


def _nn_factors(X: _Factors, rows: torch.Tensor | None, Y: _Factors,
                memory_bytes: int = WORK_BYTES) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest neighbour in L2 of the rows ``rows`` of ``X``'s descriptor among ``Y``'s.

    ``|x - y|^2 = |x|^2 + |y|^2 - 2 Ps(x) (Cs Ct^T) Pt(y)^T``: the big product has the inner
    dimension of the factors (eigenmodes, ~60) instead of the descriptor's (landmarks x times,
    240), and no ``[m, d]`` target descriptor is ever formed. Exact up to rounding (the
    factors' dtype); returns squared distances and indices (ties: the lowest index within a
    block).
    """
    Ps = X.P if rows is None else X.P[rows]
    Pt = Y.P
    if X.C is None and Y.C is None:  # explicit descriptors: centre on Y's mean first
        c = Pt.mean(dim=0)
        Ps, Pt = Ps - c, Pt - c
        return _blocked_argmin(Ps, Pt, (Ps * Ps).sum(1), (Pt * Pt).sum(1), memory_bytes)
    if X.C is not None and Y.C is not None:
        Q = Ps @ (X.C @ Y.C.T)
    elif X.C is not None:
        Q = Ps @ X.C
    else:
        assert Y.C is not None  # (neither factored returned above)
        Q = Ps @ Y.C.T
    return _blocked_argmin(Q, Pt, X.sqnorms(rows), Y.sqnorms(), memory_bytes)


def _nn_factors_pruned(X: _Factors, rows: torch.Tensor | None, Y: _Factors,
                       centres: torch.Tensor, memory_bytes: int = WORK_BYTES
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_nn_factors` (both factored) with exact cluster pruning, for dense maps.

    The targets are grouped around ``centres`` (target vertices) by nearest centre in
    descriptor space; cluster ``c`` has radius ``r_c``. A query ``x`` at distance ``d_c``
    from centre ``c`` is at least ``d_c - r_c`` from every member (triangle inequality), and
    at most ``b(x) = min_c d_c`` from its nearest neighbour (a centre is a target), so only
    clusters with ``d_c - r_c <= b(x)`` are searched. Same minimum as the brute force (up to
    float64 rounding; ties between clusters go to the first cluster searched). Measured on a
    SCAPE pair with 447 centres: 1.2 % of the ``n m`` pairs are searched, the rest is pruned.
    Cost: ``O((n + m) C k)`` for the centres plus the searched pairs. Memory: blocks of query
    rows against all centres, and of query rows against one cluster's members, each within
    ``memory_bytes`` (a cluster can be 20x its average size: 2715 members for a mean of 122
    on a 239k-vertex KIDS target).
    """
    assert X.C is not None and Y.C is not None  # both factored (every caller's)
    Ps = X.P if rows is None else X.P[rows]
    Pt, Pc = Y.P, Y.P[centres]
    Q = Ps @ (X.C @ Y.C.T)  # [n, k_t]: x.y = Q(x) . Pt(y)
    G = Y.C @ Y.C.T  # [k_t, k_t]: y.y' = Pt(y) G Pt(y')^T
    xx, yy = X.sqnorms(rows), ((Pt @ G) * Pt).sum(dim=1)
    # targets to centres (descriptor space) and the cluster radii
    dm2, lab = _blocked_argmin(Pt, Pc @ G, yy, yy[centres], memory_bytes)
    C = centres.numel()
    radius = torch.zeros(C, dtype=Pt.dtype, device=Pt.device).scatter_reduce_(
        0, lab, dm2.sqrt(), reduce="amax")
    order = torch.argsort(lab, stable=True)
    ends = torch.cumsum(torch.bincount(lab, minlength=C), 0).tolist()
    starts = [0, *ends[:-1]]
    n = Q.shape[0]
    best_d = torch.empty(n, dtype=Q.dtype, device=Q.device)
    best_i = torch.empty(n, dtype=torch.int64, device=Q.device)
    block = max(1, int(memory_bytes // max(1, 3 * C * Q.element_size())))
    slack = 1e-7 * float((xx.max() + yy.max()).sqrt())  # rounding of the expanded form
    for r0 in range(0, n, block):
        q, xb = Q[r0 : r0 + block], xx[r0 : r0 + block]
        # in place: each temporary of a [block, C] float64 block is a fresh allocation whose
        # pages the kernel zeroes on first touch (half of this step's time on SCAPE)
        dc = torch.addmm(yy[centres][None, :], q, Pc.T, alpha=-2.0)
        dc.add_(xb[:, None]).clamp_min_(0).sqrt_()
        b0, c0 = _min_rows(dc)
        bd, bi = b0 * b0, centres[c0].clone()
        # need[c, x]: cluster c may hold a nearer target for x
        need = dc.sub_(radius[None, :]).T <= (b0 + slack)[None, :]
        for c in torch.nonzero(need.any(dim=1)).flatten().tolist():
            xi = torch.nonzero(need[c]).flatten()
            mem = order[starts[c] : ends[c]]
            ym, Pm = yy[mem][None, :], Pt[mem].T
            # [queries, members] distances (and one temporary) within the budget: a
            # cluster may hold far more than its m / C share of the targets
            step = _rows_within(2 * mem.numel() * Q.element_size(), xi.numel(), memory_bytes)
            for s0 in range(0, xi.numel(), step):
                x = xi[s0 : s0 + step]
                d2 = torch.addmm(ym, q[x], Pm, alpha=-2.0) + xb[x, None]
                dmin, am = _min_rows(d2)
                better = dmin < bd[x]
                bd[x] = torch.where(better, dmin, bd[x])
                bi[x] = torch.where(better, mem[am], bi[x])
        best_d[r0 : r0 + block] = bd.clamp_min(0)
        best_i[r0 : r0 + block] = bi
    return best_d, best_i
