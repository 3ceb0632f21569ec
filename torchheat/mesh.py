"""Triangle meshes: loading, validation and basic topology.

Conventions
-----------
* A :class:`Mesh` holds ``vertices`` (``torch.float64``, ``[n, 3]``, contiguous, on the CPU) and
  ``faces`` (``torch.int64``, ``[m, 3]``, zero-based). Meshes are treated as immutable: derived
  quantities (edges, adjacency) are computed once and cached; use :meth:`Mesh.with_vertices` for
  new coordinates on the same connectivity.
* **Vertex order is sacred.** Ground-truth correspondences of shape-matching benchmarks (TOSCA,
  SCAPE, KIDS, ...) are given as vertex indices, so :func:`load_mesh` never merges, splits,
  reorders or drops the vertices of OFF, OBJ and PLY files (polygons are triangulated). STL
  (a triangle soup), GLB and glTF files have their exact-duplicate vertices merged, in order
  of first appearance. Files are read by :mod:`torchheat.meshio`, whose docstring has the
  details.
  The only exception is ``largest_component=True`` (``--largest-component`` on the command
  line), which drops the vertices outside the largest connected component and records, in
  :attr:`Mesh.vertex_map`, the index each kept vertex had in the input
  (:meth:`Correspondence.full_map <torchheat.matching.Correspondence.full_map>` translates
  maps back to the input numbering).
* Validation (``check=True``, the default) refuses, with a :class:`MeshError` (a
  ``ValueError``) whose message starts with the file path or mesh name, says what is wrong and
  what to do: missing / unreadable / unsupported files, meshes without faces, non-triangle
  faces, non-finite coordinates, face indices out of range, degenerate (zero-area) faces,
  unreferenced vertices, and several connected components (components that meet at
  coincident vertices are named a seam of duplicated vertices, to be merged; keeping the
  largest of them warns). Non-manifold **edges** (shared by
  more than two faces) only raise a :class:`MeshWarning`: such meshes still give a usable
  Laplacian, but results near those edges are less reliable. Non-manifold (pinched) vertices
  and boundaries are accepted silently: all areas are unsigned. Faces oriented against their
  neighbours are turned (:func:`torchheat.topology.orient_faces`: in each patch the minority
  is reversed, :attr:`Mesh.flipped_faces` counts them; vertex order and indices are kept), since
  normals, boundary loops and the mirror-image test read the faces' turning sense (SHREC'16's
  michael and david, and TOSCA hires's horse5/6, centaur3/4 and david0/1, have patches of
  reversed faces); a mesh that cannot be oriented raises a :class:`MeshWarning`. A surface
  wound inside out (negative enclosed volume, its holes closed first) has every face reversed
  (:func:`torchheat.topology.orient_outward`, :attr:`Mesh.turned_outward`): matched to a shape
  stored outward it would otherwise take the mirror map for the direct one.
* A face is degenerate when its area is ``<= 1e-12 * d**2`` with ``d`` the bounding-box
  diagonal; faces with a repeated vertex are always degenerate.
* Validation is vectorised (numpy, ``scipy.sparse.csgraph``): about 50 ms for a 60k-vertex
  mesh (KIDS). ``check=False`` skips it and only converts dtypes (shapes are still checked).

Examples
--------
>>> import trimesh
>>> from torchheat.mesh import Mesh
>>> ico = trimesh.creation.icosahedron()
>>> mesh = Mesh(ico.vertices, ico.faces, name="ico")
>>> mesh
Mesh(name='ico', n_vertices=12, n_faces=20)
>>> mesh.edges().shape
torch.Size([30, 2])
"""

from __future__ import annotations

import math
import os
import warnings
from typing import Any

import numpy as np
import scipy.sparse as sp
import torch

from ._arrays import to_numpy
from .geometry import face_areas
from .meshio import SUPPORTED_FORMATS, MeshError, MeshWarning, _plural, read_arrays
from .topology import (
    adjacency_from_keys,
    components,
    edge_keys,
    orient_faces,
    orient_outward,
    restrict_faces,
)
from .topology import largest_component as _largest_component

