"""Pairs: :class:`Pair` (two shapes and their ground truth), :class:`PairCollection` (pairs served
through one :class:`~torchheat.datasets.shapes.ShapeCollection`, so shared shapes share a cache
entry), :func:`pairs_from_list`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch.utils.data import Dataset

from .ground_truth import Barycentric, GroundTruth, IdentityGT
from .shapes import Shape, ShapeCollection


# --------------------------------------------------------------------------------------------
# pairs and ground truth
# --------------------------------------------------------------------------------------------
@dataclass
class Pair:
    """Two shapes and a ground-truth correspondence (0-based, source vertex -> target vertex).

    Attributes
    ----------
    source, target : Shape
    gt_src, gt_tgt : torch.LongTensor, shape (m,), or None
        ``gt_tgt[i]`` is the true match on ``target`` of vertex ``gt_src[i]`` of ``source``.
        The map may be partial and repeat source vertices (TOSCA ``.vts``); ``None`` when the
        collection has no ground truth.
    gt_sym_tgt : torch.LongTensor, shape (m,), or None
        True match of ``gt_src`` under the intrinsic left/right symmetry, when known.
    name : str
        ``"<source>-<target>"``.
    cls : str
        Class of the pair (``"<src cls>-<tgt cls>"`` for inter-class pairs).
    """

    source: Shape
    target: Shape
    gt_src: torch.Tensor | None
    gt_tgt: torch.Tensor | None
    gt_sym_tgt: torch.Tensor | None
    name: str
    cls: str
    gt_bary: Barycentric | None = None
    gt_sym_bary: Barycentric | None = None


class PairCollection(Dataset):
    """A dataset of shape pairs with ground truth; shapes come from one :class:`ShapeCollection`.

    Parameters
    ----------
    shapes : ShapeCollection
        Every shape any pair refers to (its cache is shared by all pairs).
    pairs : sequence of (int or str, int or str)
        (source, target) by index or name in ``shapes``.
    gt : callable, "identity" or None
        ``gt(source, target) -> (gt_src, gt_tgt, gt_sym_tgt)``, optionally followed by the
        barycentric ground truth ``(gt_bary, gt_sym_bary)`` (:class:`Barycentric`, with
        ``gt_tgt`` / ``gt_sym_tgt`` their nearest corners); must be picklable for
        multi-worker loading (:class:`IdentityGT`, :class:`VtsGT`, :class:`VtsSymmetryGT` or a
        module-level function). ``"identity"`` = :class:`IdentityGT`; ``None`` = no ground
        truth (the three fields are ``None``).

    Examples
    --------
    >>> pc = tosca_remeshed_5k()  # doctest: +SKIP
    >>> p = pc[0]  # doctest: +SKIP
    >>> p.name, p.gt_src.shape  # doctest: +SKIP
    ('cat0-cat1', torch.Size([5000]))
    """

    def __init__(
        self,
        shapes: ShapeCollection,
        pairs: Sequence[tuple[int | str, int | str]],
        gt: GroundTruth | str | None = "identity",
    ) -> None:
        self.shapes = shapes
        self.pairs = [(shapes.index(a), shapes.index(b)) for a, b in pairs]
        if gt == "identity":
            gt = IdentityGT()
        elif isinstance(gt, str):
            raise ValueError(f"unknown gt {gt!r}; use 'identity', None or a callable")
        self.gt = gt

    def __len__(self) -> int:
        return len(self.pairs)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({len(self)} pairs, gt={self.gt!r}, shapes={self.shapes!r})"

    @property
    def names(self) -> list[str]:
        """Pair names ``"<source>-<target>"``."""
        n = self.shapes.names
        return [f"{n[a]}-{n[b]}" for a, b in self.pairs]

    def __getitem__(self, i: int) -> Pair:
        if not -len(self) <= i < len(self):
            raise IndexError(f"pair index {i} out of range for {len(self)} pairs")
        a, b = self.pairs[i]
        src = self.shapes[a]
        tgt = src if b == a else self.shapes[b]
        bary: tuple[Barycentric | None, Barycentric | None] = (None, None)
        if self.gt is None:
            gs, gtg, gsym = None, None, None
        else:
            gs, gtg, gsym, *extra = self.gt(src, tgt)
            if extra:  # barycentric ground truth (direct, symmetric)
                bary = (extra[0], extra[1] if len(extra) > 1 else None)
        cls = src.cls if src.cls == tgt.cls else f"{src.cls}-{tgt.cls}"
        return Pair(src, tgt, gs, gtg, gsym, f"{src.name}-{tgt.name}", cls, *bary)


def pairs_from_list(
    shapes: ShapeCollection,
    pairs: Sequence[tuple[int | str, int | str]],
    gt: GroundTruth | str | None = "identity",
) -> PairCollection:
    """Pairs of an existing :class:`ShapeCollection`, by name or index.

    Examples
    --------
    >>> shapes = folder("meshes/")  # doctest: +SKIP
    >>> pc = pairs_from_list(shapes, [("rest", "smile")], gt="identity")  # doctest: +SKIP
    """
    return PairCollection(shapes, pairs, gt=gt)
