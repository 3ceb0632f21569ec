"""Mesh connectivity from face arrays, numpy and scipy only (no torch).

:class:`torchheat.mesh.Mesh` builds its edges, adjacency and connected components with these
functions; the command line calls :func:`largest_component` on the arrays it reads *before*
it imports torch, so that the eigensolves it starts in worker processes
(:class:`torchheat.eigen.EigenWorkers`) solve exactly the piece that ``Mesh(...,
largest_component=True)`` keeps.

Examples
--------
>>> import numpy as np
>>> F = np.array([[0, 1, 2], [3, 4, 5], [3, 5, 6]])  # a triangle and a quad, apart
>>> largest_component(F, 8).tolist()  # vertex 7 is unreferenced: a component of its own
[3, 4, 5, 6]
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

__all__ = ["edge_keys", "adjacency_from_keys", "components", "largest_component", "restrict_faces"]


def edge_keys(F: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges as keys ``i * n + j`` (``i < j``), sorted, with face counts.

    Self-loops (faces with a repeated vertex) are left out.

    Parameters
    ----------
    F : numpy.ndarray of int, shape (m, 3)
        Faces, indices in ``0 .. n - 1``.
    n : int
        Number of vertices.

    Returns
    -------
    keys : numpy.ndarray of int64, shape (e,)
    counts : numpy.ndarray of int64, shape (e,)
        Number of faces using each edge.

    Examples
    --------
    >>> keys, counts = edge_keys(np.array([[0, 1, 2], [1, 3, 2]]), 4)
    >>> keys.tolist(), counts.tolist()  # edge (1, 2) = 1 * 4 + 2 is shared
    ([1, 2, 6, 7, 11], [1, 1, 2, 1, 1])
    """
    a = F[:, [0, 1, 2]].ravel()
    b = F[:, [1, 2, 0]].ravel()
    lo = np.minimum(a, b)
    hi = np.maximum(a, b)
    keep = lo != hi
    keys = lo[keep].astype(np.int64) * np.int64(n) + hi[keep]
    keys, counts = np.unique(keys, return_counts=True)
    return keys, counts


def adjacency_from_keys(keys: np.ndarray, n: int) -> sp.csr_matrix:
    """Symmetric 0/1 adjacency matrix of the edges ``keys`` (see :func:`edge_keys`).

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, n)
        float64, zero diagonal.

    Examples
    --------
    >>> adjacency_from_keys(np.array([1]), 3).toarray().tolist()  # the edge (0, 1)
    [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    """
    i, j = np.divmod(keys, np.int64(n))
    rows = np.concatenate([i, j])
    cols = np.concatenate([j, i])
    data = np.ones(rows.size, dtype=np.float64)
    return sp.csr_matrix((data, (rows, cols)), shape=(n, n))


def components(keys: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """Connected components of the edge graph; an unreferenced vertex is one on its own.

    Returns
    -------
    count : int
    labels : numpy.ndarray of int, shape (n,)
        Component of every vertex, numbered in the order of their lowest vertex.

    Examples
    --------
    >>> components(np.array([1]), 3)[1].tolist()  # edge (0, 1) and the lone vertex 2
    [0, 0, 1]
    """
    count, labels = connected_components(adjacency_from_keys(keys, n), directed=False)
    return int(count), labels


def largest_component(F: np.ndarray, n: int, keys: np.ndarray | None = None
                      ) -> np.ndarray | None:
    """Vertices of the largest connected component, or None when there is one component.

    The largest component is the one with the most vertices; ties go to the component that
    holds the lowest vertex index. Unreferenced vertices are components of their own, so
    they are never kept (unless the mesh has no face at all).

    Parameters
    ----------
    F : numpy.ndarray of int, shape (m, 3)
        Faces, indices in ``0 .. n - 1`` (not checked).
    n : int
        Number of vertices.
    keys : numpy.ndarray, optional
        ``edge_keys(F, n)[0]`` if already computed.

    Returns
    -------
    numpy.ndarray of int64, shape (k,) or None
        Sorted indices of the kept vertices, or None when every vertex is in one component
        (nothing to drop).

    Examples
    --------
    >>> largest_component(np.array([[0, 1, 2], [2, 1, 3]]), 4) is None
    True
    >>> largest_component(np.array([[0, 1, 2], [3, 4, 5]]), 6).tolist()  # a tie: lowest wins
    [0, 1, 2]
    """
    count, labels = components(edge_keys(F, n)[0] if keys is None else keys, n)
    if count <= 1:
        return None
    sizes = np.bincount(labels, minlength=count)
    return np.flatnonzero(labels == int(np.argmax(sizes))).astype(np.int64)


def restrict_faces(F: np.ndarray, kept: np.ndarray, n: int) -> np.ndarray:
    """The faces of a vertex subset, renumbered to ``0 .. len(kept) - 1``.

    Parameters
    ----------
    F : numpy.ndarray of int, shape (m, 3)
    kept : numpy.ndarray of int, shape (k,)
        Sorted vertex indices, a union of connected components (a face is kept when its
        first corner is).
    n : int
        Number of vertices of ``F``.

    Returns
    -------
    numpy.ndarray of int64, shape (m', 3)

    Examples
    --------
    >>> restrict_faces(np.array([[0, 1, 2], [3, 4, 5]]), np.array([3, 4, 5]), 6).tolist()
    [[0, 1, 2]]
    """
    keep = np.zeros(n, dtype=bool)
    keep[kept] = True
    new_index = np.full(n, -1, dtype=np.int64)
    new_index[kept] = np.arange(kept.size)
    return np.ascontiguousarray(new_index[F[keep[F[:, 0]]]])