__all__ = ["Mesh", "MeshError", "MeshWarning", "as_mesh", "load_mesh", "SUPPORTED_FORMATS"]

#: Relative area threshold of degenerate faces: ``area <= DEGENERATE_REL_AREA * diag**2``.
DEGENERATE_REL_AREA = 1e-12

_MAX_LISTED = 5  # how many offending indices an error message lists


def _listed(idx: np.ndarray) -> str:
    """Format the first few indices of ``idx``: ``"3, 7, 9, ..."``."""
    head = ", ".join(str(int(i)) for i in idx[:_MAX_LISTED])
    return head + (", ..." if idx.size > _MAX_LISTED else "")


def _repeated_faces(faces: torch.Tensor) -> str:
    """The advice of the non-manifold-edge warning: names faces that repeat another face's
    three vertices (either winding: a copy, or a two-sided flap), the common cause, and how to
    remove them; else a generic advice."""
    key = np.sort(faces.numpy(), axis=1)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    rep = np.flatnonzero(first[inverse.ravel()] != np.arange(key.shape[0]))
    if not rep.size:
        return "repair the mesh if you can"
    a, b = int(first[inverse.ravel()[rep[0]]]), int(rep[0])
    F = faces.numpy()
    same = (F[a] == np.roll(F[b], 1)).all() or (F[a] == np.roll(F[b], 2)).all() or (
        F[a] == F[b]).all()
    how = "a copy" if same else "wound the other way: a two-sided flap"
    verb = "repeats" if rep.size == 1 else "repeat"
    return (f"and {_plural(rep.size, 'face')} {verb} the three vertices of an earlier face "
            f"(first: face {b} repeats face {a}, {how}), so the Laplacian counts that surface "
            "twice: remove the repeated faces (trimesh: mesh.update_faces(mesh.unique_faces());"
            " MeshLab 'Remove Duplicate Faces'), a flap with both its faces and its own vertex; "
            "this renumbers faces (and vertices): renumber any correspondences")


def _to_numpy(x: Any, what: str, label: str) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    try:
        return np.asarray(x)
    except (ValueError, TypeError) as exc:
        raise MeshError(
            f"{label}: {what} could not be converted to an array ({exc}); "
            f"pass {what} as a numpy array, torch tensor or nested list"
        ) from exc


def _vertices_tensor(vertices: Any, label: str) -> torch.Tensor:
    if isinstance(vertices, torch.Tensor):
        V = vertices.to(device="cpu", dtype=torch.float64)
        if V is vertices:  # never share storage with the caller (meshes are immutable)
            V = V.clone()
    else:
        arr = _to_numpy(vertices, "vertices", label)
        if arr.dtype == object or not (
            np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_
        ):
            raise MeshError(
                f"{label}: vertices have non-numeric dtype {arr.dtype}; "
                "pass an [n, 3] array of floats"
            )
        V = torch.from_numpy(np.array(arr, dtype=np.float64, copy=True))
    if V.ndim != 2 or V.shape[1] != 3:
        raise MeshError(
            f"{label}: vertices must have shape [n, 3], got {tuple(V.shape)}; "
            "pass one row of x, y, z per vertex"
        )
    if V.shape[0] == 0:
        raise MeshError(f"{label}: mesh has no vertices; check that the file is not empty")
    return V.contiguous()


def _faces_tensor(faces: Any, label: str) -> torch.Tensor:
    arr = _to_numpy(faces, "faces", label)
    if arr.size == 0:
        raise MeshError(
            f"{label}: mesh has no faces (a point cloud?); a triangle mesh is required, "
            "reconstruct a surface first (e.g. Poisson / ball pivoting in MeshLab or Open3D)"
        )
    if arr.ndim != 2 or arr.shape[1] != 3:
        if arr.ndim == 2:
            raise MeshError(
                f"{label}: faces have {arr.shape[1]} corners, only triangles are supported "
                f"(non-triangle faces); triangulate it first"
            )
        raise MeshError(
            f"{label}: faces must have shape [m, 3], got {arr.shape}; "
            "pass one row of three vertex indices per triangle"
        )
    if np.issubdtype(arr.dtype, np.floating):
        if not np.isfinite(arr).all() or not np.array_equal(arr, np.round(arr)):
            raise MeshError(
                f"{label}: face indices must be integers, got non-integral {arr.dtype} values; "
                "pass an integer array of vertex indices"
            )
    elif not np.issubdtype(arr.dtype, np.integer):
        raise MeshError(
            f"{label}: face indices have dtype {arr.dtype}; pass an integer array of vertex indices"
        )
    return torch.from_numpy(np.array(arr, dtype=np.int64, copy=True)).contiguous()


