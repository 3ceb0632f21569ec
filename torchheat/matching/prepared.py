"""Prepared shapes: a mesh with its heat kernel, HKS, feature points and normals, computed once
(:func:`prepare`), and the landmark descriptors of a prepared shape (memoised per call).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, TypeGuard

import numpy as np
import torch

from .._arrays import to_numpy
from ..descriptors import (
    farthest_point_sampling,
    feature_points,
    heat_kernel_map,
    hks,
)
from ..eigen import DEFAULT_EIGENPAIRS
from ..heat import HeatKernel
from ..mesh import Mesh, MeshError, as_mesh
from ..operators import Boundary, Kind
from .options import _PREPARE_LEAST, _check_numbers

__all__ = ["CachedShape", "PreparedShape", "ShapeCaches", "is_cached_shape", "prepare"]


# ------------------------------------------------------------------------------------------
# prepared shapes
# ------------------------------------------------------------------------------------------
@dataclass
class ShapeCaches:
    """What a prepared shape computes once on demand and shares with its role copies: results
    that depend on the mesh and the eigenbasis only, not on the heat kernel's times (a
    target's times are re-planned to each source's, :func:`_role_copy`).

    Attributes
    ----------
    fps : torch.Tensor or None, int64, shape (s,)
        Farthest-point order of the vertices (:func:`_fps`; longer requests extend it).
    self_symmetry : dict
        ``(own times, log floor) -> (samples, images) or None``: the shape's intrinsic
        self-symmetry (``pipeline._self_symmetry``), computed at the shape's own times.
    self_symmetry_alternates : dict
        Same keys: up to two distinct orientation-reversing self-maps (``_self_symmetries``).
    self_rotation : dict
        Same keys: the functional map of the shape's half-turn self-map, or None where it has
        no clean one (``pipeline._self_rotation``, ``select._rotation_map``).
    fmap_operators : dict
        ``(k, n_descr, eigenpairs) -> (red, mult, orient)`` (:func:`.fmap.shape_operators`).
    filled_mesh : Mesh or None
        The shape with its holes closed (``partial_scale._filled_of``).
    boundary_distance : dict
        ``scale -> (n,)`` distances of the vertices to the mesh boundary in units of ``scale``
        (``partial._boundary_distance``; a piece is measured in its whole's sqrt(area)).
    filled_eigenpairs : (lam, phi) or None
        Eigenpairs of ``filled_mesh`` solved elsewhere (the command line's background workers,
        ``partial_scale.offer_filled``); the filled way prepares the closed piece with them.
    basis : torch.Tensor or None, float64, shape (n, K)
        An eigenbasis larger than the heat kernel's (:func:`_basis`: ``match(fine_k=K)``'s
        last ZoomOut): solved once per shape, or offered (:func:`offer_basis`) by the command
        line's background workers or a dataset cache holding more eigenpairs.
    """

    fps: torch.Tensor | None = None
    self_symmetry: dict = field(default_factory=dict)
    self_symmetry_alternates: dict = field(default_factory=dict)
    self_rotation: dict = field(default_factory=dict)
    fmap_operators: dict = field(default_factory=dict)
    filled_mesh: Mesh | None = None
    filled_eigenpairs: tuple | None = None
    boundary_distance: dict = field(default_factory=dict)
    basis: torch.Tensor | None = None


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
        times (on a private copy: the caller's shape is never re-planned); the target's
        self-symmetry (the mirror hypothesis) is computed at these own times instead, once
        per prepared target, whatever the source.
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
    caches: ShapeCaches = field(default_factory=ShapeCaches, repr=False, compare=False)
    # one match's memo of landmark descriptors (time-dependent, emptied after each match);
    # init=False: every copy gets its own
    _desc_cache: dict = field(default_factory=dict, init=False, repr=False, compare=False)

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
    cached = shape.caches.fps
    if cached is None or cached.numel() < k:
        V, _ = shape.mesh.numpy()
        cached = shape.caches.fps = farthest_point_sampling(V, max(k, 256))
    return cached[:k]


def _cluster_centres(shape: PreparedShape) -> torch.Tensor:
    """Centres of the cluster-pruned exact search (:func:`~.nn._nn_factors_pruned`) over the
    shape's vertices: its first ``4 sqrt(m)`` farthest-point samples (at least 16, at most
    all ``m`` vertices)."""
    m = shape.n
    return _fps(shape, min(m, max(16, int(4 * math.sqrt(m)))))


def _basis(shape: PreparedShape, k: int) -> torch.Tensor:
    """The first ``k`` mass-orthonormal eigenfunctions of the shape, float64, shape (n, k'):
    the heat kernel's when it holds ``k`` of them, otherwise one new eigensolve
    (:meth:`~torchheat.heat.HeatKernel.eigenpairs`) kept in the shape's caches (shared by its
    role copies) and cut to ``k``. ``k' = min(k, free vertices)``."""
    if k <= shape.hk.eigenvalues.numel():
        return shape.hk.eigenvectors[:, :k].to(torch.float64)
    cached = shape.caches.basis
    if cached is None or cached.shape[1] < k:
        cached = shape.caches.basis = shape.hk.eigenpairs(k)[1]
    return cached[:, :k]


