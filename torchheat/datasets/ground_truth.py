"""Ground-truth readers of the benchmarks: identity, ``.vts`` files (direct and symmetric), and
SHREC'16's barycentric points on the full shape; all indices 0-based, checked against the
meshes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from .cache import PathLike
from .shapes import Shape


@dataclass(frozen=True)
class Barycentric:
    """Points on a mesh's triangles, as three corner vertices and barycentric weights.

    Attributes
    ----------
    corners : torch.LongTensor, shape (m, 3)
        0-based vertex indices of the triangle of each point, in the order the face lists them.
    weights : torch.DoubleTensor, shape (m, 3)
        Non-negative barycentric weights summing to 1: point ``i`` is
        ``sum_j weights[i, j] * V[corners[i, j]]``.

    Examples
    --------
    >>> b = Barycentric(torch.tensor([[0, 1, 2]]), torch.tensor([[0.2, 0.7, 0.1]],
    ...                 dtype=torch.float64))
    >>> b.nearest_corner().tolist()  # the corner of largest weight
    [1]
    """

    corners: torch.Tensor
    weights: torch.Tensor

    def nearest_corner(self) -> torch.Tensor:
        """The corner of largest weight of every point (the field's ``.vts`` convention)."""
        j = torch.argmax(self.weights, dim=1, keepdim=True)
        return torch.gather(self.corners, 1, j).squeeze(1)

    def __len__(self) -> int:
        return int(self.corners.shape[0])


#: What a ground truth returns: ``(gt_src, gt_tgt, gt_sym_tgt)``, optionally followed by the
#: barycentric points ``(gt_bary, gt_sym_bary)`` (:class:`BarycentricGT`)
GTResult = (tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]
            | tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None,
                    Barycentric, Barycentric | None])


def _check_range(idx: np.ndarray, n: int, what: str) -> torch.Tensor:
    idx = np.asarray(idx, dtype=np.int64).ravel()
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(
            f"ground truth {what} has indices in [{idx.min()}, {idx.max()}], "
            f"outside [0, {n}) — wrong index base or vertex order?"
        )
    return torch.from_numpy(idx)


class IdentityGT:
    """Ground truth of meshes sharing their vertex order: vertex i -> vertex i.

    Examples
    --------
    >>> gt = IdentityGT()  # used by scape(), tosca_hires(), kids()
    """

    def __call__(self, source: Shape, target: Shape) -> GTResult:
        n, m = source.n_vertices, target.n_vertices
        if n != m:
            raise ValueError(
                f"identity ground truth needs equal vertex counts: {source.name} has {n}, "
                f"{target.name} has {m}"
            )
        idx = torch.arange(n, dtype=torch.int64)
        return idx, idx.clone(), None

    def __repr__(self) -> str:
        return "IdentityGT()"


def _read_vts(path: Path) -> np.ndarray:
    """A 1-based ``.vts`` point list as 0-based int64."""
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth file not found: {path}")
    idx = np.loadtxt(path, dtype=np.int64, ndmin=1)
    if idx.size == 0 or idx.min() < 1:
        raise ValueError(f"{path}: expected 1-based vertex indices (min >= 1)")
    return idx - 1


@dataclass(frozen=True)
class VtsGT:
    """TOSCA/BCICP ``.vts`` ground truth: ``A.vts[k]-1 -> B.vts[k]-1``.

    The symmetric map is ``A.vts[k]-1 -> B.sym.vts[k]-1`` (``None`` if ``B.sym.vts`` is
    missing).

    Parameters
    ----------
    corres_dir : pathlib.Path
        Folder holding ``<name>.vts`` and ``<name>.sym.vts``.
    """

    corres_dir: Path

    def __call__(self, source: Shape, target: Shape) -> GTResult:
        d = Path(self.corres_dir)
        a = _read_vts(d / f"{source.name}.vts")
        b = _read_vts(d / f"{target.name}.vts")
        if a.size != b.size:
            raise ValueError(f"{source.name}.vts and {target.name}.vts differ in length")
        sym_path = d / f"{target.name}.sym.vts"
        bs = _read_vts(sym_path) if sym_path.is_file() else None
        return (
            _check_range(a, source.n_vertices, f"{source.name}.vts"),
            _check_range(b, target.n_vertices, f"{target.name}.vts"),
            None if bs is None else _check_range(bs, target.n_vertices, sym_path.name),
        )


