"""Heat-kernel descriptors: the Heat Kernel Map, the Heat Kernel Signature, feature points.

* **Heat Kernel Map** (paper eq. 2) of a landmark ``p``: ``Phi_p(x) = (t_j k_{t_j}(p, x))_j``.
  Several landmarks are concatenated (the paper's "correspondence augmentation").
* **HKS augmentation**: ``(t_j k_{t_j}(x, x))_j``, the same t-scaling, appended to the map.
* **Feature points**: local maxima of the HKS at a large time over the 2-ring neighbourhood.

All functions take a :class:`torchheat.HeatKernel` (one per shape) so that the expensive
operators are computed once.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp
import torch

from ._arrays import to_numpy
from .heat import HeatKernel
from .mesh import Mesh

__all__ = [
    "heat_kernel_map",
    "hks",
    "feature_points",
    "ring_neighbors",
    "farthest_point_sampling",
]


def heat_kernel_map(
    hk: HeatKernel,
    landmarks: Sequence[int] | torch.Tensor,
    columns: torch.Tensor | None = None,
    time_index: Sequence[int] | slice | None = None,
    dtype: torch.dtype | None = None,
) -> torch.Tensor:
    """Heat Kernel Map ``Phi(x) = (t_j k_{t_j}(p_l, x))_{l, j}`` of one or more landmarks.

    Parameters
    ----------
    hk : HeatKernel
        Solver of the shape (n vertices, J times).
    landmarks : sequence of int, shape (L,)
        Landmark vertices ``p_l``.
    columns : torch.Tensor, optional
        Precomputed ``hk.columns(landmarks)``, shape (L, n, J).
    time_index : sequence of int or slice, optional
        Use only these of the J times.
    dtype : torch.dtype, optional
        Compute in this precision where the eigenbasis serves every time (default: the
        solver's); e.g. float32 for nearest-neighbour searches that run in float32 anyway.

    Returns
    -------
    torch.Tensor
        Shape (n, L * J'), landmark-major (``[:, l*J':(l+1)*J']`` is landmark ``l``).

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import HeatKernel, Mesh
    >>> s = trimesh.creation.icosphere(2)
    >>> heat_kernel_map(HeatKernel(Mesh(s.vertices, s.faces)), [0, 1]).shape
    torch.Size([162, 20])
    """
    if columns is None:
        fast = hk.spectral_map(landmarks, time_index, dtype=dtype)
        if fast is not None:
            return fast
    C = hk.columns(landmarks, certify=False) if columns is None else columns
    t = hk.times.to(C.dtype).to(C.device)
    if time_index is not None:
        C, t = C[:, :, time_index], t[time_index]
    L, n, J = C.shape
    return (C * t).permute(1, 0, 2).reshape(n, L * J)


def hks(hk: HeatKernel, scaled: bool = True) -> torch.Tensor:
    """Heat Kernel Signature ``k_t(x, x)``, optionally t-scaled like the Heat Kernel Map.

    Parameters
    ----------
    hk : HeatKernel
    scaled : bool
        Multiply by ``t_j`` (default), so that HKS coordinates have the HKM's scale.

    Returns
    -------
    torch.Tensor
        float64, shape (n, J). Truncated spectrum: see :meth:`HeatKernel.hks`.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import HeatKernel, Mesh
    >>> s = trimesh.creation.icosphere(2)
    >>> hks(HeatKernel(Mesh(s.vertices, s.faces))).shape
    torch.Size([162, 10])
    """
    h = hk.hks()
    return h * hk.times if scaled else h


def ring_neighbors(mesh: Mesh, rings: int = 2) -> sp.csr_matrix:
    """Boolean adjacency of the k-ring neighbourhood (without the vertex itself).

    Parameters
    ----------
    mesh : Mesh
    rings : int

    Returns
    -------
    scipy.sparse.csr_matrix, shape (n, n)

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> s = trimesh.creation.icosphere(1)
    >>> int(ring_neighbors(Mesh(s.vertices, s.faces), 1)[0].sum())
    5
    """
    A = sp.csr_matrix(mesh.adjacency(), dtype=np.float64)
    A.data[:] = 1.0
    R = A.copy()
    P = A.copy()
    for _ in range(rings - 1):
        P = (P @ A).tocsr()
        P.data[:] = 1.0
        R = (R + P).tocsr()
    R.setdiag(0)
    R.eliminate_zeros()
    R.data[:] = 1.0
    return R.tocsr()


def feature_points(
    mesh: Mesh,
    signature: torch.Tensor | np.ndarray,
    rings: int = 2,
    max_features: int | None = 50,
) -> torch.Tensor:
    """Local maxima of a per-vertex signature over the k-ring, strongest first.

    Parameters
    ----------
    mesh : Mesh
        n vertices.
    signature : array_like, shape (n,)
        Typically the HKS at a large time.
    rings : int
        Neighbourhood size (the paper: 2-ring).
    max_features : int or None
        Keep at most this many (default 50), by decreasing signature; None keeps all.

    Returns
    -------
    torch.Tensor
        int64 vertex indices, shape (f,), ordered by decreasing signature. A vertex is a
        maximum when its value is >= every value in its k-ring (ties: the lowest index wins).

    Examples
    --------
    >>> import numpy as np, trimesh
    >>> from torchheat import Mesh
    >>> s = trimesh.creation.icosphere(2)
    >>> m = Mesh(s.vertices, s.faces)
    >>> int(feature_points(m, s.vertices[:, 2])[0]) == int(np.argmax(s.vertices[:, 2]))
    True
    """
    h = to_numpy(signature, dtype=np.float64).reshape(-1)
    if h.size != mesh.n_vertices:
        raise ValueError(f"signature has {h.size} values for a mesh of {mesh.n_vertices} vertices")
    R = ring_neighbors(mesh, rings).tocoo()
    # a vertex loses if a neighbour is larger, or equal with a lower index
    beats = (h[R.col] > h[R.row]) | ((h[R.col] == h[R.row]) & (R.col < R.row))
    loser = np.zeros(h.size, dtype=bool)
    loser[R.row[beats]] = True
    idx = np.flatnonzero(~loser)
    idx = idx[np.argsort(-h[idx], kind="stable")]
    if max_features is not None:
        idx = idx[:max_features]
    return torch.from_numpy(idx.astype(np.int64))


def farthest_point_sampling(
    points: torch.Tensor | np.ndarray, k: int, start: int | None = None
) -> torch.Tensor:
    """Greedy farthest-point order of a point set (Euclidean), deterministic.

    Parameters
    ----------
    points : array_like, shape (n, d)
        Positions or descriptors.
    k : int
        Number of samples (clipped to n).
    start : int, optional
        First sample (default: the point farthest from the centroid).

    Returns
    -------
    torch.Tensor
        int64 indices, shape (k,).

    Examples
    --------
    >>> import numpy as np
    >>> farthest_point_sampling(np.array([[0.0], [1.0], [10.0]]), 2).tolist()
    [2, 0]
    """
    X = to_numpy(points, dtype=np.float64)
    n = X.shape[0]
    k = min(int(k), n)
    if start is None:
        start = int(np.argmax(((X - X.mean(axis=0)) ** 2).sum(axis=1)))
    out = np.empty(k, dtype=np.int64)
    out[0] = start
    cols = [np.ascontiguousarray(X[:, j]) for j in range(X.shape[1])]

    def sq(i: int) -> np.ndarray:
        r = (cols[0] - cols[0][i]) ** 2
        for c in cols[1:]:
            r += (c - c[i]) ** 2
        return r

    d = sq(start)
    for i in range(1, k):
        out[i] = int(np.argmax(d))
        np.minimum(d, sq(int(out[i])), out=d)
    return torch.from_numpy(out)