def offer_basis(shape: PreparedShape, lam: Any, phi: Any) -> bool:
    """Give the shape a larger eigenbasis solved elsewhere (the command line's background
    workers, ``--fine``), for :func:`_basis`. Kept only if it extends the heat kernel's: more
    columns, on the same vertices, its first eigenvalues those of the heat kernel (relative
    1e-6); otherwise ignored (``_basis`` then solves it in-process), so an offer never changes
    a result.

    Parameters
    ----------
    shape : PreparedShape
    lam : array_like, shape (K,)
    phi : array_like, shape (n, K)

    Returns
    -------
    bool
        Whether the basis was kept.
    """
    lam = np.asarray(lam, dtype=np.float64)
    phi = np.asarray(phi, dtype=np.float64)
    held = shape.hk.eigenvalues.numpy()
    if phi.ndim != 2 or phi.shape != (shape.n, lam.size) or lam.size <= held.size:
        return False
    scale = max(float(np.abs(held).max()) if held.size else 0.0, 1e-300)
    if not np.all(np.abs(lam[: held.size] - held) <= 1e-6 * scale):
        return False
    shape.caches.basis = torch.from_numpy(phi)
    return True


def _memoised(memo: dict | None, key: tuple, compute: Callable[[], Any]) -> Any:
    """``memo[key]``, computed by ``compute()`` the first time (always, without a memo): the
    per-match memo a match's stages share (refined hypotheses, ZoomOuts, functional-map
    Hessians)."""
    if memo is None:
        return compute()
    if key not in memo:
        memo[key] = compute()
    return memo[key]


def _role_copy(shape: PreparedShape, times: torch.Tensor | None = None) -> PreparedShape:
    """A copy of the shape with its own heat-kernel solver, at ``times`` if given
    (:meth:`~torchheat.heat.HeatKernel.with_times`: :func:`match` plans a target at its
    source's times on such a copy) and its own timings; the eigenbasis and the
    :class:`ShapeCaches` (farthest-point samples, self-symmetries, functional-map operators,
    filled mesh) are shared: computed once per shape, whichever copy asks first."""
    hk = copy.copy(shape.hk) if times is None else shape.hk.with_times(times)
    return dataclasses.replace(shape, hk=hk, timings=dict(shape.timings))


def _vertex_normals(mesh: Mesh) -> np.ndarray:
    V, F = mesh.numpy()
    fn = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])  # area-weighted
    vn = np.zeros_like(V)
    for k in range(3):
        np.add.at(vn, F[:, k], fn)
    return vn / np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)


class CachedShape(Protocol):
    """What :func:`prepare` reads from a dataset shape (:class:`torchheat.datasets.Shape`):
    the mesh, the cached preprocessing (``data``, None when there is none) and a heat kernel
    rebuilt from it. Declared here so that matching need not import ``datasets``."""

    mesh: Mesh
    data: dict | None

    def heat_kernel(self, **kw: Any) -> HeatKernel: ...


def is_cached_shape(x: Any) -> TypeGuard[CachedShape]:
    """Whether ``x`` is a dataset shape (:class:`CachedShape`) rather than a mesh.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> s = trimesh.creation.icosphere(1)
    >>> is_cached_shape(Mesh(s.vertices, s.faces))
    False
    """
    return (not isinstance(x, (Mesh, PreparedShape)) and isinstance(getattr(x, "mesh", None), Mesh)
            and hasattr(x, "data") and callable(getattr(x, "heat_kernel", None)))


