"""Laplace–Beltrami operators of triangle meshes, as torch sparse tensors.

Conventions (those of the paper and of libigl / geometry-central):

* The **stiffness** matrix ``W`` is positive semidefinite: ``W[i, i] = -sum_j W[i, j]`` and, for
  the cotangent operator, ``W[i, j] = -(cot a_ij + cot b_ij) / 2`` for an edge ``(i, j)`` with
  opposite angles ``a_ij, b_ij``. Cotangents use unsigned triangle areas, so inconsistently
  oriented faces (common in real TOSCA files) do not change the operator.
* The **mass** ``A`` is the lumped (barycentric) mass, a third of the area of every incident
  triangle per vertex, unless ``kind="fem"`` (consistent linear-FEM mass).
* The Laplace–Beltrami operator is ``L = A^-1 W`` and its symmetric form, used by the heat
  kernel, is ``S = A^-1/2 W A^-1/2`` (same spectrum as ``L``).
* ``normalize=True`` (default) rescales the mass to a **unit total area**, which is the paper's
  convention; every time ``t`` of :mod:`torchheat.heat` refers to that scale. Stiffness is scale
  invariant in 2-D, so this is exactly the operator of the mesh scaled to area 1.
* Boundary conditions: ``"neumann"`` (natural, default) keeps all vertices; ``"dirichlet"``
  (zero on the boundary) keeps only the interior vertices in the reduced operators.

Data flows ``mesh.py -> operators.py -> heat/``.
"""

from __future__ import annotations

import contextlib
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.sparse as sp
import torch

from ._arrays import to_numpy
from .eigen import cotmatrix_scipy as _cotmatrix_scipy
from .eigen import massmatrix_scipy as _massmatrix_scipy
from .mesh import Mesh, MeshError

Kind = Literal["cotan", "fem", "robust"]
Boundary = Literal["neumann", "dirichlet"]

__all__ = [
    "Laplacian",
    "cotmatrix",
    "cotmatrix_intrinsic",
    "massmatrix",
    "laplacian",
    "scipy_to_torch",
    "quiet_sparse_construction",
]