def _bbox_diagonal_np(V: np.ndarray) -> float:
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


class Mesh:
    """A triangle mesh with validated, index-preserving vertices.

    Parameters
    ----------
    vertices : array_like or torch.Tensor, shape [n, 3]
        Vertex coordinates (numpy array, torch tensor or nested lists). Stored as a contiguous
        ``float64`` CPU tensor.
    faces : array_like or torch.Tensor, shape [m, 3]
        Zero-based vertex indices of the triangles. Stored as ``int64``.
    name : str, optional
        File path or user-chosen name, used in error messages and ``repr``.
    check : bool, default True
        Validate the mesh (see the module docstring). ``False`` skips the validation for
        speed and only converts dtypes (and checks shapes).
    largest_component : bool, default False
        Keep only the largest connected component (by number of vertices; ties go to the
        component holding the lowest vertex index), renumbering vertices and faces;
        :attr:`vertex_map` records the original index of each kept vertex and
        :attr:`n_input_vertices` how many the input had. Unreferenced vertices count as
        (single-vertex) components and are dropped too. A :class:`~torchheat.Correspondence`
        between such meshes gives maps in the input numbering by ``full_map()``.

    Attributes
    ----------
    vertices : torch.Tensor
        ``[n, 3]`` float64.
    faces : torch.Tensor
        ``[m, 3]`` int64.
    name : str or None
        File path or user name.
    vertex_map : torch.Tensor
        ``[n]`` int64: index in the original input of each kept vertex (``arange(n)`` unless
        ``largest_component=True`` dropped some).
    n_input_vertices : int
        Number of vertices of the input, those dropped by ``largest_component=True``
        included (``n_vertices`` unless some were dropped).
    flipped_faces : int
        Faces whose vertex order was reversed at load (``check=True``): those turned against
        their neighbours, or all of them when the surface was wound inside out.
    turned_outward : bool
        Whether the surface was wound inside out and every face was reversed
        (:func:`torchheat.topology.orient_outward`).

    Raises
    ------
    MeshError
        Empty or wrongly shaped input; with ``check=True`` also non-finite coordinates, face
        indices out of range, degenerate faces, unreferenced vertices and several connected
        components (unless ``largest_component=True``).

    Warns
    -----
    MeshWarning
        Non-manifold edges (shared by more than two faces). This is a warning, not an error:
        the operators still work, and some public datasets contain a few such edges. Also
        faces that cannot be oriented consistently, and ``largest_component=True`` dropping
        components that meet the kept one at coincident vertices (a seam).

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    >>> F = np.array([[0, 1, 2], [1, 3, 2]])
    >>> mesh = Mesh(V, F, name="square")
    >>> mesh.n_vertices, mesh.n_faces, mesh.area()
    (4, 2, 1.0)
    >>> mesh.boundary_edges().tolist()
    [[0, 1], [0, 2], [1, 3], [2, 3]]
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    name: str | None
    vertex_map: torch.Tensor
    n_input_vertices: int

    def __init__(
        self,
        vertices: Any,
        faces: Any,
        *,
        name: str | None = None,
        check: bool = True,
        largest_component: bool = False,
    ) -> None:
        self.name = None if name is None else str(name)
        label = self._label()
        V = _vertices_tensor(vertices, label)
        F = _faces_tensor(faces, label)
        n = V.shape[0]
        self.n_input_vertices = int(n)
        vertex_map = torch.arange(n, dtype=torch.int64)
        self._edge_cache: tuple[np.ndarray, np.ndarray] | None = None

        Vn = V.detach().numpy()
        Fn = F.numpy()
        if check:
            self._check_finite(Vn)
            self._check_range(Fn, n)
        if largest_component:
            keys, counts = edge_keys(Fn, n)
            kept = _largest_component(Fn, n, keys)
            if kept is None:
                self._edge_cache = (keys, counts)
            else:
                inside = np.zeros(n, dtype=np.int64)
                inside[kept] = 1
                seam = _shared_positions(Vn, inside)
                if seam:
                    warnings.warn(
                        f"{label}: the dropped components meet the kept one at "
                        f"{_plural(seam, 'coincident vertex')}: a seam of duplicated vertices "
                        "(as UV-mapped exports store it) cuts the surface, and only one side "
                        "is matched; merge the duplicate vertices instead (trimesh's "
                        "merge_vertices, MeshLab 'Merge Close Vertices')",
                        MeshWarning,
                        stacklevel=2,
                    )
                Fn = restrict_faces(Fn, kept, n)
                Vn = Vn[kept]
                V = V[torch.from_numpy(kept)].contiguous()
                F = torch.from_numpy(Fn)
                vertex_map = torch.from_numpy(kept.astype(np.int64))
                n = kept.size
                if Fn.shape[0] == 0:
                    raise MeshError(
                        f"{label}: the largest connected component has no faces (the mesh "
                        "is made of isolated vertices); check the file"
                    )
        self.vertices = V
        self.faces = F
        self.vertex_map = vertex_map
        #: Faces whose vertex order was reversed (``check=True``): to agree with their
        #: neighbours, and all of them when the surface was wound inside out
        self.flipped_faces = 0
        #: Whether every face was reversed because the surface was wound inside out
        #: (:func:`torchheat.topology.orient_outward`; ``check=True``)
        self.turned_outward = False
        self._oriented = False  # set by _orient: faces consistently oriented and wound outward
        if check:
            self._check_degenerate(Vn, Fn)
            self._check_unreferenced(Fn, n)
            self._check_topology()
            self._orient(Vn, Fn, n)

    # ------------------------------------------------------------------ checks
    def _label(self) -> str:
        return self.name if self.name is not None else "mesh"

    def _check_finite(self, V: np.ndarray) -> None:
        bad = np.flatnonzero(~np.isfinite(V).all(axis=1))
        if bad.size:
            raise MeshError(
                f"{self._label()}: {_plural(bad.size, 'vertex')} with NaN/inf coordinates "
                f"(first: vertex {int(bad[0])}; vertices {_listed(bad)}); "
                "fix or remove them in the file before loading"
            )

    def _check_range(self, F: np.ndarray, n: int) -> None:
        bad_mask = (F < 0) | (F >= n)
        bad = np.flatnonzero(bad_mask.any(axis=1))
        if bad.size:
            values = F[bad_mask]
            advice = "the file is corrupt or indices are not zero-based, fix the face list"
            if F.size and int(F.min()) == 1 and int(F.max()) == n:
                advice = (f"the indices run from 1 to {n}: they are one-based (as MATLAB "
                          "and .mat files store them), subtract 1 from every index")
            raise MeshError(
                f"{self._label()}: {_plural(bad.size, 'face')} with vertex indices out of range "
                f"(valid: 0..{n - 1}; found e.g. {int(values[0])} in face {int(bad[0])}; "
                f"faces {_listed(bad)}); {advice}"
            )

    def _check_degenerate(self, V: np.ndarray, F: np.ndarray) -> None:
        areas = face_areas(V, F)
        diag = _bbox_diagonal_np(V)
        bad = np.flatnonzero(areas <= DEGENERATE_REL_AREA * diag**2)
        if bad.size:
            Fb = F[bad]
            repeated = int(
                ((Fb[:, 0] == Fb[:, 1]) | (Fb[:, 1] == Fb[:, 2]) | (Fb[:, 0] == Fb[:, 2])).sum()
            )
            extra = f", {repeated} with a repeated vertex" if repeated else ""
            # two distinct corners at one position (within 1e-6 of the diagonal): vertices
            # stored twice (a UV sphere's poles, a seam), which only merging repairs; removing
            # the faces would open a hole
            close = math.sqrt(DEGENERATE_REL_AREA) * diag
            twins = int(np.logical_or.reduce([
                (Fb[:, a] != Fb[:, b])
                & (np.linalg.norm(V[Fb[:, a]] - V[Fb[:, b]], axis=1) <= close)
                for a, b in ((0, 1), (1, 2), (0, 2))]).sum())
            remove = ("remove or collapse them (e.g. MeshLab 'Remove Zero Area Faces') while "
                      "keeping the vertex order")
            merge = (f"{twins} of them {'has' if twins == 1 else 'have'} two corners at one "
                     "position under two vertex indices (vertices stored twice, as a UV "
                     "sphere's poles or a seam often are): merge coincident vertices, then "
                     "remove the faces that collapse (MeshLab 'Merge Close Vertices', then "
                     "'Remove Zero Area Faces'; trimesh.load(path, process=True, "
                     "validate=True)); this renumbers the vertices")
            remedy = (remove if not twins else merge if twins == bad.size
                      else f"{merge}; {remove} for the others")
            raise MeshError(
                f"{self._label()}: {_plural(bad.size, 'degenerate face')} of zero area{extra} "
                f"(first faces {_listed(bad)}; area <= {DEGENERATE_REL_AREA:g} * bbox "
                f"diagonal^2); {remedy}"
            )

    def _check_unreferenced(self, F: np.ndarray, n: int) -> None:
        used = np.bincount(F.ravel(), minlength=n)
        bad = np.flatnonzero(used == 0)
        if bad.size:
            raise MeshError(
                f"{self._label()}: {_plural(bad.size, 'unreferenced vertex')} (used by no "
                f"face; vertices {_listed(bad)}); they would shift ground-truth vertex indices "
                "if dropped silently, so clean the file (remove them and renumber the "
                "correspondences), or drop them: --largest-component on the command line "
                "(maps keep the file's vertex indices, -1 for dropped vertices), "
                "largest_component=True in Python (Mesh.vertex_map has the original indices)"
            )

    def _check_topology(self) -> None:
        n = self.n_vertices
        keys, counts = self._edges_cached()
        ncomp, labels = components(keys, n)
        if ncomp > 1:
            sizes = np.sort(np.bincount(labels, minlength=ncomp))[::-1]
            shown = ", ".join(str(int(s)) for s in sizes[:10]) + (", ..." if ncomp > 10 else "")
            seam = _shared_positions(self.vertices.numpy(), labels)
            if seam:
                raise MeshError(
                    f"{self._label()}: mesh has {ncomp} connected components (vertex counts "
                    f"{shown}) that meet at {_plural(seam, 'coincident vertex')}: the surface "
                    "is cut along a seam of duplicated vertices (as UV-mapped exports store "
                    "it); merge the duplicate vertices (trimesh's merge_vertices, MeshLab "
                    "'Merge Close Vertices') and renumber any correspondences, since "
                    "--largest-component / largest_component=True would keep one side only"
                )
            raise MeshError(
                f"{self._label()}: mesh has {ncomp} connected components (vertex counts "
                f"{shown}); keep the largest one with --largest-component on the command line "
                "(maps keep the file's vertex indices, -1 for dropped vertices) or "
                "largest_component=True in Python (Mesh.vertex_map has the original indices), "
                "or split the file"
            )
        nonmanifold = np.flatnonzero(counts > 2)
        if nonmanifold.size:
            i, j = np.divmod(keys[nonmanifold[0]], np.int64(n))
            warnings.warn(
                f"{self._label()}: {_plural(nonmanifold.size, 'non-manifold edge')} (shared by "
                f"more than two faces; first ({int(i)}, {int(j)})); the mesh is used as is but "
                f"results near these edges are less reliable, {_repeated_faces(self.faces)}",
                MeshWarning,
                stacklevel=3,
            )

    def _orient(self, V: np.ndarray, F: np.ndarray, n: int) -> None:
        F2, flipped, orientable = orient_faces(F, n)
        if not orientable:
            warnings.warn(
                f"{self._label()}: the faces cannot be oriented consistently (a twisted, "
                "Moebius-like strip); areas and the Laplacian are unaffected, but normals and "
                "the orientation test that tells a shape from its mirror image are unreliable",
                MeshWarning,
                stacklevel=3,
            )
            return
        self._oriented = True  # consistently: with_vertices reads the winding again
        F2, turned = orient_outward(V, F2)
        if turned:  # wound inside out: every face reversed, those turned above back again
            flipped = len(F2) - flipped
            self.turned_outward = True
        if flipped:
            self.faces = torch.from_numpy(F2)
            self.flipped_faces = flipped

    def _edges_cached(self) -> tuple[np.ndarray, np.ndarray]:
        if self._edge_cache is None:
            self._edge_cache = edge_keys(self.faces.numpy(), self.n_vertices)
        return self._edge_cache

    # ------------------------------------------------------------- properties
    @property
    def n_vertices(self) -> int:
        """Number of vertices ``n``.

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).n_vertices
        3
        """
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        """Number of triangles ``m``.

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).n_faces
        1
        """
        return int(self.faces.shape[0])

    # ---------------------------------------------------------------- geometry
    def face_areas(self) -> torch.Tensor:
        """Unsigned triangle areas.

        Returns
        -------
        torch.Tensor
            ``[m]`` float64 (differentiable with respect to :attr:`vertices`).

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).face_areas().tolist()
        [0.5]
        """
        V, F = self.vertices, self.faces
        a = V[F[:, 0]]
        cross = torch.linalg.cross(V[F[:, 1]] - a, V[F[:, 2]] - a, dim=1)
        return 0.5 * torch.linalg.vector_norm(cross, dim=1)

    def area(self) -> float:
        """Total surface area.

        Returns
        -------
        float

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [2, 0, 0], [0, 2, 0]], [[0, 1, 2]]).area()
        2.0
        """
        return float(self.face_areas().detach().sum())

    def bbox_diagonal(self) -> float:
        """Length of the diagonal of the axis-aligned bounding box.

        Returns
        -------
        float

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [3, 0, 0], [0, 4, 0]], [[0, 1, 2]]).bbox_diagonal()
        5.0
        """
        return _bbox_diagonal_np(self.vertices.detach().numpy())

    # ---------------------------------------------------------------- topology
    def edges(self) -> torch.Tensor:
        """Unique undirected edges.

        Returns
        -------
        torch.Tensor
            ``[e, 2]`` int64, ``i < j`` in every row, rows sorted lexicographically.

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).edges().tolist()
        [[0, 1], [0, 2], [1, 2]]
        """
        keys, _ = self._edges_cached()
        return self._keys_to_edges(keys)

    def boundary_edges(self) -> torch.Tensor:
        """Edges used by exactly one face.

        Returns
        -------
        torch.Tensor
            ``[b, 2]`` int64, ``i < j``, sorted lexicographically (empty for a closed mesh).

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).boundary_edges().shape
        torch.Size([3, 2])
        """
        keys, counts = self._edges_cached()
        return self._keys_to_edges(keys[counts == 1])

    def boundary_vertices(self) -> torch.Tensor:
        """Mask of the vertices on a boundary edge.

        Returns
        -------
        torch.Tensor
            ``[n]`` bool.

        Examples
        --------
        >>> Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).boundary_vertices().tolist()
        [True, True, True]
        """
        mask = torch.zeros(self.n_vertices, dtype=torch.bool)
        mask[self.boundary_edges().reshape(-1)] = True
        return mask

    def adjacency(self) -> sp.csr_matrix:
        """Vertex adjacency matrix.

        Returns
        -------
        scipy.sparse.csr_matrix
            ``[n, n]`` float64, 1 where ``(i, j)`` is an edge, symmetric, zero diagonal.

        Examples
        --------
        >>> A = Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).adjacency()
        >>> A.toarray().tolist()
        [[0.0, 1.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 0.0]]
        """
        keys, _ = self._edges_cached()
        return adjacency_from_keys(keys, self.n_vertices)

    def _keys_to_edges(self, keys: np.ndarray) -> torch.Tensor:
        i, j = np.divmod(keys, np.int64(self.n_vertices))
        return torch.from_numpy(np.stack([i, j], axis=1).astype(np.int64, copy=False))

    # ------------------------------------------------------------- conversions
    def numpy(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the vertices and faces as numpy arrays.

        Returns
        -------
        V : numpy.ndarray
            ``[n, 3]`` float64.
        F : numpy.ndarray
            ``[m, 3]`` int64.

        Examples
        --------
        >>> V, F = Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]]).numpy()
        >>> V.dtype, F.dtype, F.shape
        (dtype('float64'), dtype('int64'), (1, 3))
        """
        return self.vertices.detach().numpy().copy(), self.faces.numpy().copy()

    def with_vertices(self, vertices: Any) -> Mesh:
        """A mesh with the same faces, name and ``vertex_map`` but new coordinates.

        The coordinates are checked (shape ``[n, 3]``, finite, no degenerate face); the
        connectivity and its cached topology are reused. Faces are wound outward for the new
        coordinates as :class:`Mesh` winds them (a mirror image turns them all:
        ``turned_outward`` then flips).

        Parameters
        ----------
        vertices : array_like or torch.Tensor, shape [n, 3]
            New coordinates, same number of vertices.

        Returns
        -------
        Mesh

        Raises
        ------
        MeshError
            Wrong shape, non-finite coordinates or degenerate faces.

        Examples
        --------
        >>> mesh = Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
        >>> mesh.with_vertices(2 * mesh.vertices).area()
        2.0
        """
        label = self._label()
        V = _vertices_tensor(vertices, label)
        if V.shape[0] != self.n_vertices:
            raise MeshError(
                f"{label}: new vertices have shape {tuple(V.shape)} but the mesh has "
                f"{self.n_vertices} vertices; pass an [{self.n_vertices}, 3] array"
            )
        new = Mesh.__new__(Mesh)
        new.name = self.name
        new.vertices = V
        new.faces = self.faces
        new.vertex_map = self.vertex_map
        new.n_input_vertices = self.n_input_vertices
        new._edge_cache = self._edge_cache
        new.flipped_faces = getattr(self, "flipped_faces", 0)
        new.turned_outward = getattr(self, "turned_outward", False)
        new._oriented = getattr(self, "_oriented", False)
        Vn = V.detach().numpy()
        new._check_finite(Vn)
        new._check_degenerate(Vn, self.faces.numpy())
        if new._oriented:
            # new coordinates may turn the surface inside out (a mirror image, a negative
            # scale): wound as Mesh(vertices, faces) would wind it, else the mirror map would
            # be taken for the direct one
            F2, turned = orient_outward(Vn, self.faces.numpy())
            if turned:
                new.faces = torch.from_numpy(F2)
                new.turned_outward = not new.turned_outward
                new.flipped_faces = self.n_faces - new.flipped_faces
        return new

    def __repr__(self) -> str:
        return f"Mesh(name={self.name!r}, n_vertices={self.n_vertices}, n_faces={self.n_faces})"


