"""Partial shapes: a piece ``M`` of a surface matched into the whole ``N`` (the paper's third
application, Ovsjanikov et al. 2010, Sec. 5.3 and Figs. 1, 9).

What changes against a full match (see :func:`torchheat.match` with ``partial=True``):

* **One scale.** Both shapes are in the same units; the heat-kernel operators are normalised to
  unit area per shape, so the piece, whose true area is ``r = area(M) / area(N)`` of the whole,
  would be blown up. Its time samples are therefore those of the whole divided by ``r``: the
  t-scaled kernel ``t k_t`` is invariant under a change of scale (``k`` is an inverse area), so
  ``t' k'_{t'}`` of the unit-area piece at ``t' = t / r`` equals ``t k_t`` of the piece at the
  whole's scale, and the descriptors of both shapes mean the same thing.
* **Times from the piece.** The adaptive times come from the piece's own spectrum (in the
  whole's units): the largest is ``4 ln 10 / lambda_1(M)``, the time at which heat has spread
  over the piece, smaller for a small piece — heat must not feel the cut.
* **The boundary, measured.** Every vertex gets its geodesic (edge-graph) distance to the
  boundary, in units of ``sqrt(area(N))``. Landmarks, the samples of the landmark score, of the
  refinement and of ZoomOut are taken among the vertices at least ``margin`` from the cut,
  where the heat kernel of the piece is close to that of the whole (Neumann and Dirichlet
  conditions both change it only near the boundary). Every vertex still gets an image.
* **A landmark-free map** (:func:`partial_descriptor_map`): one-point maps with small times
  are precise where right but often wrong as a whole; a partial functional map of wave kernel
  signatures (both shapes at the whole's scale, orientation term) is coarse but needs no
  landmark. The pipeline refines it by :func:`partial_zoomout`, seeds one-point hypotheses
  from its images of the deepest features, and scores every hypothesis by its agreement with
  it (:mod:`.pipeline`, ``descriptor_seed``).
* **Rectangular functional maps.** A piece's ``j``-th eigenvalue is about that of the whole's
  ``j / r``-th (Weyl's law), so ZoomOut grows ``ceil(r k)`` modes of the piece against ``k``
  of the whole (Rodolà et al. 2017, Melzi et al. 2019, Sec. 6). The functional map pulls the
  whole's functions back onto the piece, ``Phi_M C ~ Phi_N[T]`` (``C`` is ``k_M x k_N``: the
  restriction of a function of N is always defined on M, the converse is not), and the point
  map is ``T(x) = argmin_y |Phi_M[x] C - Phi_N[y]|``.

This module is the piece-scale way; :mod:`.partial_scale` adds the other (the piece with its
holes filled, matched as a whole shape) and chooses between the two.

Direction: the partial shape must be the source. A full shape matched *into* a piece
(``match(full, part)``) is a full match whose map sends the missing region to wherever its
descriptors are closest — meaningless there; this module is for ``part -> full``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.csgraph import dijkstra
from scipy.spatial import cKDTree

from ..descriptors import farthest_point_sampling
from ..heat import threads
from ..mesh import Mesh, MeshError
from .fmap import (
    _coefficients,
    _resolvent_mask,
    _solve_quadratic,
    descriptor_operators,
    wave_kernel_signature,
)
from .nn import _blocked_argmin, _Factors, _nn_factors, _nn_factors_pruned
from .prepared import PreparedShape, ShapeCaches, _cluster_centres, _fps, _role_copy
from .refine import _agree, _refine_factors
from .zoomout import ZoomOutResult, _sizes, lstsq

__all__ = [
    "PARTIAL_MARGIN",
    "area_ratio",
    "boundary_distance",
    "partial_descriptor_images",
    "partial_descriptor_map",
    "partial_functional_map",
    "partial_zoomout",
    "shared_band",
]

#: Default distance from the boundary (in units of sqrt(area of the full shape)) inside which
#: vertices are not used as landmarks or samples.
PARTIAL_MARGIN = 0.02
#: Fewest vertices a partial shape must keep beyond the margin.
_MIN_INTERIOR = 50
#: Interior farthest-point samples prepared for a piece (every sample request is a prefix).
_INTERIOR_SAMPLES = 2048
#: Area ratio below which a piece without enough interior is said to be perhaps in other units
#: than its whole (a millimetre piece of a metre whole: 1e-6).
_UNITS_HINT_RATIO = 1e-3
#: Area ratio above which the "partial" source is taken to be as large as the target.
_RATIO_MAX = 1.1


def area_ratio(part: Mesh, full: Mesh) -> float:
    """Area of the partial shape over the area of the full one, in the meshes' own units.

    Parameters
    ----------
    part, full : Mesh
        In the same units (the pieces of a benchmark are cut from the full shape).

    Returns
    -------
    float
        ``area(part) / area(full)``; clipped to at most 1.

    Raises
    ------
    MeshError
        The piece is more than 10 % larger than the whole: the shapes are not in the same
        units, or the arguments are swapped (the partial shape is the source).

    Examples
    --------
    >>> import trimesh
    >>> m = trimesh.creation.icosphere(2)
    >>> M = Mesh(m.vertices, m.faces)
    >>> area_ratio(M, M)
    1.0
    """
    r = part.area() / full.area()
    if not math.isfinite(r) or r <= 0:
        raise MeshError(f"{part.name or 'source'}: zero or invalid area")
    if r > _RATIO_MAX:
        raise MeshError(
            f"{part.name or 'source'}: partial shape {r:.2f} times the area of "
            f"{full.name or 'the target'}: with partial=True the source must be the piece and "
            "the target the whole, in the same units (swap the shapes or rescale one)")
    return min(r, 1.0)


def boundary_distance(mesh: Mesh, scale: float = 1.0) -> np.ndarray:
    """Geodesic distance of every vertex to the mesh boundary, along edges (Dijkstra).

    Parameters
    ----------
    mesh : Mesh
        n vertices.
    scale : float
        Unit of the result: distances are divided by it (e.g. ``sqrt(area)`` of the full
        shape).

    Returns
    -------
    numpy.ndarray, float64, shape (n,)
        0 on the boundary; ``inf`` everywhere for a closed mesh. Edge paths overestimate the
        surface distance by a few percent on regular meshes.

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0]])
    >>> F = np.array([[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]])
    >>> boundary_distance(Mesh(V, F)).tolist()  # every vertex of a strip is on its boundary
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
    """
    n = mesh.n_vertices
    bnd = mesh.boundary_vertices().numpy()
    if not bnd.any():
        return np.full(n, np.inf)
    V, _ = mesh.numpy()
    E = mesh.edges().numpy()
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1) / float(scale)
    G = sp.coo_matrix((w, (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    d = dijkstra(G, directed=False, indices=np.flatnonzero(bnd), min_only=True)
    return np.asarray(d, dtype=np.float64)


def _boundary_distance(shape: PreparedShape, scale: float) -> np.ndarray:
    """:func:`boundary_distance` of a prepared shape's mesh, computed once per ``scale``
    (kept in its caches, shared by its role copies); read-only."""
    cache = shape.caches.boundary_distance
    key = float(scale)
    if key not in cache:
        dist = boundary_distance(shape.mesh, key)
        dist.setflags(write=False)
        cache[key] = dist
    return cache[key]


@dataclass(frozen=True)
class _PartialSetup:
    """What a partial match knows about its source: the area ratio and the usable vertices."""

    ratio: float
    interior: np.ndarray  # bool (n,): vertices at least `margin` from the boundary
    dist: np.ndarray  # (n,) distance to the boundary, units of sqrt(area(N))
    margin: float


def _setup(src: PreparedShape, tgt: PreparedShape, margin: float) -> _PartialSetup:
    """Area ratio and interior of the source; refuses a piece without enough interior."""
    r = area_ratio(src.mesh, tgt.mesh)
    dist = _boundary_distance(src, math.sqrt(tgt.mesh.area()))
    interior = dist >= margin
    n_in = int(interior.sum())
    if n_in < _MIN_INTERIOR:
        label = src.mesh.name or "source"
        units = ""
        if r < _UNITS_HINT_RATIO:  # a piece in other units than its whole looks tiny
            units = (f"; the piece covers only {r:.2g} of the whole's area: if it is stored in "
                     "other units than the whole (e.g. metres against millimetres), rescale "
                     "it, both must be in the same units")
        raise MeshError(
            f"{label}: only {n_in} vertices lie at least {margin:g} sqrt(area) from the "
            f"boundary (largest distance {float(np.max(dist)):.3f}), too little interior to "
            f"match a partial shape (at least {_MIN_INTERIOR}); lower the margin "
            f"(partial_margin=..., --partial-margin) or use a larger piece{units}")
    return _PartialSetup(r, interior, dist, margin)


#: Largest time of a partial match: heat from a point this deep inside (the 90th percentile of
#: the distances to the boundary) keeps exp(-d^2 / 4t) <= exp(-4) of its mass off the cut...
_TIME_DEPTH_QUANTILE = 0.9
_TIME_DEPTH_FACTOR = 16.0
#: ...but never below this (the whole's units: heat spread over a disc of radius ~0.2
#: sqrt(area)); below it a one-point map describes only the landmark's neighbourhood, and
#: small holes, which put every vertex near a boundary, perturb the kernel far less than a
#: cut at the same distance (measured on SHREC'16 holes with ground-truth landmarks: the
#: refinement's error is lowest for t_max between 0.003 and 0.03).
_TIME_FLOOR = 0.01


def partial_times(src: PreparedShape, setup: _PartialSetup, n_times: int | None = None
                  ) -> torch.Tensor:
    """Time samples of a partial source, in the whole's units (``t``; the unit-area piece
    uses ``t / r``).

    ``t_max = max(d^2 / 16, 0.01)`` with ``d`` the 90th percentile of the distances to the
    boundary (heat released that deep reaches the cut only at ``exp(-d^2/4t) = e^-4`` of its
    peak), capped by the piece's own adaptive largest time; ``t_min`` the piece's adaptive
    smallest time (the resolution of its eigenbasis), at most ``t_max / 3``. Log-spaced, as many
    as the source's current times. A closed source keeps its own adaptive times.
    """
    own = src.hk.times.double() * setup.ratio
    J = int(n_times or own.numel())
    finite = setup.dist[np.isfinite(setup.dist)]
    t_hi = float(own.max())
    if finite.size:
        d = float(np.quantile(finite, _TIME_DEPTH_QUANTILE))
        t_hi = min(t_hi, max(d * d / _TIME_DEPTH_FACTOR, _TIME_FLOOR))
    t_lo = min(float(own.min()), t_hi / 3.0)
    return torch.logspace(math.log10(t_lo), math.log10(t_hi), J, dtype=torch.float64)


def _interior_view(src: PreparedShape, setup: _PartialSetup, order: str = "deepest",
                   times: torch.Tensor | None = None) -> PreparedShape:
    """A copy of the source whose feature points and farthest-point samples are interior.

    The pipeline draws every landmark and sample from ``shape.features`` and :func:`_fps`;
    pre-filling the copy's sample cache with an interior farthest-point order makes all of
    them avoid the cut (the copy's heat kernel shares the eigenbasis, at ``times`` if given;
    the caller's shape is untouched).
    """
    # own times, shared eigenbasis; its own caches (its samples are the interior's only)
    view = dataclasses.replace(_role_copy(src, times), caches=ShapeCaches())
    feats = src.features.numpy()
    keep = feats[setup.interior[feats]]
    if order == "deepest":
        # the first landmark's one-point map is the most reliable where the cut is farthest
        keep = keep[np.argsort(-setup.dist[keep], kind="stable")]
    elif order != "strongest":
        raise ValueError(f"unknown partial landmark order {order!r}; use 'deepest' or "
                         "'strongest'")
    if keep.size == 0:  # no feature point beyond the margin: start from the deepest vertex
        keep = np.array([int(np.argmax(np.where(np.isfinite(setup.dist), setup.dist, 0.0)))])
    view.features = torch.as_tensor(keep, dtype=torch.int64)
    inner = np.flatnonzero(setup.interior)
    V, _ = src.mesh.numpy()
    picked = farthest_point_sampling(V[inner], min(inner.size, _INTERIOR_SAMPLES))
    view.caches.fps = torch.as_tensor(inner[picked.numpy()], dtype=torch.int64)
    return view


#: Landmark counts of the growing rounds of a partial hypothesis (nearest samples to its
#: source landmark first); the last round uses all samples.
_GROW_COUNTS = (6, 12, 24)
#: Target farthest-point samples the growing rounds map to (the later rounds: every vertex).
_GROW_TARGETS = 2000


def _geodesic_order(mesh: Mesh, sources: list[int], vertices: torch.Tensor) -> torch.Tensor:
    """``vertices`` sorted by edge-path distance from the nearest of ``sources``."""
    V, _ = mesh.numpy()
    E = mesh.edges().numpy()
    n = mesh.n_vertices
    w = np.linalg.norm(V[E[:, 0]] - V[E[:, 1]], axis=1)
    G = sp.coo_matrix((w, (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    d = dijkstra(G, directed=False, indices=np.asarray(sources, dtype=np.int64), min_only=True)
    v = vertices.numpy()
    return torch.as_tensor(v[np.argsort(d[v], kind="stable")], dtype=torch.int64)


def grow_hypothesis(src: PreparedShape, tgt: PreparedShape, p: list[int], samples: torch.Tensor,
                    images: torch.Tensor, make_refiner) -> torch.Tensor:
    """Images of ``samples`` grown outwards from the landmarks ``p`` of a hypothesis.

    On a piece only small times are usable, so a one-point map is right near its landmarks
    ``p`` (the first and the one that splits it from its mirror) and arbitrary far from them.
    The samples nearest to them (:data:`_GROW_COUNTS`) become landmarks
    with their current images and map every sample; the next, larger ring does the same with
    the images just found — the paper's correspondence augmentation, spreading from where the
    map is known instead of trusting all samples at once.

    ``make_refiner(landmarks)`` returns a :class:`~torchheat.matching.refine._Refiner` of the
    piece and the whole with those source landmarks.
    """
    order = _geodesic_order(src.mesh, p, samples)
    pos = torch.full((src.n,), -1, dtype=torch.int64)
    pos[samples] = torch.arange(samples.numel())
    targets = _fps(tgt, _GROW_TARGETS)
    g = images.clone()
    for c in _GROW_COUNTS:
        if c >= samples.numel():
            break
        lm = order[:c]
        ref = make_refiner(lm)
        Fs = ref.source(torch.float32)
        Ft = _refine_factors(tgt, g[pos[lm]], torch.float32, ref.log_floor, ref.centre)
        Ft = _Factors(Ft.P[targets], Ft.C)
        with threads(src.hk.num_threads):
            g = targets[_nn_factors(Fs, samples, Ft)[1]]
    return g


# ------------------------------------------------------------------------------------------
# rectangular functional maps
# ------------------------------------------------------------------------------------------
def _k_source(k: int, ratio: float, limit: int) -> int:
    return int(max(1, min(limit, math.ceil(ratio * k))))


def partial_functional_map(phi_s: torch.Tensor, phi_t: torch.Tensor, rows: torch.Tensor,
                           images: torch.Tensor, k_s: int, k_t: int,
                           weights: torch.Tensor | None = None) -> torch.Tensor:
    """The ``k_s x k_t`` functional map pulling the target's functions back onto a piece.

    Least squares ``min_C |W^1/2 (Phi_M[rows, :k_s] C - Phi_N[images, :k_t])|_F``.

    The system is rectangular: the whole's modes past the piece's ``k_s`` are fitted by the
    piece's ``k_s`` modes, and how they are fitted depends on how the rows are weighted. The
    bases are orthonormal in the area inner product, so rows weighted by the area they stand
    for (``weights``, see :func:`sample_areas`) read the right map's ``C`` as the area
    projection; unweighted rows read it only where they cover the surface uniformly (a
    capsule of 578 vertices whose masses span 122x, all vertices as rows: the identity read
    ``|C C^T - I| / sqrt(k_s)`` 0.69 unweighted, 0.00 weighted).

    Parameters
    ----------
    phi_s : torch.Tensor, shape (n, K_s)
        Eigenbasis of the piece.
    phi_t : torch.Tensor, shape (m, K_t)
        Eigenbasis of the whole.
    rows, images : torch.Tensor, int64, shape (s,)
        Source samples and their target vertices; ``s >= k_s``.
    k_s, k_t : int
    weights : torch.Tensor, shape (s,), optional
        Positive weight of each row (default: all equal).

    Returns
    -------
    torch.Tensor, shape (k_s, k_t)

    Examples
    --------
    >>> phi = torch.linalg.qr(torch.randn(60, 8, dtype=torch.float64))[0]
    >>> partial_functional_map(phi, phi, torch.arange(60), torch.arange(60), 4, 8).shape
    torch.Size([4, 8])
    """
    A, B = phi_s[rows, :k_s], phi_t[images, :k_t]
    if weights is not None:
        w = weights.to(A.dtype).sqrt()[:, None]
        A, B = A * w, B * w.to(B.dtype)
    return lstsq(A, B)


def sample_areas(shape: PreparedShape, rows: torch.Tensor) -> torch.Tensor:
    """The area each sample stands for: the lumped masses of the vertices nearest to it
    (Euclidean Voronoi cells of the samples among the vertices).

    Every vertex as a row gives the lumped masses themselves.

    Parameters
    ----------
    shape : PreparedShape
        n vertices.
    rows : torch.Tensor, int64, shape (s,)
        Distinct vertices.

    Returns
    -------
    torch.Tensor, float64, shape (s,)
        Sums to the shape's area at its eigenbasis' scale (the masses ``vertex_mass``).

    Examples
    --------
    >>> import trimesh, torchheat
    >>> m = trimesh.creation.icosphere(2)
    >>> s = torchheat.prepare(torchheat.Mesh(m.vertices, m.faces), k=20)
    >>> a = sample_areas(s, torch.arange(10))
    >>> bool(torch.isclose(a.sum(), s.hk.vertex_mass.double().sum()))
    True
    """
    mass = shape.hk.vertex_mass.double().cpu()
    rows = torch.as_tensor(rows, dtype=torch.int64).cpu()
    if rows.numel() == shape.n:
        return mass[rows]
    V, _ = shape.mesh.numpy()
    owner = cKDTree(V[rows.numpy()]).query(V)[1]
    return torch.from_numpy(np.bincount(owner, weights=mass.numpy(), minlength=rows.numel()))


def _pull_map(Ps: torch.Tensor, Pt_sub: torch.Tensor, C: torch.Tensor, rows: torch.Tensor
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """``argmin_y |Phi_M[x, :k_s] C - Phi_N[y, :k_t]|`` for the rows (brute force, blocked)."""
    k_s, k_t = C.shape
    X = Ps[rows, :k_s] @ C.to(Ps.dtype)
    Y = Pt_sub[:, :k_t]
    return _blocked_argmin(X, Y, (X * X).sum(1), (Y * Y).sum(1), 256 * 2**20)


def partial_zoomout(phi_s: torch.Tensor, phi_t: torch.Tensor, seed_rows: torch.Tensor,
                    seed_images: torch.Tensor, rows: torch.Tensor, ratio: float, *,
                    k_start: int = 16, k_end: int = 100, step: int = 8,
                    targets: torch.Tensor | None = None) -> ZoomOutResult:
    """ZoomOut of a piece into a whole: ``k`` modes of the whole against ``ceil(ratio k)`` of
    the piece at every step (see the module docstring).

    Parameters
    ----------
    phi_s, phi_t : torch.Tensor, shapes (n, K_s), (m, K_t)
        Eigenbases of the piece and of the whole (mass-orthonormal, ascending).
    seed_rows, seed_images : torch.Tensor, int64, shape (s0,)
        The starting map on a few source samples.
    rows : torch.Tensor, int64, shape (s,)
        Source samples the map is refined on.
    ratio : float
        ``area(piece) / area(whole)`` in (0, 1].
    k_start, k_end, step : int
        Sizes on the whole's side.
    targets : torch.Tensor, int64, optional
        Target vertices the samples may map to (default all).

    Returns
    -------
    ZoomOutResult
        ``C`` is ``k_s x k_end``; ``residual`` the mean squared spectral distance of the
        samples divided by ``k_end``.

    Notes
    -----
    Cost as :func:`~torchheat.matching.zoomout.zoomout`: per step a least-squares solve of
    ``s x k_s`` and a brute-force search of ``s`` queries among the targets in ``k``
    dimensions.

    Examples
    --------
    >>> phi = torch.linalg.qr(torch.randn(300, 30, dtype=torch.float64))[0]
    >>> perm = torch.randperm(300)
    >>> r = partial_zoomout(phi[perm], phi, torch.arange(40), perm[:40], torch.arange(300),
    ...                     1.0, k_start=8, k_end=30, step=4)
    >>> bool((r.images == perm).all()), tuple(r.C.shape)
    (True, (30, 30))
    """
    k_end = int(min(k_end, phi_t.shape[1]))
    Ks = min(phi_s.shape[1], rows.numel())
    k_start = int(max(1, min(k_start, k_end)))
    Ps, Pt = phi_s.to(torch.float32), phi_t.to(torch.float32)
    tmap = torch.arange(phi_t.shape[0]) if targets is None else targets
    Pt_sub = Pt if targets is None else Pt[targets]
    ks = min(_k_source(k_start, ratio, Ks), seed_rows.numel())
    C = partial_functional_map(Ps, Pt, seed_rows, seed_images, ks, k_start)
    d2, j = _pull_map(Ps, Pt_sub, C, rows)
    images = tmap[j]
    for k in _sizes(k_start, k_end, step)[1:]:
        C = partial_functional_map(Ps, Pt, rows, images, _k_source(k, ratio, Ks), k)
        d2, j = _pull_map(Ps, Pt_sub, C, rows)
        images = tmap[j]
    C = partial_functional_map(phi_s, phi_t, rows, images, _k_source(k_end, ratio, Ks), k_end)
    return ZoomOutResult(rows, images, C, float(d2.double().mean()) / k_end)


#: Whole-shape modes of the descriptor functional map of a piece (more lost right maps on the
#: SHREC'16 cuts: 24 modes 0.63, 30 0.59, 40 0.62, 60 0.38 of the samples right on 10 pairs)
PARTIAL_DESCR_K = 24
#: Distance from the boundary (units of sqrt(area(N))) over which the descriptor term's
#: weight rises from 0 to 1: the WKS of a piece differs from the whole's near the cut.
PARTIAL_DESCR_RAMP = 0.05


def partial_descriptor_map(src: PreparedShape, tgt: PreparedShape, ratio: float,
                           k: int = PARTIAL_DESCR_K, n_descr: int = 50,
                           weights: tuple[float, float, float, float] = (1.0, 0.1, 1.0, 1.0),
                           ramp: float = PARTIAL_DESCR_RAMP,
                           dist: np.ndarray | None = None) -> torch.Tensor:
    """A landmark-free rectangular functional map of a piece into the whole (a partial
    functional map with the region fixed by the area ratio, after Rodolà et al. 2017).

    The energy of :func:`~torchheat.matching.fmap.descriptor_functional_map` (wave kernel
    signatures preserved, commutativity with the Laplacians, with the descriptor products and
    with the orientation operators), on both shapes at the whole's scale: the piece's
    eigenvalues are ``lambda / r``, its basis ``phi / sqrt(r)``, its masses ``r A``. What
    changes for a piece:

    * one WKS filter bank for both, over the energies both spectra cover, without the
      per-energy normalisation (the local density of states agrees on a piece and its whole;
      each descriptor is scaled by its norm on the whole, the same number on both shapes);
    * ``ceil(r k)`` modes of the piece against ``k`` of the whole (Weyl's law: the piece's
      ``j``-th eigenvalue is near the whole's ``j / r``-th), at least 8; the resolvent mask
      on the common-unit spectra then favours the slanted diagonal by itself;
    * the descriptor term is weighed in space by ``min(1, dist / ramp)`` (``dist``: distance
      to the boundary), where the piece's WKS is that of the whole.

    Parameters
    ----------
    src, tgt : PreparedShape
        The piece and the whole (same units), with at least ``k`` eigenpairs each.
    ratio : float
        ``area(src) / area(tgt)`` in (0, 1].
    k : int
        Modes of the whole.
    n_descr : int
        WKS energies.
    weights : (w_descr, w_lap, w_dcomm, w_orient)
    ramp : float
        Distance over which the descriptor weight rises (units of ``sqrt(area(tgt))``).
    dist : numpy.ndarray, shape (n,), optional
        Distances of the piece's vertices to its boundary (:func:`boundary_distance` with
        ``scale = sqrt(area(tgt))``), computed if not given.

    Returns
    -------
    torch.Tensor, float64, shape (k_s, k)
        ``C`` with ``Phi_M C ~ Phi_N[T]`` in the piece's unit-area basis (as
        :func:`partial_zoomout` and :func:`dense_partial_map` use it).

    Raises
    ------
    ValueError
        The two spectra share no band (:func:`shared_band` is None): a piece too small for
        its eigenpairs, or a wrong area ratio.

    Notes
    -----
    Accuracy: coarse, a seed (on the SHREC'16 cuts its samples land within 0.25 sqrt(area)
    of the truth 60-80 % of the time where it works). Cost: the WKS and operators of both
    shapes, ``O(p F k^2)``, and the ``k_s k x k_s k`` normal equations: 0.3-0.6 s for a 10k
    whole, one thread.

    Examples
    --------
    >>> import trimesh, torchheat
    >>> m = trimesh.creation.icosphere(3)
    >>> s = torchheat.prepare(torchheat.Mesh(m.vertices, m.faces), k=40)
    >>> tuple(partial_descriptor_map(s, s, 1.0, k=10).shape)
    (10, 10)
    """
    terms = _partial_terms(src, tgt, float(ratio), k, n_descr, weights, ramp, dist)
    C = _solve_quadratic(*terms)
    return torch.from_numpy(C / math.sqrt(float(ratio)))


def _band(lam_s: np.ndarray, lam_t: np.ndarray) -> tuple[float, float] | None:
    """Log-eigenvalue range both spectra cover (with room for the WKS filters), or None."""
    pos_s, pos_t = lam_s[lam_s > 1e-8 * lam_s.max()], lam_t[lam_t > 1e-8 * lam_t.max()]
    if pos_s.size == 0 or pos_t.size == 0:
        return None
    lo = math.log(max(pos_s.min(), pos_t.min()))
    hi = math.log(min(pos_s.max(), pos_t.max()))
    return (lo, hi) if hi > lo else None


def shared_band(src: PreparedShape, tgt: PreparedShape, ratio: float
                ) -> tuple[float, float] | None:
    """The log-eigenvalue band a piece and its whole both cover at the whole's scale (the
    WKS energies of :func:`partial_descriptor_map`), or None: the piece's first eigenvalue
    (``lambda_1 / r``) lies beyond the whole's last computed one.

    Parameters
    ----------
    src, tgt : PreparedShape
        The piece and the whole.
    ratio : float
        ``area(src) / area(tgt)``.

    Returns
    -------
    (float, float) or None
        ``(log lambda_lo, log lambda_hi)``.

    Examples
    --------
    >>> import trimesh, torchheat
    >>> m = trimesh.creation.icosphere(2)
    >>> s = torchheat.prepare(torchheat.Mesh(m.vertices, m.faces), k=20)
    >>> shared_band(s, s, 1.0) is not None, shared_band(s, s, 1e-6)
    (True, None)
    """
    return _band(src.hk.eigenvalues.double().numpy() / float(ratio),
                 tgt.hk.eigenvalues.double().numpy())


def _partial_terms(src: PreparedShape, tgt: PreparedShape, r: float, k: int, n_descr: int,
                   weights: tuple[float, float, float, float], ramp: float,
                   dist: np.ndarray | None) -> tuple:
    """The energy of :func:`partial_descriptor_map` at the whole's scale, as the arguments of
    :func:`~torchheat.matching.fmap._solve_quadratic` (``coef, A, B, mask, (D_M, D_N),
    (O_M, O_N), gram``); its minimiser is ``sqrt(r)`` times the returned map."""
    scale = math.sqrt(tgt.mesh.area())
    lam_t = tgt.hk.eigenvalues.double().numpy()
    lam_s = src.hk.eigenvalues.double().numpy() / r
    phi_t = tgt.hk.eigenvectors.double()
    phi_s = src.hk.eigenvectors.double() / math.sqrt(r)
    mass_t = tgt.hk.vertex_mass.double().numpy()
    mass_s = src.hk.vertex_mass.double().numpy() * r
    k = int(min(k, lam_t.size))
    k_s = int(min(lam_s.size, k, max(8, math.ceil(r * k))))
    band = _band(lam_s, lam_t)
    if band is None:
        raise ValueError(
            f"{src.mesh.name or 'source'}: its spectrum (scaled by the area ratio {r:.3g}) and "
            "the whole's share no band of eigenvalues; the piece is too small for its "
            "eigenpairs (prepare more, k=...) or the area ratio is wrong")
    lo, hi = band
    sigma = 7.0 * (hi - lo) / max(2 * n_descr, 1)
    energies = np.linspace(lo + 2 * sigma, hi - 2 * sigma, n_descr)
    d_t = wave_kernel_signature(torch.from_numpy(lam_t), phi_t, energies, sigma,
                                normalize=False).numpy()
    d_s = wave_kernel_signature(torch.from_numpy(lam_s), phi_s, energies, sigma,
                                normalize=False).numpy()
    norm = np.sqrt((mass_t[:, None] * d_t * d_t).sum(0)).clip(1e-300)[None, :]
    d_t, d_s = d_t / norm, d_s / norm
    Vt, Ft = tgt.mesh.numpy()
    Vs, Fs = src.mesh.numpy()
    B, Dn, On = descriptor_operators(np.asarray(Vt, np.float64) / scale, Ft, mass_t,
                                     phi_t[:, :k].numpy(), d_t)
    ph_s = phi_s[:, :k_s].numpy()
    A, Dm, Om = descriptor_operators(np.asarray(Vs, np.float64) / scale, Fs, mass_s, ph_s, d_s)
    mask = _resolvent_mask(lam_s[:k_s], lam_t[:k])
    coef = _coefficients(A, B, mask, (Dm, Dn), (Om, On), weights)
    if dist is None:
        dist = _boundary_distance(src, scale)
    w = np.clip(np.where(np.isfinite(dist), dist, np.inf) / ramp, 0.0, 1.0) * mass_s
    gram = (ph_s.T * w[None, :]) @ ph_s
    return coef, (ph_s.T * w[None, :]) @ d_s, B, mask, (Dm, Dn), (Om, On), gram


#: Radius (units of ``sqrt(area(N))``) within which two maps of a piece agree at a point
AGREE_RADIUS = 0.15


def _agreement(tgt: PreparedShape, images: torch.Tensor, other: torch.Tensor) -> float:
    """Share of the positions where two arrays of target vertices lie within
    ``AGREE_RADIUS sqrt(area(N))`` of each other (:func:`~.refine._agree` at a piece's
    radius)."""
    V, _ = tgt.mesh.numpy()
    return _agree(V, images.cpu(), other.cpu(), AGREE_RADIUS * math.sqrt(tgt.mesh.area()))


def partial_descriptor_images(src: PreparedShape, tgt: PreparedShape, C: torch.Tensor,
                              rows: torch.Tensor) -> torch.Tensor:
    """Target vertices of ``rows`` under a rectangular functional map (exact, brute force).

    ``T(x) = argmin_y |Phi_M[x, :k_s] C - Phi_N[y, :k_t]|`` over every target vertex.

    Parameters
    ----------
    src, tgt : PreparedShape
        The piece and the whole.
    C : torch.Tensor, shape (k_s, k_t)
        As returned by :func:`partial_descriptor_map` or :func:`partial_zoomout`.
    rows : torch.Tensor, int64, shape (s,)
        Source vertices.

    Returns
    -------
    torch.Tensor, int64, shape (s,)

    Examples
    --------
    >>> import trimesh, torchheat
    >>> m = trimesh.creation.icosphere(2)
    >>> s = torchheat.prepare(torchheat.Mesh(m.vertices, m.faces), k=20)
    >>> C = torch.eye(20, dtype=torch.float64)
    >>> bool((partial_descriptor_images(s, s, C, torch.arange(s.n)) == torch.arange(s.n)).all())
    True
    """
    k_s, k_t = C.shape
    Ps = src.hk.eigenvectors.to(torch.float32)
    Pt = tgt.hk.eigenvectors[:, :k_t].to(torch.float32)
    return _pull_map(Ps, Pt, C.to(torch.float32), rows)[1]


def dense_partial_map(src: PreparedShape, tgt: PreparedShape, C: torch.Tensor,
                      num_threads: int | None = None, rows: torch.Tensor | None = None
                      ) -> torch.Tensor:
    """Every vertex of the piece (or the vertices ``rows``) mapped by a rectangular functional
    map (exact pruned search).

    Each row's image is searched on its own, so the images of ``rows`` are those of the full
    map at ``rows`` (checked bit for bit on 26 SHREC'16 pieces, 1000 rows each). Cost: the
    target's clusters (``O(m sqrt(m) k_t)``, independent of the rows) plus the searched pairs
    of the rows.

    Parameters
    ----------
    src, tgt : PreparedShape
        The piece (n vertices) and the whole (m vertices).
    C : torch.Tensor, shape (k_s, k_t)
    num_threads : int, optional
        Torch threads for the search.
    rows : torch.Tensor, int64, shape (r,), optional
        Source vertices to map (default: all).

    Returns
    -------
    torch.Tensor, int64, shape (n,) or (r,)

    Examples
    --------
    >>> import trimesh, torchheat
    >>> ico = trimesh.creation.icosphere(3)
    >>> ball = torchheat.prepare(torchheat.Mesh(ico.vertices, ico.faces), k=16)
    >>> dense_partial_map(ball, ball, torch.eye(16), rows=torch.tensor([5, 7])).tolist()
    [5, 7]
    """
    k_s, k_t = C.shape
    phi_s = src.hk.eigenvectors[:, :k_s].to(torch.float64)
    phi_t = tgt.hk.eigenvectors[:, :k_t].to(torch.float64)
    centres = _cluster_centres(tgt)
    with threads(num_threads):
        return _nn_factors_pruned(_Factors(phi_s, C.to(torch.float64)), rows,
                                  _Factors(phi_t, torch.eye(k_t, dtype=torch.float64)),
                                  centres)[1]
