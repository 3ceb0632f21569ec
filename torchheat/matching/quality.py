"""A map's own evidence of being right: is it close to an isometry, and does it keep the
orientation?

Two readings of a dense map ``T: M -> N`` that need no ground truth:

* **Isometry**: the functional map ``C`` of ``T`` in the first ``k = 30`` eigenfunctions
  (:func:`~torchheat.matching.zoomout.functional_map` on 1000 farthest-point samples) is
  orthogonal for an area-preserving isometry (Ovsjanikov et al. 2012, Thm. 5.1). Its defect
  ``|C^T C - I|_F / sqrt(k)`` is ~0.1-0.3 for correct maps of near-isometric poses and of
  their mirror maps, and grows towards 1 for maps that fold, collapse or tear (a wrong
  landmark, shapes that are not near-isometric).
* **Orientation**: a direct map keeps the surface orientation (+1), the intrinsic-symmetric
  (mirror) map reverses it (-1) (:func:`~torchheat.matching.orientation.orientation_score`).

A third reading comes from the choice itself, where the map was chosen among ZoomOut
candidates (:mod:`.select`): the **margin**, how much worse the best candidate that is a
different whole map scored (its images of the samples disagree with the chosen one's on more
than half of them, beyond 0.1 sqrt(area)). The wrong maps left on TOSCA and SCAPE are
near-isometries (half-turns, whole-body swaps) that the defect and the orientation cannot tell
from the right map; what gives them away is a rival of almost the same score. ``ambiguous``
when the margin is below 0.15 (TOSCA 284 + SCAPE 50 pairs: 3 of the 5 maps under 50 % right,
7 of the 323 maps over 90 %; ROC AUC of the margin 0.955; RESULTS.md, eleventh session).
``suspect`` does not use it.

``quality = exp(-(defect / 0.35)^2) * (1 + orientation) / 2`` in [0, 1] (``1 - orientation``
for a symmetry); ``suspect`` when it is below 0.25. The scale and threshold were set on 8
TOSCA pairs (one per class): correct maps read 0.63-0.86, their mirror maps 0.05-0.21, maps
from a wrong landmark and maps between classes 0.00-0.21. Maps of ``method="paper"`` are
rough (not refined): their defect reads 0.35-0.8 even when mostly right, so they read suspect
more often than they are wrong. Cost: one ``1000 x 30`` least-squares solve and the orientation
test (~10 ms).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .orientation import orientation_score
from .partial import partial_functional_map, sample_areas
from .prepared import PreparedShape, _fps
from .zoomout import functional_map

__all__ = ["MapQuality", "map_quality"]

QUALITY_K = 30  # eigenfunctions of the functional map whose orthogonality is read
# A piece of area r has about r k eigenvalues below the whole's k-th (Weyl's law); its modes
# are read a margin below that, where the whole's first k functions still span them.
PARTIAL_MODES = 0.8
DEFECT_SCALE = 0.35  # defect at which the isometry factor is 1/e
SUSPECT_BELOW = 0.25  # quality under which a map is reported suspect
AMBIGUOUS_BELOW = 0.15  # score margin under which a chosen map is reported ambiguous


@dataclass(frozen=True)
class MapQuality:
    """Evidence that a map is right (see the module docstring).

    Attributes
    ----------
    defect : float
        ``|C^T C - I|_F / sqrt(k)`` of the map's functional map (0: an isometry).
    orientation : float
        Orientation score in [-1, 1] (+1 preserving), NaN if not measured.
    quality : float
        In [0, 1], higher is better.
    suspect : bool
        ``quality < 0.25``.
    margin : float or None
        Score margin of the choice (see the module docstring; None where the map was not
        chosen among ZoomOut candidates, or no rival was a different map).
    ambiguous : bool
        ``margin < 0.15``: a different whole map scored nearly as well.
    """

    defect: float
    orientation: float
    quality: float
    suspect: bool
    margin: float | None = None
    ambiguous: bool = False

    def as_dict(self) -> dict:
        return {"quality": self.quality, "suspect": self.suspect, "defect": self.defect,
                "orientation": None if math.isnan(self.orientation) else self.orientation,
                "margin": self.margin, "ambiguous": self.ambiguous}


def map_quality(src: PreparedShape, tgt: PreparedShape, fmap: torch.Tensor,
                orientation: float | None = None, samples: int = 1000,
                expect: int = 1, ratio: float | None = None,
                margin: float | None = None) -> MapQuality:
    """Quality of a dense map from the map alone (no ground truth).

    Parameters
    ----------
    src, tgt : PreparedShape
    fmap : torch.Tensor, int64, shape (n,)
        Target vertex of every source vertex.
    orientation : float, optional
        Its orientation score if known (else measured, :func:`orientation_score`).
    samples : int
        Farthest-point source samples of the functional map.
    expect : {1, -1}
        The orientation a right map has: +1 for a direct map, -1 for an intrinsic symmetry
        (:func:`~torchheat.matching.symmetry`).
    ratio : float, optional
        For a partial source (``match(..., partial=True)``): its area over the target's. The
        functional map is then rectangular, ``k_s = floor(0.8 ratio k)`` modes of the piece
        against ``k`` of the whole, pulling the whole's functions back, fitted on the samples
        weighted by the area they stand for (:func:`~torchheat.matching.partial.sample_areas`);
        a right map gives it orthogonal rows, and the defect is ``|r C C^T - I|_F /
        sqrt(k_s)`` (``r C C^T``: the piece's basis is orthonormal at unit area, ``1 /
        sqrt(r)`` times its basis at the whole's scale).
    margin : float, optional
        The choice's score margin, if the map was chosen among candidates (see the module
        docstring); sets ``ambiguous``.

    Returns
    -------
    MapQuality

    Examples
    --------
    >>> import numpy as np, trimesh
    >>> from torchheat import Mesh, prepare
    >>> m = trimesh.creation.icosphere(3)
    >>> s = prepare(Mesh(m.vertices * [1.0, 0.8, 0.6], m.faces))
    >>> q = map_quality(s, s, torch.arange(s.n))  # the identity: an isometry, orientation kept
    >>> round(q.defect, 6), q.suspect
    (0.0, False)
    >>> map_quality(s, s, torch.zeros(s.n, dtype=torch.int64)).suspect  # everything to one vertex
    True
    """
    fmap = torch.as_tensor(fmap, dtype=torch.int64)
    k = int(min(QUALITY_K, src.hk.eigenvectors.shape[1], tgt.hk.eigenvectors.shape[1]))
    rows = _fps(src, min(samples, src.n))
    if ratio is None:
        C = functional_map(src.hk.eigenvectors, tgt.hk.eigenvectors, rows, fmap[rows], k)
        defect = float(torch.linalg.norm(C.T @ C - torch.eye(k, dtype=C.dtype)) / math.sqrt(k))
    else:
        k_s = int(max(1, min(src.hk.eigenvectors.shape[1], math.floor(PARTIAL_MODES * ratio * k))))
        # rows weighted by the area they stand for: the rectangular fit depends on it (a right
        # map of a piece with uneven vertex masses read suspect unweighted)
        C = partial_functional_map(src.hk.eigenvectors, tgt.hk.eigenvectors, rows, fmap[rows],
                                   k_s, k, weights=sample_areas(src, rows))
        # the piece's basis is orthonormal at unit area, i.e. sqrt(1/r) times its basis at
        # the whole's scale: C C^T = I / r for a right map
        defect = float(torch.linalg.norm(ratio * (C @ C.T) - torch.eye(k_s, dtype=C.dtype))
                       / math.sqrt(k_s))
    o = orientation_score(src, tgt, fmap) if orientation is None else float(orientation)
    iso = math.exp(-((defect / DEFECT_SCALE) ** 2))
    q = iso * (1.0 + expect * float(np.clip(o, -1.0, 1.0))) / 2.0 if not math.isnan(o) else iso
    return MapQuality(defect, o, q, q < SUSPECT_BELOW, margin,
                      margin is not None and margin < AMBIGUOUS_BELOW)