@dataclass(frozen=True)
class VtsSymmetryGT:
    """Self-symmetry ground truth from ``.vts`` files: ``A.vts[k]-1 -> A.sym.vts[k]-1``.

    Used with pairs whose source and target are the same shape; ``gt_sym_tgt`` is ``None``.
    """

    corres_dir: Path

    def __call__(self, source: Shape, target: Shape) -> GTResult:
        d = Path(self.corres_dir)
        a = _read_vts(d / f"{source.name}.vts")
        s = _read_vts(d / f"{target.name}.sym.vts")
        if a.size != s.size:
            raise ValueError(f"{source.name}.vts and {target.name}.sym.vts differ in length")
        return (
            _check_range(a, source.n_vertices, f"{source.name}.vts"),
            _check_range(s, target.n_vertices, f"{target.name}.sym.vts"),
            None,
        )


def read_barycentric(path: PathLike, n_faces: int, faces: np.ndarray) -> Barycentric:
    """Read a SHREC'16 ``.baryc_gt`` file: one line per point, ``tri w1 w2 w3`` with a
    **1-based** triangle index into ``faces`` (``n_faces`` rows) and weights on its corners.

    Raises
    ------
    FileNotFoundError, ValueError
        Missing file; wrong column count, triangle index out of ``[1, n_faces]``, negative
        weights or weights not summing to 1 (within 1e-3), non-finite values — naming the file.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"ground-truth file not found: {p}")
    a = np.loadtxt(p, dtype=np.float64, ndmin=2)
    if a.shape[1] != 4:
        raise ValueError(f"{p}: expected 4 columns (tri w1 w2 w3), got {a.shape[1]}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{p}: non-finite values")
    tri = a[:, 0].round().astype(np.int64)
    if tri.min() < 1 or tri.max() > n_faces:
        raise ValueError(f"{p}: triangle indices in [{tri.min()}, {tri.max()}], outside "
                         f"[1, {n_faces}] (1-based) of the full shape")
    w = a[:, 1:]
    if (w < -1e-6).any() or np.abs(w.sum(1) - 1).max() > 1e-3:
        raise ValueError(f"{p}: barycentric weights must be >= 0 and sum to 1")
    w = np.clip(w, 0.0, None)
    w /= w.sum(1, keepdims=True)
    return Barycentric(torch.from_numpy(np.ascontiguousarray(faces[tri - 1], dtype=np.int64)),
                       torch.from_numpy(w))


@dataclass(frozen=True)
class BarycentricGT:
    """SHREC'16 partial ground truth: vertex ``i`` of the partial source lies at a barycentric
    point of the full target (``<source>.baryc_gt``, and ``<source>.baryc_gt_sym`` for the
    left/right symmetric correspondence).

    Returns ``(gt_src, gt_tgt, gt_sym_tgt, gt_bary, gt_sym_bary)``: every source vertex, the
    nearest corners (largest weight) of the direct and symmetric points, and the
    :class:`Barycentric` points themselves.

    Parameters
    ----------
    folder : pathlib.Path
        Folder of the partial shapes and their ``.baryc_gt`` files.
    """

    folder: Path

    def __call__(self, source: Shape, target: Shape) -> GTResult:
        _, F = target.mesh.numpy()
        d = Path(self.folder)
        b = read_barycentric(d / f"{source.name}.baryc_gt", len(F), F)
        sym_path = d / f"{source.name}.baryc_gt_sym"
        bs = read_barycentric(sym_path, len(F), F) if sym_path.is_file() else None
        n = source.n_vertices
        for name, x in (("baryc_gt", b), ("baryc_gt_sym", bs)):
            if x is not None and len(x) != n:
                raise ValueError(f"{source.name}.{name} has {len(x)} rows but {source.name} "
                                 f"has {n} vertices")
        return (torch.arange(n, dtype=torch.int64), b.nearest_corner(),
                None if bs is None else bs.nearest_corner(), b, bs)


GroundTruth = Callable[[Shape, Shape], GTResult]
