"""One-point isometric matching (the paper's Section 4), batched.

Pipeline of :func:`match` (source M with n vertices, target N with m vertices):

1. One :class:`PreparedShape` per mesh: heat kernel solver, t-scaled HKS, feature points (local
   maxima of the HKS at a large time over the 2-ring), vertex normals.
2. **Landmark search**: fix ``p`` on M (default: the strongest feature), score **every**
   candidate ``q`` on N at once by ``E(p, q) = sum_x min_y ||Phi_p(x) - Phi_q(y)||_inf^2`` and
   rank them.
3. **Dense map** ``f(x) = argmin_y ||Phi_p(x) - Phi_q(y)||_inf`` (HKS appended by default).
4. Optional **greedy extra landmarks** (paper: add ``(p2, q2)`` among feature pairs minimising the
   combined error), **orientation test** (the direct map of a bilaterally symmetric shape keeps
   the surface orientation, the mirror map reverses it), and **refinement** by correspondence
   augmentation (landmarks sampled on M, their images taken from the current map, recompute).
5. The direct map is the best orientation-preserving hypothesis, the symmetric map the best
   orientation-reversing one.

``method="paper"`` runs steps 1–3 (+ greedy landmarks) exactly as the paper; the default
``method="refine"`` adds the orientation test and the refinement.
"""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from .descriptors import (
    farthest_point_sampling,
    feature_points,
    heat_kernel_map,
    hks,
    ring_neighbors,
)
from .eigen import DEFAULT_EIGENPAIRS
from .heat import HeatKernel, threads
from .mesh import Mesh, MeshError

__all__ = [
    "Correspondence",
    "PreparedShape",
    "prepare",
    "nearest_neighbors",
    "landmark_scores",
    "dense_map",
    "orientation_score",
    "match",
    "symmetry",
]


# ------------------------------------------------------------------------------------------
# nearest-neighbour engines
# ------------------------------------------------------------------------------------------
@dataclass
class _Budget:
    """Bookkeeping of the last cdist call: the largest working set of one block (bytes).

    A block of ``r`` query rows against ``c`` reference rows (dimension ``d``, element size
    ``e``) holds the distance block ``r c e``, the ``min`` outputs ``r (e + 8)`` and, for
    ``p = 2`` (where ``torch.cdist`` goes through a matrix product), the padded copies and
    their temporaries, at most ``(r + c)(2d + 4) e``.
    """

    peak_bytes: int = 0
    budget_bytes: int = 0
    block: tuple[int, int] = (0, 0)


LAST_CDIST_PEAK = _Budget()


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
    X: torch.Tensor, Y: torch.Tensor, p: float, memory_bytes: int
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
            dmin, i = D.min(dim=1)  # first (lowest) index among ties
            del D
            if c0 == 0:
                bd.copy_(dmin)
                bi.copy_(i)
            else:
                better = dmin < bd
                bd.copy_(torch.where(better, dmin, bd))
                bi.copy_(torch.where(better, i + c0, bi))
    LAST_CDIST_PEAK.peak_bytes = peak
    LAST_CDIST_PEAK.budget_bytes = int(memory_bytes)
    LAST_CDIST_PEAK.block = (rows, cols)
    return best_d, best_i


def _kdtree(Y: np.ndarray) -> cKDTree:
    """A k-d tree of descriptor rows: sliding-midpoint splits with loose node boxes.

    The same (exact) neighbours as scipy's defaults, queries 40 % faster on heat-kernel
    descriptors (SCAPE, d = 20, L-inf: 4.8 -> 2.9 ms per 1000 queries against 12.5k points;
    the build is ~1 ms either way).
    """
    return cKDTree(Y, balanced_tree=False, compact_nodes=False)