def as_mesh(x: Any) -> Mesh:
    """A :class:`Mesh` from what a user holds: a Mesh (itself), a file path (:func:`load_mesh`),
    an object with ``vertices`` and ``faces`` (or ``triangles``) arrays (``trimesh.Trimesh``,
    Open3D's ``TriangleMesh``, ...), a PyTorch Geometric ``Data`` (``pos`` and ``face`` of
    shape (3, m)), or a ``(vertices, faces)`` pair of arrays.

    Validated as :class:`Mesh` validates (vertex order kept; several components refused).

    Parameters
    ----------
    x : Mesh, str, os.PathLike, mesh-like object or (array_like, array_like)
        Vertices of shape (n, 3) and triangle faces of shape (m, 3), zero-based.

    Returns
    -------
    Mesh

    Raises
    ------
    TypeError
        Anything else.
    MeshError
        What :class:`Mesh` or :func:`load_mesh` refuse.

    Examples
    --------
    >>> import trimesh
    >>> s = trimesh.creation.icosphere(1)
    >>> as_mesh(s).n_vertices, as_mesh((s.vertices, s.faces)).n_faces
    (42, 80)
    """
    if isinstance(x, Mesh):
        return x
    if isinstance(x, str | os.PathLike):
        return load_mesh(x)
    V = getattr(x, "vertices", None)
    F = getattr(x, "faces", None)
    if F is None:
        F = getattr(x, "triangles", None)  # Open3D
    if V is not None and F is not None:
        meta = getattr(x, "metadata", None)
        name = meta.get("file_name") if isinstance(meta, dict) else None
        return Mesh(to_numpy(V), to_numpy(F), name=name or type(x).__name__)
    pos, face = getattr(x, "pos", None), getattr(x, "face", None)
    if pos is not None and face is not None:  # PyTorch Geometric's Data: face is (3, m)
        return Mesh(to_numpy(pos), to_numpy(face).T, name=type(x).__name__)
    if isinstance(x, tuple | list) and len(x) == 2:
        return Mesh(to_numpy(x[0]), to_numpy(x[1]))
    raise TypeError(
        f"expected a mesh: a torchheat.Mesh, a file path, an object with vertices and faces "
        f"arrays (e.g. trimesh.Trimesh), a PyTorch Geometric Data (pos, face) or a "
        f"(vertices, faces) pair; got {type(x).__name__}")


