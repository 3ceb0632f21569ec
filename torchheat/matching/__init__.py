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

The package's modules, in the order data flows: :mod:`.nn` (nearest-neighbour engines),
:mod:`.prepared` (prepared shapes and their landmark descriptors), :mod:`.landmarks` (landmark
search, dense maps, seeding), :mod:`.orientation`, :mod:`.refine` (correspondence
augmentation), :mod:`.result` (:class:`Correspondence`), :mod:`.select` (the choice among
refined hypotheses by ZoomOut, and the chosen maps made dense), :mod:`.hypotheses` (one
match's landmark hypotheses refined: samples, round 1, further rounds),
:mod:`.partial_scale` (a piece matched two ways — at the whole's scale and with its holes
filled, ``partial_scale="auto"``),
:mod:`.pipeline` (:func:`match`, its stages in order; :mod:`.options` holds what they read)
and :mod:`.symmetry` (:func:`symmetry`), with
:mod:`.zoomout` (spectral refinement), :mod:`.fmap` (the landmark-free functional map),
:mod:`.partial` (a piece matched into its whole, ``match(..., partial=True)``) and
:mod:`.quality`. Each imports only the ones before it: the stages that need :func:`match` run
again get it passed in (the two ways of a piece get ``match``, the mirror partners of
:mod:`.select` the target's self-symmetry).
"""

from __future__ import annotations

from .landmarks import dense_map, landmark_scores
from .nn import CdistStats, nearest_neighbors
from .orientation import orientation_score
from .pipeline import match
from .prepared import PreparedShape, _check_matchable, prepare
from .result import Correspondence
from .symmetry import symmetry

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
    "CdistStats",
    "_check_matchable",
]


def __getattr__(name: str):  # LAST_CDIST_PEAK: deprecated (nn.__getattr__ warns)
    if name == "LAST_CDIST_PEAK":
        from . import nn

        return nn.__getattr__(name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