@contextlib.contextmanager
def quiet_sparse_construction() -> Iterator[None]:
    """Silence torch's "Sparse CSR tensor support is in beta" warning, nothing else.

    Wrap every construction of a torch sparse tensor in torchheat
    (``torch.sparse_csr_tensor`` / ``sparse_coo_tensor``) with it: torch emits that
    ``UserWarning`` once per process (so once per ``DataLoader`` worker too), about its own
    API, not about anything a user of torchheat can act on. The other construction warning,
    "Sparse invariant checks are implicitly disabled", is avoided at its source by passing
    ``check_invariants=False`` explicitly. Only this one message is filtered, and only inside
    the block: other warnings, torchheat's own :class:`~torchheat.MeshWarning` included, pass
    through. (``warnings.catch_warnings`` swaps the process-wide filter list for the duration
    of the block, as every local filter in Python before 3.14 does.)

    Examples
    --------
    >>> import warnings, torch
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     with quiet_sparse_construction():
    ...         A = torch.sparse_csr_tensor(torch.tensor([0, 1]), torch.tensor([0]),
    ...                                     torch.tensor([2.0]), size=(1, 1),
    ...                                     check_invariants=False)
    >>> [str(w.message) for w in caught if "parse" in str(w.message)]
    []
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"Sparse CSR tensor support is in beta",
                                category=UserWarning)
        yield


def _arrays(V, F) -> tuple[np.ndarray, np.ndarray]:
    V, F = to_numpy(V), to_numpy(F)
    return np.ascontiguousarray(V, dtype=np.float64), np.ascontiguousarray(F, dtype=np.int64)


def cotmatrix_intrinsic(lengths, F) -> torch.Tensor:
    """Cotangent stiffness from edge lengths alone (intrinsic geometry).

    Useful for meshes given by a metric rather than an embedding (e.g. a flat torus).

    Parameters
    ----------
    lengths : array_like, shape (m, 3)
        ``lengths[f, k]`` is the length of the edge of face ``f`` opposite corner ``k``.
    F : array_like, shape (m, 3)

    Returns
    -------
    torch.Tensor
        Sparse CSR float64, shape (n, n) with ``n = F.max() + 1``.

    Examples
    --------
    >>> import numpy as np
    >>> W = cotmatrix_intrinsic(np.array([[1.0, 1.0, 2**0.5]]), np.array([[0, 1, 2]]))
    >>> round(float(W.to_dense()[0, 2]), 6)  # 45-degree angle opposite edge (0, 2)
    -0.5
    """
    l_ = np.asarray(lengths, dtype=np.float64)
    F = np.asarray(F, dtype=np.int64)
    n = int(F.max()) + 1
    s = 0.5 * l_.sum(axis=1)
    area = np.sqrt(np.maximum(s * (s - l_[:, 0]) * (s - l_[:, 1]) * (s - l_[:, 2]), 0.0))
    rows, cols, vals = [], [], []
    for k in range(3):
        i, j = F[:, (k + 1) % 3], F[:, (k + 2) % 3]
        a, b, c = l_[:, k], l_[:, (k + 1) % 3], l_[:, (k + 2) % 3]
        cot = (b**2 + c**2 - a**2) / (4.0 * np.maximum(area, 1e-300))
        rows += [i, j]
        cols += [j, i]
        vals += [-0.5 * cot, -0.5 * cot]
    W = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)
    )
    W = (W - sp.diags(np.asarray(W.sum(axis=1)).ravel())).tocsr()
    return scipy_to_torch(W)


def scipy_to_torch(M: sp.spmatrix, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Convert a scipy sparse matrix to a torch sparse CSR tensor.

    Parameters
    ----------
    M : scipy.sparse matrix, shape (n, m)
    dtype : torch.dtype

    Returns
    -------
    torch.Tensor
        Sparse CSR tensor of shape (n, m).

    Examples
    --------
    >>> import scipy.sparse as sp
    >>> scipy_to_torch(sp.eye(3)).layout
    torch.sparse_csr
    """
    M = sp.csr_matrix(M)
    M.sort_indices()
    with quiet_sparse_construction():
        return torch.sparse_csr_tensor(
            torch.from_numpy(M.indptr.astype(np.int64)),
            torch.from_numpy(M.indices.astype(np.int64)),
            torch.from_numpy(M.data.astype(np.float64)).to(dtype),
            size=M.shape,
            check_invariants=False,  # scipy's sorted CSR; explicit: torch warns otherwise
        )


def cotmatrix(V, F) -> torch.Tensor:
    """Cotangent stiffness matrix ``W`` (positive semidefinite).

    Parameters
    ----------
    V : array_like, shape (n, 3)
        Vertex positions.
    F : array_like, shape (m, 3)
        Triangle vertex indices.

    Returns
    -------
    torch.Tensor
        Sparse CSR float64 tensor of shape (n, n); rows sum to zero.

    Examples
    --------
    >>> import trimesh
    >>> ico = trimesh.creation.icosahedron()
    >>> W = cotmatrix(ico.vertices, ico.faces)
    >>> W.shape
    torch.Size([12, 12])
    """
    return scipy_to_torch(_cotmatrix_scipy(*_arrays(V, F)))


def massmatrix(V, F, kind: Literal["lumped", "consistent"] = "lumped") -> torch.Tensor:
    """Mass matrix of linear finite elements.

    Parameters
    ----------
    V : array_like, shape (n, 3)
    F : array_like, shape (m, 3)
    kind : {"lumped", "consistent"}
        ``"lumped"``: diagonal, a third of each incident triangle's area (barycentric).
        ``"consistent"``: full linear-FEM mass (``area/6`` diagonal, ``area/12`` off-diagonal).

    Returns
    -------
    torch.Tensor
        Sparse CSR float64 tensor of shape (n, n); entries sum to the total area.

    Examples
    --------
    >>> import trimesh
    >>> ico = trimesh.creation.icosahedron()
    >>> float(massmatrix(ico.vertices, ico.faces).to_dense().sum()) > 0
    True
    """
    return scipy_to_torch(_massmatrix_scipy(*_arrays(V, F), kind))