def prepare(
    mesh: Mesh | CachedShape | Any,
    times: str | Sequence[float] | torch.Tensor | None = "adaptive",
    *,
    feature_time: float = 0.05,
    max_features: int = 50,
    k: int | None = None,
    rtol: float = 1e-6,
    kind: Kind | None = None,
    boundary: Boundary | None = None,
    hk: HeatKernel | None = None,
    eigenpairs: tuple | None = None,
    num_threads: int | None = None,
) -> PreparedShape:
    """Precompute a shape for matching (heat kernel, HKS, features, normals).

    Parameters
    ----------
    mesh : Mesh, torchheat.datasets.Shape, or what :func:`torchheat.as_mesh` takes
        A mesh (or a file path, a ``trimesh.Trimesh``, a ``(vertices, faces)`` pair), or a
        shape of a dataset (:class:`torchheat.datasets.ShapeCollection`): its
        cached eigenpairs (``shape.data``, from the collection's :class:`~torchheat.datasets.
        Preprocess` and disk cache) are used, so no eigensolve runs; a shape without cached
        data is prepared from its mesh.
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
    k : int, optional
        Eigenpairs of the heat kernel's eigenbasis (default 100; for a dataset shape with
        cached data: the cached ones; fewer: the first ``k`` of them, the rest kept for
        ``match(fine_k=...)``; more: a new eigensolve).
    rtol, num_threads
        Passed to :class:`HeatKernel`.
    kind, boundary : str, optional
        Passed to :class:`HeatKernel` (default ``"cotan"``, ``"neumann"``; for a dataset
        shape: those of its cached data; others than those mean a new eigensolve).
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

    A shape of a dataset with a :class:`~torchheat.datasets.Preprocess` (eigenpairs read from
    the disk cache, no eigensolve):

    >>> from torchheat.datasets import Preprocess, tosca_remeshed_5k
    >>> pair = tosca_remeshed_5k(preprocess=Preprocess())[0]  # doctest: +SKIP
    >>> prepare(pair.source).hk.k  # doctest: +SKIP
    100
    """
    _check_numbers({"k": k, "max_features": max_features, "feature_time": feature_time,
                    "rtol": rtol, "num_threads": num_threads}, _PREPARE_LEAST)
    t0 = time.perf_counter()
    cached = None  # a dataset shape's cached eigenpairs, when the heat kernel uses them
    if is_cached_shape(mesh):
        shape, mesh = mesh, mesh.mesh
        if hk is None and eigenpairs is None and shape.data is not None:
            hk = _cached_heat_kernel(shape, times, k, rtol, kind, boundary, num_threads)
            cached = (shape.data["eigenvalues"], shape.data["eigenvectors"])
    else:
        mesh = as_mesh(mesh)  # a path, a trimesh, (V, F): loaded and checked as a Mesh
    k = DEFAULT_EIGENPAIRS if k is None else k
    _check_matchable(mesh, k if hk is None else hk.k)
    if hk is None:
        kind = "cotan" if kind is None else kind
        boundary = "neumann" if boundary is None else boundary
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
            hk = hk.with_times(hk.adaptive_times())
    t1 = time.perf_counter()
    lam = hk.eigenvalues.numpy()
    phi = hk.eigenvectors.numpy()
    sig = (phi**2) @ np.exp(-feature_time * lam)  # HKS at the feature time
    feats = feature_points(mesh, sig, rings=2, max_features=max_features)
    normals = _vertex_normals(mesh)
    t2 = time.perf_counter()
    out = PreparedShape(mesh, hk, feats, normals,
                        {"heat_kernel": t1 - t0, "descriptors": t2 - t1},
                        own_times=hk.times.clone())
    if cached is not None and len(cached[0]) > hk.eigenvalues.numel():
        # more cached than the heat kernel uses (Preprocess(k=200), prepare(k=100)): kept
        # for match(fine_k=...), which then solves nothing
        offer_basis(out, to_numpy(cached[0]), to_numpy(cached[1]))
    return out


def _cached_heat_kernel(shape: CachedShape, times: Any, k: int | None, rtol: float,
                        kind: Kind | None, boundary: Boundary | None,
                        num_threads: int | None) -> HeatKernel:
    """The heat kernel :func:`prepare` would build, from a dataset shape's cached eigenpairs
    (the same eigenpairs, so the same prepared shape)."""
    if isinstance(times, str) and times not in ("adaptive", "paper"):
        raise ValueError(f"unknown times {times!r}; use 'adaptive', 'paper' or a list")
    adaptive = isinstance(times, str) and times == "adaptive"
    kw: dict[str, Any] = {"times": None if isinstance(times, str) else times, "rtol": rtol,
                          "method": "spectral" if adaptive else "auto",
                          "num_threads": num_threads}
    kw.update({name: v for name, v in (("k", k), ("kind", kind), ("boundary", boundary))
               if v is not None})
    hk = shape.heat_kernel(**kw)
    if adaptive:
        hk = hk.with_times(hk.adaptive_times())
    return hk


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
    return prepare(x, **kw)  # a Mesh, a dataset shape, or what as_mesh takes


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
            hit = shape._desc_cache.get(key)
        if hit is not None:
            return hit
    D = heat_kernel_map(shape.hk, landmarks, columns)
    if use_hks:
        D = torch.cat([D, shape.hks.to(D.dtype)], dim=1)
    if key is not None:
        limit = _DESC_CACHE_BYTES // max(1, D.element_size() * D.numel())
        with _DESC_LOCK:
            cache = shape._desc_cache
            while cache and len(cache) >= limit:
                cache.pop(next(iter(cache)))  # oldest first
            if limit > 0:
                cache[key] = D
    return D