def nearest_neighbors(
    X: torch.Tensor,
    Y: torch.Tensor,
    p: float = math.inf,
    engine: str = "auto",
    memory_bytes: int = 256 * 2**20,
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
    if engine == "auto":
        engine = "kdtree" if (X.device.type == "cpu" and X.shape[1] <= 40) else "cdist"
    if engine == "cdist":
        return _nn_cdist(X, Y.to(X.dtype), p, memory_bytes)
    if engine == "kdtree":
        tree = _kdtree(Y.detach().cpu().double().numpy())
        # as many query threads as torch may use (1 in batch workers: no oversubscription)
        workers = torch.get_num_threads()
        d, i = tree.query(X.detach().cpu().double().numpy(), k=1, p=p, workers=workers)
        return (torch.from_numpy(d).to(X.dtype).to(X.device),
                torch.from_numpy(i.astype(np.int64)).to(X.device))
    raise ValueError(f"unknown engine {engine!r}; use 'auto', 'cdist' or 'kdtree'")


# ------------------------------------------------------------------------------------------
# prepared shapes
# ------------------------------------------------------------------------------------------
@dataclass
class PreparedShape:
    """A mesh with everything matching needs, computed once.

    Attributes
    ----------
    mesh : Mesh
    hk : HeatKernel
        Heat kernel solver; its ``times`` are the descriptor's time samples.
    features : torch.Tensor, shape (f,)
        Feature points, strongest first.
    normals : numpy.ndarray, shape (n, 3)
        Area-weighted vertex normals (for the orientation test).
    hks : torch.Tensor, shape (n, J)
        t-scaled HKS at ``hk.times`` (the augmentation coordinates; recomputed if the times
        change).
    own_times : torch.Tensor, shape (J,), optional
        The times the shape was prepared with. :func:`match` gives a target its source's
        times; the target's self-symmetry (the mirror hypothesis) is computed at these own
        times instead, once per prepared target, whatever the source.
    """

    mesh: Mesh
    hk: HeatKernel
    features: torch.Tensor
    normals: np.ndarray
    timings: dict = field(default_factory=dict)
    own_times: torch.Tensor | None = None  # the times it was prepared with (a target's
    # hk.times become its source's; its self-symmetry is computed at these, once)
    _hks: torch.Tensor | None = None
    _hks_times: torch.Tensor | None = None

    @property
    def n(self) -> int:
        return self.mesh.n_vertices

    @property
    def hks(self) -> torch.Tensor:
        t = self.hk.times
        if self._hks is None or self._hks_times is None or not (
            self._hks_times.shape == t.shape and torch.equal(self._hks_times, t)
        ):
            self._hks = hks(self.hk)
            self._hks_times = t.clone()
        return self._hks


def _fps(shape: PreparedShape, k: int) -> torch.Tensor:
    """First ``k`` farthest-point samples of the shape's vertices, cached on the shape (the
    greedy order is deterministic, so shorter requests are prefixes of longer ones)."""
    k = min(int(k), shape.n)
    cached = shape.__dict__.get("_fps_cache")
    if cached is None or cached.numel() < k:
        V, _ = shape.mesh.numpy()
        cached = farthest_point_sampling(V, max(k, 256))
        shape.__dict__["_fps_cache"] = cached
    return cached[:k]


def _vertex_normals(mesh: Mesh) -> np.ndarray:
    V, F = mesh.numpy()
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area-weighted
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


def prepare(
    mesh: Mesh,
    times: str | Sequence[float] | torch.Tensor | None = "adaptive",
    *,
    feature_time: float = 0.05,
    max_features: int = 50,
    k: int = DEFAULT_EIGENPAIRS,
    rtol: float = 1e-6,
    kind: str = "cotan",
    boundary: str = "neumann",
    hk: HeatKernel | None = None,
    eigenpairs: tuple | None = None,
    num_threads: int | None = None,
) -> PreparedShape:
    """Precompute a shape for matching (heat kernel, HKS, features, normals).

    Parameters
    ----------
    mesh : Mesh
    times : "adaptive", "paper", None or sequence of float
        ``"adaptive"`` (default): 10 log-spaced samples in ``[4 ln10 / lambda_k,
        4 ln10 / lambda_1]`` from the shape's own spectrum, computed from the eigenbasis
        alone (accurate to about 1e-4 there). ``"paper"`` / None: the paper's 10 in
        [0.001, 2] at unit area, certified to ``rtol`` by the hybrid heat kernel. A sequence:
        those times (hybrid, certified).
    feature_time : float
        Time of the HKS whose 2-ring maxima are the feature points.
    max_features : int
        Cap on the number of feature points (strongest first).
    k : int
        Eigenpairs of the heat kernel's eigenbasis (default 100).
    rtol, kind, boundary, num_threads
        Passed to :class:`HeatKernel`.
    hk : HeatKernel, optional
        A ready solver (e.g. rebuilt from a disk cache); ``times`` is then ignored.
    eigenpairs : (lam, phi), optional
        The ``k`` eigenpairs of the mesh's operator if already known (shapes (k,), (n, k);
        e.g. from :class:`torchheat.eigen.EigenWorkers`); skips the eigensolve.

    Returns
    -------
    PreparedShape

    Raises
    ------
    MeshError
        A mesh too small to match: fewer vertices than ``k`` (the time samples come from the
        ``k``-th eigenvalue, which a mesh of fewer vertices does not have), or no interior
        vertex (a strip or fan of triangles, every vertex on the boundary).

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> s = trimesh.creation.icosphere(2)
    >>> prepare(Mesh(s.vertices, s.faces)).hks.shape
    torch.Size([162, 10])
    >>> prepare(Mesh(s.vertices, s.faces, name="ico2"), k=200)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    torchheat.meshio.MeshError: ico2: 162 vertices, too few to match: ... at least 200 vertices; ...
    """
    _check_matchable(mesh, k if hk is None else hk.k)
    t0 = time.perf_counter()
    if hk is None:
        if isinstance(times, str):
            if times not in ("adaptive", "paper"):
                raise ValueError(f"unknown times {times!r}; use 'adaptive', 'paper' or a list")
            adaptive = times == "adaptive"
            times = None
        else:
            adaptive = False
        hk = HeatKernel(mesh, times=times, rtol=rtol, k=k, kind=kind, boundary=boundary,
                        num_threads=num_threads, method="spectral" if adaptive else "auto",
                        eigenpairs=eigenpairs)
        if adaptive:
            hk.set_times(hk.adaptive_times())
    t1 = time.perf_counter()
    lam = hk.eigenvalues.numpy()
    phi = hk.eigenvectors.numpy()
    sig = (phi**2) @ np.exp(-feature_time * lam)  # HKS at the feature time
    feats = feature_points(mesh, sig, rings=2, max_features=max_features)
    normals = _vertex_normals(mesh)
    t2 = time.perf_counter()
    return PreparedShape(mesh, hk, feats, normals,
                         {"heat_kernel": t1 - t0, "descriptors": t2 - t1},
                         own_times=hk.times.clone())


def _check_matchable(mesh: Mesh, k: int, remedy: str | None = None) -> None:
    """Refuse a mesh too small for the descriptors: fewer than ``k`` vertices, or no interior
    vertex.

    The minimum is ``k`` vertices (100 by default, :data:`~torchheat.eigen.DEFAULT_EIGENPAIRS`):
    the heat kernel map and the HKS are built on the ``k`` lowest eigenpairs of the Laplacian,
    and the adaptive time samples span ``[4 ln10 / lambda_k, 4 ln10 / lambda_1]``, so a mesh
    needs a ``k``-th eigenvalue, i.e. at least ``k`` vertices; with fewer, the basis is the
    whole (mesh-resolution) spectrum and the target, which takes the source's times, is
    asked for a band it does not resolve. A mesh without an interior vertex is a strip or
    fan of triangles: no vertex has a complete one-ring, so the Laplacian has no interior
    stencil and there is no surface to match. ``remedy`` replaces the advice of the message
    (the command line has no ``k``).
    """
    n = mesh.n_vertices
    label = mesh.name or "mesh"
    piece = "" if mesh.n_input_vertices == n else (
        f" in its largest connected component (the file has {mesh.n_input_vertices})")
    if n < k:
        advice = remedy or (f"use a finer mesh (subdivide it), or prepare it with fewer "
                            f"eigenpairs: prepare(mesh, k=K) with K <= {n}")
        raise MeshError(
            f"{label}: {n} vertices{piece}, too few to match: the descriptors are built from "
            f"the {k} lowest eigenpairs of the Laplacian (the time samples from the last of "
            f"them), so a mesh needs at least {k} vertices; {advice}"
        )
    if bool(mesh.boundary_vertices().all()):
        advice = remedy or "use a finer mesh (subdivide it)"
        raise MeshError(
            f"{label}: no interior vertex (all {n} vertices{piece} lie on the boundary: a "
            "strip or fan of triangles), too little surface to match: a mesh needs at least "
            f"one vertex with a complete ring of triangles; {advice}"
        )


def _as_prepared(x, **kw) -> PreparedShape:
    if isinstance(x, PreparedShape):
        return x
    if isinstance(x, Mesh):
        return prepare(x, **kw)
    raise TypeError(f"expected a Mesh or PreparedShape, got {type(x).__name__}")


# ------------------------------------------------------------------------------------------
# scoring and maps
# ------------------------------------------------------------------------------------------
# Descriptors of the landmark sets a match asks for, memoised per shape: the same one-point
# descriptor is wanted by the candidate scoring, the twin and ambiguity tests, every expansion
# and every hypothesis seeded from it (94 of 146 computations on a SCAPE pair were repeats).
_DESC_CACHE_BYTES = 64 * 2**20
_DESC_LOCK = threading.Lock()  # the background self-symmetry may share the shape's cache


def _descriptor(shape: PreparedShape, landmarks, use_hks: bool, columns=None) -> torch.Tensor:
    """``[n, L J (+ J)]`` HKM (+ HKS) of ``landmarks``; read-only (it may be cached)."""
    key = None
    if columns is None:
        key = (tuple(int(v) for v in np.atleast_1d(np.asarray(landmarks))), bool(use_hks),
               tuple(shape.hk.times.tolist()))
        with _DESC_LOCK:
            hit = shape.__dict__.get("_desc_cache", {}).get(key)
        if hit is not None:
            return hit
    D = heat_kernel_map(shape.hk, landmarks, columns)
    if use_hks:
        D = torch.cat([D, shape.hks.to(D.dtype)], dim=1)
    if key is not None:
        limit = _DESC_CACHE_BYTES // max(1, D.element_size() * D.numel())
        with _DESC_LOCK:
            cache = shape.__dict__.setdefault("_desc_cache", {})
            while cache and len(cache) >= limit:
                cache.pop(next(iter(cache)))  # oldest first
            if limit > 0:
                cache[key] = D
    return D


def landmark_scores(
    source: PreparedShape,
    target: PreparedShape,
    p: int | Sequence[int],
    candidates: Sequence[int] | torch.Tensor,
    *,
    q_fixed: Sequence[int] = (),
    use_hks: bool = True,
    engine: str = "auto",
    samples: torch.Tensor | None = None,
    memory_bytes: int = 256 * 2**20,
) -> torch.Tensor:
    """Score every candidate ``q`` for the source landmark ``p``.

    ``E(p, q) = sum_x min_y ||Phi_p(x) - Phi_q(y)||_inf^2`` (divided by the number of x).

    Parameters
    ----------
    source, target : PreparedShape
    p : int or sequence of int
        Source landmark; a sequence ``[p_1, ..., p_l]`` scores the last one given the images
        ``q_fixed`` of the others (greedy extra landmarks).
    candidates : sequence of int, shape (c,)
        Target vertices to score.
    q_fixed : sequence of int
        Images of the earlier landmarks.
    use_hks : bool
        Append the HKS coordinates.
    engine : str
        See :func:`nearest_neighbors`.
    samples : torch.Tensor, optional
        Source vertices x summed over (default: all).

    Returns
    -------
    torch.Tensor
        float64 scores, shape (c,) (lower is better).

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> m = trimesh.creation.icosphere(2)
    >>> s = prepare(Mesh(m.vertices, m.faces))
    >>> landmark_scores(s, s, 0, [0, 1]).shape
    torch.Size([2])
    """
    ps = [int(p)] if np.isscalar(p) or isinstance(p, int | np.integer) else [int(v) for v in p]
    qf = [int(v) for v in q_fixed]
    if len(qf) != len(ps) - 1:
        raise ValueError("q_fixed must give the images of all but the last source landmark")
    cand = torch.as_tensor(candidates, dtype=torch.int64).reshape(-1)
    Dp = _descriptor(source, ps, use_hks)
    if samples is not None:
        Dp = Dp[samples]
    Cq = target.hk.columns(cand, certify=False)  # [c, m, J]: all candidates, one call
    J = target.hk.times.numel()
    fixed = heat_kernel_map(target.hk, qf) if qf else None
    t = target.hk.times.to(Cq.dtype)
    scores = torch.empty(cand.numel(), dtype=torch.float64)
    for i in range(cand.numel()):
        parts = [] if fixed is None else [fixed]
        parts.append(Cq[i] * t)
        if use_hks:
            parts.append(target.hks.to(Cq.dtype))
        Dq = torch.cat(parts, dim=1)
        d, _ = nearest_neighbors(Dp, Dq, p=math.inf, engine=engine, memory_bytes=memory_bytes)
        scores[i] = float((d.double() ** 2).mean())
    del J
    return scores


def dense_map(
    source: PreparedShape,
    target: PreparedShape,
    landmarks: Sequence[tuple[int, int]],
    *,
    use_hks: bool = True,
    engine: str = "auto",
    p: float = math.inf,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense map ``f(x) = argmin_y ||Phi(x) - Phi(y)||_p`` from landmark pairs.

    Parameters
    ----------
    source, target : PreparedShape
    landmarks : sequence of (p, q)
    use_hks : bool
    engine : str
    p : float
        Norm of the nearest-neighbour search (paper: inf).

    Returns
    -------
    map : torch.Tensor, int64, shape (n,)
    dist : torch.Tensor, shape (n,)
        Descriptor distance of each vertex to its image.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> m = trimesh.creation.icosphere(2)
    >>> s = prepare(Mesh(m.vertices, m.faces))
    >>> dense_map(s, s, [(0, 0)])[0].shape
    torch.Size([162])
    """
    ps = [int(a) for a, _ in landmarks]
    qs = [int(b) for _, b in landmarks]
    Dp = _descriptor(source, ps, use_hks)
    Dq = _descriptor(target, qs, use_hks)
    d, i = nearest_neighbors(Dp, Dq, p=p, engine=engine)
    return i, d


def _triangles(V: np.ndarray, samples: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Fat triangles ``(s, a, b)`` between neighbouring samples (indices into V)."""
    S = np.asarray(samples)
    _, nb = cKDTree(V[S]).query(V[S], k=min(7, len(S)))
    a = S[nb[:, 1]]
    ea = V[a] - V[S]
    cand = S[nb[:, 2:]]
    eb = V[cand] - V[S][:, None]
    cos = np.abs(np.einsum("ij,icj->ic", ea, eb)) / (
        np.linalg.norm(ea, axis=1)[:, None] * np.linalg.norm(eb, axis=2) + 1e-300
    )
    b = cand[np.arange(len(S)), np.argmin(cos, axis=1)]
    return S, a, b


def _orientation(source, target, tri, f_of) -> float:
    """Mean sign of the image orientation of the triangles ``tri``; ``f_of(idx)`` maps."""
    V, _ = source.mesh.numpy()
    W, _ = target.mesh.numpy()
    s, a, b = tri
    fs, fa, fb = f_of(s), f_of(a), f_of(b)
    o_src = np.einsum("ij,ij->i", np.cross(V[a] - V[s], V[b] - V[s]), source.normals[s])
    o_tgt = np.einsum("ij,ij->i", np.cross(W[fa] - W[fs], W[fb] - W[fs]), target.normals[fs])
    valid = (np.abs(o_src) > 0) & (np.abs(o_tgt) > 0)
    if not valid.any():
        return 0.0
    return float(np.mean(np.sign(o_src[valid]) * np.sign(o_tgt[valid])))


def orientation_score(
    source: PreparedShape, target: PreparedShape, fmap: torch.Tensor, n_samples: int = 64
) -> float:
    """How a map transports the surface orientation, in [-1, 1].

    Fat triangles ``(s, a, b)`` are formed from farthest-point samples of the source and
    their nearest samples, oriented by the source normal at ``s``; the sign of the image
    triangle ``(f(s), f(a), f(b))`` against the target normal at ``f(s)`` is averaged.
    +1: orientation preserved (the direct map), -1: reversed (the mirror map). On TOSCA
    ground-truth maps it reads +0.7..0.85 (direct) and -0.7..-0.9 (symmetric). Vertex normals
    average many faces, so a few flipped triangles (real TOSCA meshes) do not change it.

    Parameters
    ----------
    source, target : PreparedShape
    fmap : torch.Tensor, int64, shape (n,)
    n_samples : int

    Returns
    -------
    float

    Examples
    --------
    >>> import trimesh, torch
    >>> from torchheat import Mesh
    >>> m = trimesh.creation.icosphere(2)
    >>> s = prepare(Mesh(m.vertices, m.faces))
    >>> orientation_score(s, s, torch.arange(162)) > 0.99
    True
    """
    V, _ = source.mesh.numpy()
    f = fmap.detach().cpu().numpy()
    tri = _triangles(V, farthest_point_sampling(V, n_samples).numpy())
    return _orientation(source, target, tri, lambda i: f[i])


# ------------------------------------------------------------------------------------------
# the pipeline
# ------------------------------------------------------------------------------------------
class Correspondence:
    """Result of :func:`match` / :func:`symmetry`.

    Attributes
    ----------
    map : torch.Tensor, int64, shape (n_source,)
        Target vertex of every source vertex (the direct map).
    landmarks : list of (int, int)
        Landmark pairs (p, q) the direct map was computed from (first: the one-point match;
        with refinement, followed by the augmented landmarks).
    candidates : torch.Tensor, int64, shape (c,)
        Target candidates for the first source landmark, ranked best first.
    scores : torch.Tensor, float64, shape (c,)
        Their scores ``E(p, q)`` (ascending).
    symmetric_map : torch.Tensor or None
        The intrinsic-symmetric alternative, if one was found.
    symmetric_landmarks : list of (int, int) or None
    orientation : float
        Orientation score of the direct map (+1 preserving), NaN if not tested.
    info : dict
        Timings (s) per stage, the options used and the hypotheses considered.
    source_vertex_map, target_vertex_map : torch.Tensor or None
        int64, shapes (n_source,) and (n_target,): the index in the input file of every
        vertex of the matched meshes (their :attr:`Mesh.vertex_map`), for a mesh that
        ``largest_component=True`` cut; None for one that kept all its vertices.
    n_source_input : int or None
        Number of vertices of the source file (:attr:`Mesh.n_input_vertices`); needed
        with ``source_vertex_map``.

    Notes
    -----
    **Vertex numbering.** ``map``, ``symmetric_map``, ``landmarks`` and ``candidates`` use
    the vertex indices of the meshes that were matched, so that ``target.vertices[map]``
    is the image of ``source.vertices``. They differ from the files' indices only for meshes
    loaded with ``largest_component=True`` (``--largest-component`` on the command line):
    :meth:`full_map` and :meth:`full_symmetric_map` give the maps in the files' numbering,
    one entry per vertex of the source file, ``-1`` for a source vertex that was dropped
    (they are what ``torchheat match`` writes).


    ``map`` and ``symmetric_map`` may be given as zero-argument callables: the dense map is
    then computed on first access and kept (the refined pipeline's last round is a dense
    ``n x m`` search, the most expensive single step on large meshes, so a caller that only
    needs one of the two maps pays for one). :attr:`has_symmetric_map` tells whether there is
    a symmetric map without computing it. Until then the result keeps references to the two
    prepared shapes.
    """

    def __init__(
        self,
        map: torch.Tensor | Callable[[], torch.Tensor],
        landmarks: list,
        candidates: torch.Tensor,
        scores: torch.Tensor,
        symmetric_map: torch.Tensor | Callable[[], torch.Tensor] | None = None,
        symmetric_landmarks: list | None = None,
        orientation: float = float("nan"),
        info: dict | None = None,
        *,
        source_vertex_map: torch.Tensor | None = None,
        target_vertex_map: torch.Tensor | None = None,
        n_source_input: int | None = None,
    ) -> None:
        self._map = map
        self._symmetric_map = symmetric_map
        self.landmarks = landmarks
        self.candidates = candidates
        self.scores = scores
        self.symmetric_landmarks = symmetric_landmarks
        self.orientation = orientation
        self.info = {} if info is None else info
        if source_vertex_map is not None and n_source_input is None:
            raise ValueError("source_vertex_map needs n_source_input (the number of vertices "
                             "of the source file)")
        self.source_vertex_map = source_vertex_map
        self.target_vertex_map = target_vertex_map
        self.n_source_input = n_source_input

    @property
    def map(self) -> torch.Tensor:
        if callable(self._map):
            self._map = self._map()
        return self._map

    @map.setter
    def map(self, value: torch.Tensor) -> None:
        self._map = value

    @property
    def symmetric_map(self) -> torch.Tensor | None:
        if callable(self._symmetric_map):
            self._symmetric_map = self._symmetric_map()
        return self._symmetric_map

    @symmetric_map.setter
    def symmetric_map(self, value: torch.Tensor | None) -> None:
        self._symmetric_map = value

    @property
    def has_symmetric_map(self) -> bool:
        """Whether a symmetric map was found (without computing it)."""
        return self._symmetric_map is not None

    def full_map(self) -> torch.Tensor:
        """The direct map in the numbering of the input files.

        Returns
        -------
        torch.Tensor
            int64, shape (n_source_input,): for every vertex of the source *file*, the index
            in the target *file* of its image, or ``-1`` if the vertex was dropped by
            ``largest_component=True``. Equal to :attr:`map` when no vertex was dropped.

        Examples
        --------
        >>> import numpy as np, trimesh
        >>> from torchheat import Mesh
        >>> m = trimesh.creation.icosphere(2)
        >>> V = m.vertices * [1.0, 0.8, 0.6]
        >>> V2 = np.vstack([V, V[:3] + [5.0, 0, 0]])  # plus a stray triangle, far away
        >>> F2 = np.vstack([m.faces, [[162, 163, 164]]])
        >>> M = Mesh(V2, F2, largest_component=True)  # the triangle's vertices are dropped
        >>> corr = match(M, M, method="paper")
        >>> corr.map.shape, corr.full_map().shape
        (torch.Size([162]), torch.Size([165]))
        >>> corr.full_map()[-3:].tolist()
        [-1, -1, -1]
        """
        return self._in_files(self.map)

    def full_symmetric_map(self) -> torch.Tensor | None:
        """:attr:`symmetric_map` in the numbering of the input files (see :meth:`full_map`).

        Returns
        -------
        torch.Tensor or None
            int64, shape (n_source_input,), ``-1`` for dropped source vertices; None when
            there is no symmetric map.
        """
        return self._in_files(self.symmetric_map)

    def _in_files(self, f: torch.Tensor | None) -> torch.Tensor | None:
        if f is None:
            return None
        if self.target_vertex_map is not None:
            f = self.target_vertex_map.to(f.device)[f]
        svm = self.source_vertex_map
        if svm is None or svm.numel() == self.n_source_input:
            return f  # nothing dropped: vertex_map is the identity
        full = torch.full((int(self.n_source_input),), -1, dtype=f.dtype, device=f.device)
        full[svm.to(f.device)] = f
        return full

    def __repr__(self) -> str:
        n = "lazy" if callable(self._map) else tuple(self._map.shape)
        return (f"Correspondence(map={n}, landmarks={len(self.landmarks)}, "
                f"symmetric={self.has_symmetric_map}, orientation={self.orientation:+.3f})")


def _numbering(src: PreparedShape, tgt: PreparedShape) -> dict:
    """The vertex numbering of the files behind two prepared shapes (Correspondence args);
    None for a mesh that kept all its vertices."""
    def vertex_map(mesh: Mesh) -> torch.Tensor | None:
        return None if mesh.n_vertices == mesh.n_input_vertices else mesh.vertex_map

    return {"source_vertex_map": vertex_map(src.mesh), "target_vertex_map": vertex_map(tgt.mesh),
            "n_source_input": src.mesh.n_input_vertices}


def _distinct(cands: torch.Tensor, V: np.ndarray, radius: float, limit: int) -> list[int]:
    """Keep candidates (in rank order) farther than ``radius`` from every kept one."""
    kept: list[int] = []
    for c in cands.tolist():
        if all(np.linalg.norm(V[c] - V[k]) > radius for k in kept):
            kept.append(int(c))
        if len(kept) >= limit:
            break
    return kept


def _sample_map(src, tgt, lms, rows, use_hks, engine) -> tuple[torch.Tensor, torch.Tensor]:
    """Images of the source vertices ``rows`` under the map of landmark pairs ``lms``."""
    ps = [a for a, _ in lms]
    qs = [b for _, b in lms]
    Dp = _descriptor(src, ps, use_hks)[rows]
    Dq = _descriptor(tgt, qs, use_hks)
    d, i = nearest_neighbors(Dp, Dq, p=math.inf, engine=engine)
    return i, d


_REFINE_TIMES = slice(1, None, 2)  # every other time sample: half the dimensions, same span
# Precision of the intermediate refinement rounds. The descriptors are centred (the constant
# mode is removed): uncentred, float32 GEMM distances mapped 45 % of a TOSCA shape's vertices
# onto a neighbour when matched against itself; centred, 9 % (float64: none, at 1.6x the
# matching time, with no measurable accuracy gain on 32 TOSCA pairs: 85.2 % vs 84.1 % on the
# 0.08 sqrt(area) proxy, within run-to-run noise).
_REFINE_DTYPE = torch.float32
# The last round (the returned map, and the hypothesis maps the orientation test reads) runs in
# float64, so that a shape matched with itself gives the identity exactly.
_FINAL_DTYPE = torch.float64
# Eigenmodes of the refinement descriptor: the fast tail whose weight at the smallest
# refinement time is below this fraction of the slowest mode's is left out (see
# HeatKernel.spectral_basis); with adaptive times about half of the 100 go (56 kept on TOSCA
# cat0, 49 on SCAPE mesh000), with no change in the maps of 32 TOSCA pairs.
_MODE_TOL = 1e-4
# Searches of at least this many source rows (dense maps) use the exact cluster-pruned search
# (_nn_factors_pruned): 6.6x faster than the brute force on a SCAPE pair, the same map.
_PRUNE_ROWS = 2048


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
        d, i = G.min(dim=1)
        best_d[r0 : r0 + rows] = (d + xx[r0 : r0 + rows]).clamp_min(0)
        best_i[r0 : r0 + rows] = i
    return best_d, best_i


def _nn_factors(X: _Factors, rows: torch.Tensor | None, Y: _Factors,
                memory_bytes: int = 256 * 2**20) -> tuple[torch.Tensor, torch.Tensor]:
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
        Q = Ps @ Y.C.T
    return _blocked_argmin(Q, Pt, X.sqnorms(rows), Y.sqnorms(), memory_bytes)


def _nn_factors_pruned(X: _Factors, rows: torch.Tensor | None, Y: _Factors,
                       centres: torch.Tensor, memory_bytes: int = 256 * 2**20
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_nn_factors` (both factored) with exact cluster pruning, for dense maps.

    The targets are grouped around ``centres`` (target vertices) by nearest centre in
    descriptor space; cluster ``c`` has radius ``r_c``. A query ``x`` at distance ``d_c``
    from centre ``c`` is at least ``d_c - r_c`` from every member (triangle inequality), and
    at most ``b(x) = min_c d_c`` from its nearest neighbour (a centre is a target), so only
    clusters with ``d_c - r_c <= b(x)`` are searched. Same minimum as the brute force (up to
    float64 rounding; ties between clusters go to the first cluster searched). Measured on a
    SCAPE pair with 447 centres: 1.2 % of the ``n m`` pairs are searched, the rest is pruned.
    Cost: ``O((n + m) C k)`` for the centres plus the searched pairs.
    """
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
        dc = (torch.addmm(yy[centres][None, :], q, Pc.T, alpha=-2.0) + xb[:, None]).clamp_min(0)
        dc = dc.sqrt()
        b0, c0 = dc.min(dim=1)
        bd, bi = b0 * b0, centres[c0].clone()
        need = (dc - radius[None, :]) <= (b0 + slack)[:, None]
        for c in torch.nonzero(need.any(dim=0)).flatten().tolist():
            xi = torch.nonzero(need[:, c]).flatten()
            mem = order[starts[c] : ends[c]]
            d2 = torch.addmm(yy[mem][None, :], q[xi], Pt[mem].T, alpha=-2.0) + xb[xi, None]
            dmin, am = d2.min(dim=1)
            better = dmin < bd[xi]
            bd[xi] = torch.where(better, dmin, bd[xi])
            bi[xi] = torch.where(better, mem[am], bi[xi])
        best_d[r0 : r0 + block] = bd.clamp_min(0)
        best_i[r0 : r0 + block] = bi
    return best_d, best_i


def _refine_factors(shape: PreparedShape, landmarks, dtype: torch.dtype,
                    log_floor: float | None = None) -> _Factors:
    """Multi-landmark descriptor of the refinement, ``t_j k_tj(l, x)`` at every other time,
    centred (constant mode removed), in factored spectral form where the eigenbasis serves
    every time (else explicit).

    With ``log_floor`` the heat kernel is taken in log scale, ``log max(k_t, floor)``
    (explicit): by Varadhan's formula ``-4 t log k_t(s, x) -> d(s, x)^2``, so each
    coordinate behaves like a geodesic distance to a landmark instead of vanishing away
    from it.
    """
    hk = shape.hk
    if log_floor is None:
        f = hk.spectral_factors(landmarks, _REFINE_TIMES, dtype=dtype, drop_constant=True,
                                mode_tol=_MODE_TOL)
        if f is not None:
            return _Factors(f[0], f[1])
    D = heat_kernel_map(hk, landmarks, time_index=_REFINE_TIMES, dtype=dtype).to(dtype)
    tj = hk.times[_REFINE_TIMES].to(D.dtype).to(D.device)
    t = tj.repeat(D.shape[1] // tj.numel())  # landmark-major layout: t_j per column
    if log_floor is None:
        # minus the constant mode's term t_j (unit area; the same offset on every shape)
        return _Factors(D - t)
    return _Factors(torch.log((D / t).clamp_min(log_floor)))  # undo the t-scaling first


class _Refiner:
    """Correspondence augmentation (paper Sec. 4) from landmarks ``samples`` on the source.

    Given images ``g`` of the samples on the target, one round maps source vertices by
    nearest neighbour in L2 of the multi-landmark heat kernel map ``samples -> g``. The source
    factors are computed once per match (both precisions); each round builds only the
    target's coefficients (``O(k |samples| J)``) and one factored search.
    """

    def __init__(self, src: PreparedShape, tgt: PreparedShape, samples: torch.Tensor,
                 log_floor: float | None = None) -> None:
        self.src, self.tgt, self.samples, self.log_floor = src, tgt, samples, log_floor
        self._src: dict[torch.dtype, _Factors] = {}

    def source(self, dtype: torch.dtype) -> _Factors:
        if dtype not in self._src:
            self._src[dtype] = _refine_factors(self.src, self.samples, dtype, self.log_floor)
        return self._src[dtype]

    def map(self, g: torch.Tensor, rows: torch.Tensor | None,
            dtype: torch.dtype = _REFINE_DTYPE) -> tuple[torch.Tensor, torch.Tensor]:
        """Images (and squared descriptor distances) of the source ``rows`` (None: all)."""
        Ft = _refine_factors(self.tgt, g, dtype, self.log_floor)
        Fs = self.source(dtype)
        n_rows = self.src.n if rows is None else rows.numel()
        with threads(self.src.hk.num_threads):
            if n_rows >= _PRUNE_ROWS and Fs.C is not None and Ft.C is not None:
                # a dense map: exact search with cluster pruning (~1 % of the pairs)
                m = self.tgt.n
                centres = _fps(self.tgt, min(m, max(16, int(4 * math.sqrt(m)))))
                return _nn_factors_pruned(Fs, rows, Ft, centres)
            return _nn_factors(Fs, rows, Ft)

    def augment(self, g: torch.Tensor, rows: torch.Tensor | None, iterations: int
                ) -> tuple[torch.Tensor, torch.Tensor, float]:
        """``iterations`` rounds from the sample images ``g``: the intermediate ones map the
        samples only (float32), the last one the source ``rows`` (samples first; all vertices
        when None) in float64. Returns the last round's images, the sample images fed to it
        or produced by it, and its mean squared descriptor distance."""
        for _ in range(iterations - 1):
            _, g = self.map(g, self.samples)
        d2, out = self.map(g, rows, _FINAL_DTYPE)
        if rows is not None:
            g = out[: self.samples.numel()]  # the samples are the first rows
        return out, g, float(d2.double().mean())


def _ambiguity(src: PreparedShape, p: int, use_hks: bool, rows: torch.Tensor | None,
               radius: float) -> int | None:
    """Second source landmark if the one-point map of ``p`` is ambiguous, else None.

    The map from ``p`` alone is ambiguous when a self-isometry of the source fixes ``p``
    (e.g. ``p`` on the plane of a mirror-symmetric shape): then most vertices ``x`` have a
    *twin* ``x'``, far from ``x``, whose descriptor is ten times closer to ``x``'s than any
    mesh neighbour's. The twins are found by a 2-NN self-search of the descriptor on 256
    spread samples (the first ``rows``); if more than a quarter of them qualify, the vertex
    farthest from its twin is returned: its image separates the two maps.
    """
    D = _descriptor(src, [p], use_hks).double().cpu().numpy()
    V, _ = src.mesh.numpy()
    r = (_fps(src, 256) if rows is None else rows[:256]).numpy()
    dist, idx = _kdtree(D).query(D[r], k=2, p=np.inf)
    first_is_self = idx[:, 0] == r
    twin = np.where(first_is_self, idx[:, 1], idx[:, 0])
    dtwin = np.where(first_is_self, dist[:, 1], dist[:, 0])
    A = ring_neighbors(src.mesh, 1).tocoo()
    dedge = np.abs(D[A.row] - D[A.col]).max(axis=1)
    dlocal = np.full(src.n, np.inf)
    np.minimum.at(dlocal, A.row, dedge)
    sep = np.linalg.norm(V[r] - V[twin], axis=1)
    qual = (sep > radius) & (dtwin < 0.1 * dlocal[r])
    if qual.mean() <= 0.25:
        return None
    return int(r[np.argmax(np.where(qual, sep, -1.0))])


def _twin_landmark(src: PreparedShape, p: int, use_hks: bool, rows: torch.Tensor | None,
                   diam: float) -> int | None:
    """Second source landmark that separates the direct map of ``p`` from its mirror.

    If ``p`` lies on (or near) the plane of a mirror-symmetric shape, its one-point map cannot
    tell left from right: a vertex ``x`` off the plane and its mirror twin ``x'`` have nearly
    the same descriptor. Among 256 spread samples the one whose nearest descriptor among
    vertices farther than 0.2 diameters is closest is returned (e.g. one paw of a cat whose
    ``p`` is the tail tip, its twin the other paw); its two near-best images give the two
    hypotheses. Detecting whether ``p`` is on the plane is not reliable on real meshes
    (measured: the twin/neighbour descriptor ratios of on-plane and off-plane landmarks
    overlap), so the caller branches on this landmark unconditionally.
    """
    D = _descriptor(src, [p], use_hks).double().cpu().numpy()
    V, _ = src.mesh.numpy()
    r = (_fps(src, 256) if rows is None else rows[:256]).numpy()
    k = min(64, src.n)
    dist, idx = _kdtree(D).query(D[r], k=k, p=np.inf)
    dist, idx = np.atleast_2d(dist), np.atleast_2d(idx)
    far = np.linalg.norm(V[idx] - V[r][:, None], axis=2) > 0.2 * diam
    has = far.any(axis=1)
    if not has.any():
        return None
    dtwin = np.where(has, dist[np.arange(len(r)), np.argmax(far, axis=1)], np.inf)
    return int(r[int(np.argmin(dtwin))])


def _expand(src, tgt, p, q, p2, use_hks, radius, limit=2) -> list[list[tuple[int, int]]]:
    """Landmark hypotheses from ``(p, q)``: ``[(p, q)]`` or, when ``p2`` disambiguates, one
    ``[(p, q), (p2, q2)]`` per distinct near-best image ``q2`` of ``p2``."""
    if p2 is None:
        return [[(p, q)]]
    Dp = _descriptor(src, [p], use_hks)[p2].double().cpu().numpy()
    Dq = _descriptor(tgt, [q], use_hks).double().cpu().numpy()
    k = min(64, tgt.n)
    _, nb = _kdtree(Dq).query(Dp, k=k, p=np.inf)
    W, _ = tgt.mesh.numpy()
    q2s = _distinct(torch.as_tensor(np.atleast_1d(nb)), W, radius, limit)
    return [[(p, q), (p2, int(q2))] for q2 in q2s]


def _landmark_search(src: PreparedShape, tgt: PreparedShape, landmark, use_hks: bool,
                     engine: str, score_rows: torch.Tensor | None, max_features: int,
                     n_candidates: int) -> tuple[int, torch.Tensor, torch.Tensor]:
    """The source landmark ``p`` and every target candidate ranked by ``E(p, q)``.

    ``landmark``: None (the strongest source feature), ``p``, or a known pair ``(p, q)``.
    Candidates are the target's feature points, or, for a ``p`` that is no feature point,
    the 2-ring local minima of the HKS distance to ``p``. Returns ``(p, candidates,
    scores)``, best first.
    """
    if landmark is None:
        p = int(src.features[0])
    elif isinstance(landmark, tuple | list):
        p = int(landmark[0])
    else:
        p = int(landmark)
    if not 0 <= p < src.n:
        raise IndexError(f"source landmark {p} out of range for {src.n} vertices")
    if isinstance(landmark, tuple | list):
        q0 = int(landmark[1])
        if not 0 <= q0 < tgt.n:
            raise IndexError(f"target landmark {q0} out of range for {tgt.n} vertices")
        cands = torch.tensor([q0])
        scores = landmark_scores(src, tgt, p, cands, use_hks=use_hks, engine=engine)
    else:
        pool = tgt.features
        if not bool((src.features == p).any()):
            # a landmark that is no feature point has no feature image: candidates are
            # the 2-ring local minima of the HKS distance to p (its image is one)
            dh = (tgt.hks - src.hks[p].to(tgt.hks.dtype)).abs().amax(dim=1)
            pool = feature_points(tgt.mesh, -dh, rings=2,
                                  max_features=max(int(max_features), 2 * n_candidates))
        scores = landmark_scores(src, tgt, p, pool, use_hks=use_hks, engine=engine,
                                 samples=score_rows)
        order = torch.argsort(scores, stable=True)
        cands, scores = pool[order], scores[order]
    return p, cands, scores


@dataclass(frozen=True)
class _Options:
    """The options of :func:`match` that its default pipeline (:func:`_refine`) reads."""

    n_candidates: int
    refine_samples: int
    refine_iterations: int
    orientation: bool
    score_samples: int | None
    mirror_hypothesis: bool
    mirror_energy_ratio: float | None
    orientation_weight: float
    refine_log_floor: float | None
    expand_top: int
    source_landmarks: int
    extra_candidates: int
    refine_keep: int | None
    orientation_samples: int
    num_threads: int | None
    final_map: bool
    use_hks: bool
    engine: str


def match(
    source: Mesh | PreparedShape,
    target: Mesh | PreparedShape,
    *,
    landmark: int | tuple[int, int] | None = None,
    landmarks: int = 1,
    method: str = "refine",
    times: str | Sequence[float] | None = None,
    use_hks: bool = True,
    engine: str = "auto",
    n_candidates: int = 3,
    refine_samples: int = 48,
    refine_iterations: int = 3,
    orientation: bool = True,
    max_features: int = 50,
    score_samples: int | None = 1000,
    mirror_hypothesis: bool = True,
    mirror_energy_ratio: float | None = None,
    orientation_weight: float = 3.0,
    refine_log_floor: float | None = None,
    expand_top: int = 2,
    source_landmarks: int = 5,
    extra_candidates: int = 20,
    refine_keep: int | None = 8,
    orientation_samples: int = 128,
    num_threads: int | None = None,
    final_map: bool = True,
    background: bool = True,
) -> Correspondence:
    """Dense correspondence between two near-isometric shapes from one point.

    Parameters
    ----------
    source, target : Mesh or PreparedShape
        Shapes M (n vertices) and N (m vertices).
    landmark : int or (int, int), optional
        Source landmark ``p`` (default: the strongest feature point), or a known pair
        ``(p, q)`` which skips the landmark search. Indices of the meshes as given: for a mesh
        loaded with ``largest_component=True``, file vertex ``i`` is mesh vertex
        ``int((mesh.vertex_map == i).nonzero())``.
    landmarks : int
        Number of landmark pairs of the paper's pipeline (1 or more; extra ones are chosen
        greedily among feature pairs, source candidates in farthest-point order).
    method : {"refine", "paper"}
        ``"paper"``: the paper's pipeline: one-point map (+ greedy landmarks); best candidate
        = direct map, next distinct candidate = symmetric map. ``"refine"`` (default): the
        paper's correspondence augmentation applied to many one-point hypotheses.
        ``source_landmarks`` source features (the strongest, then farthest-point order) each
        get their ``n_candidates`` best distinct target candidates (scored by ``E(p, q)``);
        the top ``expand_top`` of each are split in two by a second landmark that separates
        the direct map from its mirror. Every hypothesis is refined (``refine_samples``
        farthest-point landmarks whose images come from the current map, ``refine_iterations``
        rounds; the ``refine_keep`` best after round 1 go on), the mirror partner of the best
        one is added from the target's self-symmetry, and the direct map is the hypothesis
        minimising ``log(energy) - orientation_weight * orientation``; the symmetric map the
        best orientation-reversing one.
    times : "adaptive", "paper" or sequence of float, optional
        Time samples for shapes given as meshes (see :func:`prepare`; default "adaptive").
        The target always uses the source's times.
    use_hks : bool
        Append HKS coordinates to the one-point map (2J coordinates).
    engine : {"auto", "cdist", "kdtree"}
        Nearest-neighbour engine of the L-infinity searches (see :func:`nearest_neighbors`).
    n_candidates : int
        Distinct top candidates considered as hypotheses.
    refine_samples, refine_iterations : int
        Correspondence augmentation settings.
    orientation : bool
        Use the orientation test to choose the direct map (``method="refine"``); without it
        the lowest-energy hypothesis is the direct map.
    max_features : int
        Feature-point cap per shape.
    score_samples : int or None
        Source vertices (farthest-point samples) the landmark score ``E(p, q)`` sums over
        (default 1000; None: all, as in the paper).
    mirror_hypothesis : bool
        (``method="refine"``) Also refine the mirror partner of the best hypothesis, built
        from the target's intrinsic symmetry (computed once per prepared target and cached),
        so that the orientation test chooses between the direct and the symmetric map even
        when only one of them was reached from the landmark candidates.
    mirror_energy_ratio : float or None
        If given, hypotheses (the mirror partner included) compete only if their refined
        energy is at most this multiple of the best one's (default: all compete, ranked by
        ``log(energy) - orientation_weight * orientation``).
    orientation_weight : float
        Weight of the orientation score against the log of the refined energy when choosing
        the direct map (default 3: orientation +0.3 higher outweighs 2.5x the energy).
    expand_top : int
        (``method="refine"``) The top ``expand_top`` distinct candidates are each split into
        two hypotheses by a second source landmark that separates the direct map from its
        mirror (see ``_twin_landmark``); needed when ``p`` lies on the symmetry plane (the
        tail tip of a cat, measured: its one-point map then mixes left and right).
    source_landmarks : int
        (``method="refine"``, automatic landmark) Number of source landmarks whose
        candidates seed hypotheses: the strongest feature, then features farthest from the
        ones already used.
    refine_keep : int or None
        Hypotheses carried past the first refinement round (lowest energy first; None:
        all).
    extra_candidates : int
        Target features scored for each extra source landmark: those of closest HKS.
    orientation_samples : int
        Farthest-point samples whose fat triangles the orientation test reads (``method=
        "refine"``; more triangles average out the local errors of a refined map).
    refine_log_floor : float or None
        Refinement descriptor: None (default) the t-scaled heat kernel map of the samples;
        a float uses ``log max(k_t, floor)`` instead (Varadhan: distance-like coordinates).
    num_threads : int, optional
        torch threads.
    background : bool
        (``method="refine"``) Compute the target's self-symmetry (the mirror hypothesis; once
        per prepared target) in a background thread while the hypotheses are refined, each
        side with half of torch's threads; only when torch may use two or more threads
        (measured: the SCAPE pair's match 2.05 s -> 1.5 s on two cores). The result is the
        same either way.
    final_map : bool
        Build the dense maps (computed on first access of ``.map``); False leaves them None.

    Returns
    -------
    Correspondence
        Maps on the vertices of the meshes as given; for meshes loaded with
        ``largest_component=True``, :meth:`Correspondence.full_map` gives the map in the
        files' vertex numbering (``-1`` for dropped source vertices).

    Raises
    ------
    MeshError
        A mesh too small to match (fewer than ``k = 100`` vertices or no interior vertex,
        see :func:`prepare`).

    Examples
    --------
    >>> import numpy as np, trimesh
    >>> from torchheat import Mesh
    >>> m = trimesh.creation.icosphere(3)
    >>> rng = np.random.default_rng(0)  # random bumps: no exact self-isometry but the identity
    >>> V = m.vertices * [1.0, 0.8, 0.6] * (1 + 0.05 * rng.standard_normal((642, 1)))
    >>> M = Mesh(V, m.faces)
    >>> corr = match(M, M)
    >>> float((corr.map == torch.arange(M.n_vertices)).float().mean())
    1.0
    """
    if method not in ("refine", "paper"):
        raise ValueError(f"unknown method {method!r}; use 'refine' or 'paper'")
    if engine not in ("auto", "cdist", "kdtree"):
        raise ValueError(f"unknown engine {engine!r}; use 'auto', 'cdist' or 'kdtree'")
    if landmarks < 1:
        raise ValueError("landmarks must be >= 1")
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    with threads(num_threads), _Background() as bg:
        kw = {"times": "adaptive" if times is None else times, "max_features": max_features}
        src = _as_prepared(source, **kw)
        tgt = _as_prepared(target, **kw) if target is not source else src
        if not (tgt.hk.times.shape == src.hk.times.shape
                and torch.equal(tgt.hk.times, src.hk.times)):
            tgt.hk.set_times(src.hk.times)  # descriptors must share the time samples
        timings["prepare"] = time.perf_counter() - t_start
        if (background and method == "refine" and mirror_hypothesis and tgt is not src
                and not _self_symmetry_cached(tgt, refine_log_floor)):
            bg.start(_self_symmetry, tgt, use_hks, engine, n_candidates, refine_log_floor)
        Vt, _ = tgt.mesh.numpy()
        diam_s, diam_t = src.mesh.bbox_diagonal(), tgt.mesh.bbox_diagonal()

        # --- landmark search ------------------------------------------------------------
        t0 = time.perf_counter()
        score_rows = None
        if score_samples is not None and score_samples < src.n:
            score_rows = _fps(src, score_samples)
        p, cands, scores = _landmark_search(src, tgt, landmark, use_hks, engine, score_rows,
                                            max_features, n_candidates)
        p2 = _ambiguity(src, p, use_hks, score_rows, 0.05 * diam_s)
        timings["landmark_search"] = time.perf_counter() - t0

        t0 = time.perf_counter()
        sym = None
        orient = float("nan")
        hypotheses = []
        hyp_images: list[torch.Tensor] = []
        samples = None
        if method == "paper":
            hyp = [lm for q in _distinct(cands, Vt, 0.05 * diam_t, 2)
                   for lm in _expand(src, tgt, p, q, p2, use_hks, 0.05 * diam_t)][:2]
            results = []
            for lms in hyp:
                if len(lms) < landmarks:
                    lms = _greedy_landmarks(src, tgt, lms, landmarks, use_hks, engine)
                fmap, dist = dense_map(src, tgt, lms, use_hks=use_hks, engine=engine)
                results.append({"landmarks": lms, "map": fmap,
                                "energy": float((dist.double() ** 2).mean())})
            direct = results[0]
            sym = results[1] if len(results) > 1 else None
            hypotheses = [(r["landmarks"], r["energy"], None) for r in results]
            timings["dense_map"] = time.perf_counter() - t0
        else:
            opts = _Options(n_candidates, refine_samples, refine_iterations, orientation,
                            score_samples, mirror_hypothesis, mirror_energy_ratio,
                            orientation_weight, refine_log_floor, expand_top,
                            source_landmarks, extra_candidates, refine_keep,
                            orientation_samples, num_threads, final_map, use_hks, engine)
            out = _refine(src, tgt, p, cands, p2, landmark is None, score_rows, opts, bg,
                          timings)
            direct, sym, orient = out["direct"], out["sym"], out["orient"]
            hypotheses, hyp_images = out["hypotheses"], out["hyp_images"]
            samples = out["samples"]
    for shape in (src, tgt):  # the memo serves one call; do not hold ~64 MB per shape
        with _DESC_LOCK:
            shape.__dict__.pop("_desc_cache", None)
    timings["total"] = time.perf_counter() - t_start
    return Correspondence(
        **_numbering(src, tgt),
        map=direct["map"],
        landmarks=direct["landmarks"],
        candidates=cands,
        scores=scores,
        symmetric_map=None if sym is None else sym["map"],
        symmetric_landmarks=None if sym is None else sym["landmarks"],
        orientation=orient,
        info={"timings": timings, "method": method, "p": p, "hypotheses": hypotheses,
              "hypothesis_images": hyp_images, "refine_samples": samples,
              "sym_orientation": None if sym is None else sym.get("orientation"),
              "lms0_sym": None if sym is None else sym.get("lms0", sym.get("landmarks"))},
    )


def _refine(src: PreparedShape, tgt: PreparedShape, p: int, cands: torch.Tensor,
            p2: int | None, auto_landmark: bool, score_rows: torch.Tensor | None,
            opt: _Options, bg: _Background, timings: dict) -> dict:
    """The default pipeline after the landmark search (see :func:`match`, ``method="refine"``).

    Seeds one-point hypotheses (``p`` and, for an automatic landmark, further source
    features), refines them by correspondence augmentation, adds the mirror partner of the
    best from the target's self-symmetry and chooses the direct and symmetric maps. Returns
    ``{"direct", "sym", "orient", "hypotheses", "hyp_images", "samples"}``.
    """
    Vs, _ = src.mesh.numpy()
    Vt, _ = tgt.mesh.numpy()
    diam_s, diam_t = src.mesh.bbox_diagonal(), tgt.mesh.bbox_diagonal()
    hypotheses: list = []
    hyp_images: list[torch.Tensor] = []
    t0 = time.perf_counter()
    samples = _fps(src, opt.refine_samples)
    tri = _triangles(Vs, _fps(src, opt.orientation_samples).numpy())
    rows = torch.as_tensor(
        np.unique(np.concatenate([samples.numpy(), *tri])), dtype=torch.int64
    )
    rows = torch.cat([samples, rows[~torch.isin(rows, samples)]])  # samples first
    pos = torch.full((src.n,), -1, dtype=torch.int64)
    pos[rows] = torch.arange(rows.numel())
    if p2 is None and opt.expand_top > 0:
        p2 = _twin_landmark(src, p, opt.use_hks, score_rows, diam_s)
    hyp = [lm for i, q in enumerate(_distinct(cands, Vt, 0.05 * diam_t, opt.n_candidates))
           for lm in _expand(src, tgt, p, q, p2 if i < opt.expand_top else None, opt.use_hks,
                             0.05 * diam_t)]
    if auto_landmark and opt.source_landmarks > 1:
        # more starting points: further source features, each farthest from the ones
        # already used, with their own candidates and twin landmarks
        feats = src.features.numpy()
        used = [p]
        # a quarter of the score samples (a farthest-point prefix: still spread)
        extra_rows = _fps(src, max(100, (opt.score_samples or src.n) // 4))
        for _ in range(min(opt.source_landmarks, feats.size) - 1):
            pe = _farthest_feature(Vs, feats, used)
            used.append(pe)
            # candidates: the target features of most similar HKS (the true image
            # has nearly the same), then the full score E(pe, q) on those
            pool_e = tgt.features
            if pool_e.numel() > opt.extra_candidates:
                dh = (tgt.hks[pool_e] - src.hks[pe].to(tgt.hks.dtype)).abs().amax(1)
                pool_e = pool_e[torch.argsort(dh, stable=True)[:opt.extra_candidates]]
            sc = landmark_scores(src, tgt, pe, pool_e, use_hks=opt.use_hks,
                                 engine=opt.engine, samples=extra_rows)
            ce = pool_e[torch.argsort(sc, stable=True)]
            pe2 = _twin_landmark(src, pe, opt.use_hks, score_rows, diam_s)
            hyp += [lm for i, q in enumerate(_distinct(ce, Vt, 0.05 * diam_t,
                                                       opt.n_candidates))
                    for lm in _expand(src, tgt, pe, q, pe2 if i < opt.expand_top else None,
                                      opt.use_hks, 0.05 * diam_t)]
    refiner = _Refiner(src, tgt, samples, opt.refine_log_floor)
    # round 1 for every hypothesis (samples only), then the `refine_keep` of lowest
    # energy go on: a hypothesis that starts far behind does not converge (measured:
    # the energies of converged and failed hypotheses differ 5-50x)
    stage = []
    for lms0 in hyp:
        g0, _ = _sample_map(src, tgt, lms0, samples, opt.use_hks, opt.engine)
        if opt.refine_iterations > 1:
            d2, g0 = refiner.map(g0, samples)
            e1 = float(d2.double().mean())
        else:
            e1 = 0.0
        stage.append((e1, len(stage), lms0, g0))
    stage.sort(key=lambda s_: (s_[0], s_[1]))
    if tgt is src:
        # a shape against itself: the identity (energy 0) appears once per seed; keep
        # one, so that the pruning does not crowd out the symmetric hypotheses
        ident = [_is_identity({"g": s_[3]}, Vs, 0.05 * diam_s, samples) for s_ in stage]
        first = ident.index(True) if any(ident) else -1
        stage = [s_ for i, s_ in enumerate(stage) if not ident[i] or i == first]
    keep = len(stage) if opt.refine_keep is None else max(1, int(opt.refine_keep))
    results = []
    for e1, _, lms0, g0 in stage[keep:]:
        hypotheses.append((lms0, e1, float("nan")))
        hyp_images.append(g0)
    for _, _, lms0, g0 in stage[:keep]:
        f_rows, g, energy = refiner.augment(g0, rows, max(opt.refine_iterations - 1, 1))
        o = _orientation(src, tgt, tri, lambda i, f=f_rows: f[pos[i]].numpy())
        results.append({"lms0": lms0, "g": g, "energy": energy, "orientation": o})
        hypotheses.append((lms0, energy, o))
        hyp_images.append(g)
    timings["hypotheses"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    by_energy = sorted(results, key=lambda r: r["energy"])
    best = by_energy[0]
    # The best refined hypothesis is a good map, but it may be the mirror one: the
    # true image of a limb-tip landmark and its mirror tip score alike. Its mirror
    # partner sigma_N o f (sigma_N: the target's intrinsic symmetry, at the sample
    # images only) is the other hypothesis; the orientation test tells them apart.
    mirror = None
    if opt.mirror_hypothesis and tgt is not src:
        bg.wait()  # the self-symmetry, if it was computed in the background
        sig = _symmetry_at(tgt, best["g"], opt.use_hks, opt.engine, opt.n_candidates,
                           opt.refine_log_floor)
        if sig is not None:
            f_rows, g2, e2 = refiner.augment(sig, rows, opt.refine_iterations)
            o2 = _orientation(src, tgt, tri, lambda i, f=f_rows: f[pos[i]].numpy())
            mirror = {"lms0": best["lms0"], "g": g2, "energy": e2, "orientation": o2}
            hypotheses.append((["mirror of best"], e2, o2))
            hyp_images.append(g2)
    # The orientation test picks the direct (orientation-preserving) map among the
    # hypotheses, softly: score = log(energy) - orientation_weight * orientation, so
    # that a clearly better-converged hypothesis is not overruled by a noisy
    # orientation reading (refined maps of humans read only +-0.1..0.5). Measured on
    # 32 TOSCA pairs against the hard rule "most preserving among energies within 3x
    # of the best": 70.8 % / 75.1 % vs 66.9 % / 71.3 % (direct / flip-aware, 0.08
    # sqrt(area) Euclidean proxy). Hypotheses above `mirror_energy_ratio` times the
    # reference energy (if given) do not compete.
    pool_r = by_energy + ([mirror] if mirror is not None else [])
    ref = best
    if tgt is src:
        # a shape against itself: the identity is a perfect map of energy ~0, so the
        # energy reference for the other self-maps is the best non-identity one
        others = [r for r in by_energy
                  if not _is_identity(r, Vs, 0.05 * diam_s, samples)]
        if others:
            ref = others[0]
    good = [r for r in pool_r if r is best or opt.mirror_energy_ratio is None
            or r["energy"] <= opt.mirror_energy_ratio * ref["energy"]]
    w = opt.orientation_weight if opt.orientation else 0.0

    def logE(r: dict) -> float:
        return math.log(max(r["energy"], 1e-300))

    direct = min(good, key=lambda r: logE(r) - w * r["orientation"])
    rest = [r for r in good if r is not direct]
    if tgt is src:  # self-maps: the symmetric map is never the identity
        rest = [r for r in rest if not _is_identity(r, Vs, 0.05 * diam_s, samples)]
    if opt.orientation and any(r["orientation"] < 0 for r in rest):
        rest = [r for r in rest if r["orientation"] < 0]
    elif opt.orientation and tgt is not src:
        rest = []
    sym = min(rest, key=lambda r: logE(r) + w * r["orientation"]) if rest else None
    for r in (direct, sym):
        if r is None:
            continue
        # the dense map, computed when first asked for (Correspondence)
        r["map"] = _dense_final(refiner, r["g"], opt.num_threads, timings) \
            if opt.final_map else None
        r["landmarks"] = list(r["lms0"]) + [
            (int(a), int(b)) for a, b in zip(samples.tolist(), r["g"].tolist(),
                                             strict=True)
        ]
    orient = direct["orientation"]
    timings["dense_map"] = time.perf_counter() - t0
    return {"direct": direct, "sym": sym, "orient": orient, "hypotheses": hypotheses,
            "hyp_images": hyp_images, "samples": samples}


def _dense_final(refiner: _Refiner, g: torch.Tensor, num_threads: int | None,
                 timings: dict) -> Callable[[], torch.Tensor]:
    """The refined pipeline's last round over all source vertices, deferred."""

    def compute() -> torch.Tensor:
        t0 = time.perf_counter()
        with threads(num_threads):
            out = refiner.augment(g, None, 1)[0]
        timings["final_map"] = timings.get("final_map", 0.0) + time.perf_counter() - t0
        return out

    return compute


def _is_identity(r: dict, V: np.ndarray, radius: float, samples: torch.Tensor) -> bool:
    """Whether a refined self-map hypothesis is (mostly) the identity: most samples land
    within ``radius`` of themselves (its starting landmarks may not say so)."""
    s = samples.numpy()
    g = r["g"].numpy()
    return bool(np.mean(np.linalg.norm(V[g] - V[s], axis=1) <= radius) > 0.5)


_SELF_SEEDS = 5  # source landmarks of the self-match behind the mirror hypothesis


class _Background:
    """At most one function run in a background thread, torch's threads split meanwhile.

    A context manager, inert until :meth:`start`; :meth:`wait` joins (re-raising the
    function's exception) and gives the calling thread its threads back; leaving the context
    waits too. torch's thread count is per OS thread under OpenMP, so each side sets its own.
    """

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._exc: BaseException | None = None
        self._threads = 0

    def start(self, fn: Callable[..., object], *args: object) -> None:
        nt = torch.get_num_threads()
        if nt < 2 or self._thread is not None:
            return  # nothing to split (e.g. one-thread batch workers): stay sequential
        half = nt // 2
        self._threads = nt

        def run() -> None:
            try:
                torch.set_num_threads(nt - half)
                fn(*args)
            except BaseException as exc:  # re-raised by wait()
                self._exc = exc

        torch.set_num_threads(half)
        self._thread = threading.Thread(target=run, daemon=True, name="torchheat-background")
        self._thread.start()

    def wait(self) -> None:
        if self._thread is None:
            return
        self._thread.join()
        self._thread = None
        torch.set_num_threads(self._threads)
        if self._exc is not None:
            exc, self._exc = self._exc, None
            raise exc

    def __enter__(self) -> _Background:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.wait()
            return
        with contextlib.suppress(BaseException):  # the exception in flight wins
            self.wait()


def _sym_key(shape: PreparedShape, log_floor: float | None) -> tuple:
    own = shape.hk.times if shape.own_times is None else shape.own_times
    return (tuple(own.tolist()), log_floor)


def _self_symmetry_cached(shape: PreparedShape, log_floor: float | None) -> bool:
    return _sym_key(shape, log_floor) in shape.__dict__.get("_sym_cache", {})


def _self_symmetry(shape: PreparedShape, use_hks: bool, engine: str, n_candidates: int,
                   log_floor: float | None = None) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The shape's intrinsic (orientation-reversing) self-symmetry on farthest-point samples.

    Returns ``(samples, images)`` or None when no orientation-reversing self-map is found.
    Computed at the shape's own times (``own_times``: those it was prepared with, not the
    ones of the source it is being matched to), so it is computed once per prepared target
    and reused for every source; cached on the PreparedShape.
    """
    own = shape.hk.times if shape.own_times is None else shape.own_times
    key = _sym_key(shape, log_floor)
    cache = shape.__dict__.setdefault("_sym_cache", {})
    if key in cache:
        return cache[key]
    view = shape
    if not (own.shape == shape.hk.times.shape and torch.equal(own, shape.hk.times)):
        view = dataclasses.replace(shape, hk=copy.copy(shape.hk))  # own solver, own times
        view.hk.set_times(own)
        if "_fps_cache" in shape.__dict__:
            view.__dict__["_fps_cache"] = shape.__dict__["_fps_cache"]
    corr = match(view, view, use_hks=use_hks, engine=engine, n_candidates=n_candidates,
                 mirror_hypothesis=False, final_map=False, refine_log_floor=log_floor,
                 source_landmarks=_SELF_SEEDS)
    out = None
    if corr.symmetric_landmarks is not None and corr.info.get("sym_orientation", 0) < 0:
        lm = corr.symmetric_landmarks[len(corr.info["lms0_sym"]):]
        out = (torch.tensor([a for a, _ in lm]), torch.tensor([b for _, b in lm]))
    cache[key] = out
    return out


def _symmetry_at(shape, vertices, use_hks, engine, n_candidates, log_floor=None
                 ) -> torch.Tensor | None:
    """Images of ``vertices`` under the shape's intrinsic symmetry (None if none found)."""
    sym = _self_symmetry(shape, use_hks, engine, n_candidates, log_floor)
    if sym is None:
        return None
    S, G = sym
    return _Refiner(shape, shape, S, log_floor).map(G, torch.as_tensor(vertices))[1]


def _farthest_feature(V: np.ndarray, feats: np.ndarray, used: Sequence[int]) -> int:
    """The feature point farthest (Euclidean) from every vertex in ``used``."""
    d = np.min(np.linalg.norm(V[feats][:, None] - V[list(used)][None], axis=2), axis=1)
    return int(feats[int(np.argmax(d))])


def _greedy_landmarks(src, tgt, lms, total, use_hks, engine):
    """Paper Sec. 4: add (p_i, q_i) among feature pairs minimising the combined error.

    Source candidates are taken in farthest-point order from the existing landmarks (the top
    HKS maxima cluster, e.g. fingertips of one hand)."""
    lms = list(lms)
    V, _ = src.mesh.numpy()
    feats = src.features.numpy()
    while len(lms) < total:
        used = [a for a, _ in lms]
        p2 = _farthest_feature(V, feats, used)
        sc = landmark_scores(src, tgt, [*used, p2], tgt.features, q_fixed=[b for _, b in lms],
                             use_hks=use_hks, engine=engine)
        lms.append((p2, int(tgt.features[int(torch.argmin(sc))])))
    return lms


def symmetry(
    mesh: Mesh | PreparedShape, **options
) -> Correspondence:
    """Intrinsic symmetry of a shape: the best orientation-reversing self-map.

    The shape is matched against itself (:func:`match`); the identity is excluded by the
    orientation test, so ``.map`` is the symmetry (and ``.symmetric_map`` the direct
    self-map, near the identity).

    Parameters
    ----------
    mesh : Mesh or PreparedShape
    **options
        Passed to :func:`match`.

    Returns
    -------
    Correspondence
        A self-map; :meth:`Correspondence.full_map` gives it in the file's numbering for a
        mesh loaded with ``largest_component=True``.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> m = trimesh.creation.icosphere(3)
    >>> V = m.vertices * [1.0, 0.8, 0.6]  # mirror-symmetric ellipsoid
    >>> symmetry(Mesh(V, m.faces)).map.shape
    torch.Size([642])
    """
    t = options.get("times")
    shape = _as_prepared(mesh, times="adaptive" if t is None else t,
                         max_features=options.get("max_features", 50))
    options.setdefault("n_candidates", 8)
    corr = match(shape, shape, **options)
    if not corr.has_symmetric_map:
        return corr
    o = corr.info.get("sym_orientation")  # None with method="paper" (not tested)
    return Correspondence(
        map=corr._symmetric_map,  # still lazy: only the map asked for is computed
        landmarks=corr.symmetric_landmarks,
        candidates=corr.candidates,
        scores=corr.scores,
        symmetric_map=corr._map,
        symmetric_landmarks=corr.landmarks,
        orientation=float("nan") if o is None else float(o),
        info=corr.info,
        **_numbering(shape, shape),
    )