@dataclass(frozen=True)
class Laplacian:
    """A discrete Laplace–Beltrami operator ``L = A^-1 W`` with its boundary condition.

    Attributes
    ----------
    stiffness_scipy : scipy.sparse.csr_matrix, shape (n, n)
        Positive semidefinite stiffness ``W`` over all vertices (``.W`` is the torch form).
    mass_scipy : scipy.sparse.csr_matrix, shape (n, n)
        Mass ``A`` (diagonal when lumped), scaled to unit total area if ``normalized``
        (``.M`` is the torch form, ``.mass`` its diagonal).
    kind : str
        ``"cotan"``, ``"fem"`` or ``"robust"``.
    boundary : str
        ``"neumann"`` or ``"dirichlet"``.
    active : numpy.ndarray of bool, shape (n,)
        Vertices carried by the reduced operator: all for Neumann, the interior for Dirichlet.
    area : float
        Total surface area of the input mesh (before normalisation).
    normalized : bool
        Whether the mass was divided by ``area``.
    """

    stiffness_scipy: sp.csr_matrix
    mass_scipy: sp.csr_matrix
    kind: str
    boundary: str
    active: np.ndarray
    area: float
    normalized: bool

    @property
    def n_vertices(self) -> int:
        """Number of vertices of the mesh (not of the reduced system)."""
        return int(self.stiffness_scipy.shape[0])

    @property
    def lumped(self) -> bool:
        """Whether the mass is diagonal (needed by the Chebyshev heat path)."""
        return self.kind != "fem"

    def reduced(self) -> tuple[sp.csr_matrix, sp.csr_matrix]:
        """``(W, A)`` restricted to the active vertices (the boundary condition applied).

        Returns
        -------
        W, A : scipy.sparse.csr_matrix, shape (k, k)
            ``k = active.sum()``.
        """
        idx = np.flatnonzero(self.active)
        if idx.size == self.n_vertices:
            return self.stiffness_scipy, self.mass_scipy
        return (
            self.stiffness_scipy[idx][:, idx].tocsr(),
            self.mass_scipy[idx][:, idx].tocsr(),
        )

    def mass_diagonal(self) -> np.ndarray:
        """Diagonal of the reduced lumped mass, shape (k,).

        Raises
        ------
        ValueError
            For the consistent (``kind="fem"``) mass, which is not diagonal.
        """
        if not self.lumped:
            raise ValueError("kind='fem' has a consistent (non-diagonal) mass")
        return self.reduced()[1].diagonal().copy()

    def symmetric_scipy(self) -> sp.csr_matrix:
        """Symmetric form ``S = A^-1/2 W A^-1/2`` on the active vertices (lumped mass only)."""
        W, _ = self.reduced()
        d = 1.0 / np.sqrt(self.mass_diagonal())
        S = sp.diags(d) @ W @ sp.diags(d)
        S = 0.5 * (S + S.T)
        return S.tocsr()

    def symmetric(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """Symmetric form ``S = A^-1/2 W A^-1/2`` as a torch sparse CSR tensor, shape (k, k).

        Examples
        --------
        >>> import trimesh
        >>> from torchheat import Mesh
        >>> ico = trimesh.creation.icosahedron()
        >>> laplacian(Mesh(ico.vertices, ico.faces)).symmetric().shape
        torch.Size([12, 12])
        """
        return scipy_to_torch(self.symmetric_scipy(), dtype)

    @property
    def W(self) -> torch.Tensor:
        """Stiffness ``W`` (all vertices) as a torch sparse CSR float64 tensor, shape (n, n)."""
        return scipy_to_torch(self.stiffness_scipy)

    @property
    def M(self) -> torch.Tensor:
        """Mass ``A`` (all vertices) as a torch sparse CSR float64 tensor, shape (n, n)."""
        return scipy_to_torch(self.mass_scipy)

    @property
    def mass(self) -> torch.Tensor:
        """Lumped mass per vertex (row sums of ``A``), float64 tensor of shape (n,)."""
        return torch.from_numpy(np.asarray(self.mass_scipy.sum(axis=1)).ravel())

    @property
    def S(self) -> torch.Tensor:
        """Symmetric form ``A^-1/2 W A^-1/2`` on the active vertices, torch sparse CSR."""
        return self.symmetric()


def _robust(V: np.ndarray, F: np.ndarray) -> tuple[sp.csr_matrix, sp.csr_matrix]:
    try:
        import robust_laplacian
    except ImportError as exc:  # pragma: no cover - dependency is declared
        raise ImportError(
            "kind='robust' needs the robust-laplacian package: pip install robust-laplacian"
        ) from exc
    W, M = robust_laplacian.mesh_laplacian(V, F)
    return sp.csr_matrix(W), sp.csr_matrix(M)


def check_kind(kind: str, boundary: str) -> None:
    """Refuse an unknown Laplacian ``kind`` or ``boundary`` condition (``ValueError``).

    Examples
    --------
    >>> check_kind("cotan", "dirichlet")
    >>> check_kind("cot", "neumann")
    Traceback (most recent call last):
    ...
    ValueError: unknown Laplacian kind 'cot'; use 'cotan', 'fem' or 'robust'
    """
    if kind not in ("cotan", "fem", "robust"):
        raise ValueError(f"unknown Laplacian kind {kind!r}; use 'cotan', 'fem' or 'robust'")
    if boundary not in ("neumann", "dirichlet"):
        raise ValueError(f"unknown boundary condition {boundary!r}; use 'neumann' or 'dirichlet'")


def laplacian(
    mesh: Mesh,
    kind: Kind = "cotan",
    boundary: Boundary = "neumann",
    normalize: bool = True,
) -> Laplacian:
    """Laplace–Beltrami operator of a triangle mesh.

    Parameters
    ----------
    mesh : Mesh
        Triangle mesh with n vertices.
    kind : {"cotan", "fem", "robust"}
        ``"cotan"`` (default): cotangent stiffness with lumped mass, as in the paper.
        ``"fem"``: cotangent stiffness with the consistent linear-FEM mass (more accurate
        eigenpairs; only the eigenbasis heat path supports it).
        ``"robust"``: intrinsic-Delaunay Laplacian of Sharp & Crane 2020 (robust-laplacian
        package) with lumped mass; handles poor triangles and non-manifold input.
    boundary : {"neumann", "dirichlet"}
        Boundary condition for meshes with boundary (ignored when there is none).
    normalize : bool
        Scale the mass to unit total area (default, the paper's convention).

    Returns
    -------
    Laplacian
        ``.W`` (stiffness) and ``.M`` (mass) as torch sparse CSR tensors, ``.mass`` the
        per-vertex mass, ``.S`` the symmetric form; scipy copies in ``.stiffness_scipy`` and
        ``.mass_scipy``.

    Raises
    ------
    ValueError
        Unknown ``kind`` or ``boundary``, or Dirichlet on a mesh whose vertices are all on the
        boundary.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> ico = trimesh.creation.icosahedron()
    >>> L = laplacian(Mesh(ico.vertices, ico.faces))
    >>> round(float(L.mass.sum()), 12)
    1.0
    """
    check_kind(kind, boundary)
    V, F = mesh.numpy()
    if kind == "robust":
        W, M = _robust(V, F)
    else:
        W = _cotmatrix_scipy(V, F)
        M = _massmatrix_scipy(V, F, "consistent" if kind == "fem" else "lumped")
    area = float(M.sum())
    if normalize:
        M = (M / area).tocsr()
    n = V.shape[0]
    active = np.ones(n, dtype=bool)
    if boundary == "dirichlet":
        active[mesh.boundary_vertices().numpy()] = False
        if not active.any():
            raise MeshError(
                f"{mesh.name or 'mesh'}: every vertex lies on the boundary; "
                "Dirichlet conditions leave nothing to solve (use boundary='neumann')"
            )
    if kind != "fem" and (M.diagonal() <= 0).any():
        bad = np.flatnonzero(M.diagonal() <= 0)[:5].tolist()
        raise MeshError(
            f"{mesh.name or 'mesh'}: vertices {bad} have zero mass (isolated or degenerate); "
            "clean the mesh"
        )
    return Laplacian(W.tocsr(), M.tocsr(), kind, boundary, active, area, normalize)