def _shared_positions(V: np.ndarray, labels: np.ndarray) -> int:
    """Number of vertex positions held by vertices of more than one label, positions within
    ``sqrt(DEGENERATE_REL_AREA)`` (1e-6) of the bounding-box diagonal counting as one (the
    tolerance of the duplicated-corner check: exporters that compute a seam's two copies
    separately leave them a few ulps apart): where connected components meet along a seam of
    duplicated vertices."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = V.shape[0]
    diag = float(np.linalg.norm(V.max(0) - V.min(0))) if n else 0.0
    pairs = cKDTree(V).query_pairs(math.sqrt(DEGENERATE_REL_AREA) * diag, output_type="ndarray")
    if not pairs.size:
        return 0
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, pos = connected_components(graph, directed=False)  # clusters of coincident vertices
    both = np.unique(np.stack([pos, labels.astype(np.int64)], axis=1), axis=0)
    return int((np.bincount(both[:, 0]) > 1).sum())


def load_mesh(
    path: str | os.PathLike[str],
    *,
    check: bool = True,
    largest_component: bool = False,
) -> Mesh:
    """Load a mesh from an OFF, OBJ, PLY (vertex order kept), STL, GLB or glTF file.

    Parameters
    ----------
    path : str or os.PathLike
        File to read; the format comes from the extension (``.off``, ``.obj``, ``.ply``,
        ``.stl``, ``.glb``, ``.gltf``, case-insensitive).
    check : bool, default True
        Validate the mesh (see :class:`Mesh`).
    largest_component : bool, default False
        Keep only the largest connected component; see :attr:`Mesh.vertex_map`.

    Returns
    -------
    Mesh
        With ``name`` set to ``str(path)``.

    Raises
    ------
    MeshError
        Missing, unreadable or unsupported file, no faces, malformed faces, or any
        validation failure listed in the module docstring.

    Warns
    -----
    MeshWarning
        Non-manifold edges.

    Notes
    -----
    Files are read by :func:`torchheat.meshio.read_arrays`: OFF, OBJ and PLY keep every
    vertex in file order (polygons are triangulated); STL, GLB and glTF have their
    exact-duplicate vertices merged, in order of first appearance.

    Examples
    --------
    >>> from importlib.resources import files
    >>> mesh = load_mesh(files("torchheat") / "data" / "spot.obj")
    >>> mesh.n_vertices, mesh.n_faces
    (2930, 5856)
    """
    V, F = read_arrays(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", MeshWarning)
        mesh = Mesh(V, F, name=str(path), check=check, largest_component=largest_component)
    for w in caught:  # re-emit so that warnings point at the caller of load_mesh
        warnings.warn(w.message, w.category, stacklevel=2)
    return mesh
