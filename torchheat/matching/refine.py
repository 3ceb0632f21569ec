"""Refinement by correspondence augmentation: multi-landmark heat-kernel descriptors in factored
form and the refiner that maps samples and recomputes; :class:`Hypothesis`, the record of one
whole map that the stages (hypotheses, ZoomOut choice, dense maps) pass on.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeVar

import numpy as np
import torch

from ..descriptors import (
    heat_kernel_map,
)
from ..heat import threads
from .nn import _Factors, _nn_factors, _nn_factors_pruned
from .prepared import PreparedShape, _cluster_centres

if TYPE_CHECKING:
    from .zoomout import ZoomOutResult

_REFINE_TIMES = slice(1, None, 2)  # every other time sample: half the dimensions, same span


@dataclass(eq=False)
class Hypothesis:
    """One whole map the refined pipeline considers, as it passes through the stages.

    Seeding and refinement (:mod:`.hypotheses`) set the first four fields; the ZoomOut
    choice (:mod:`.select`) the ``zo*`` fields and the kind flags; the dense stage
    (:mod:`.pipeline`) the outputs. A field left at ``None`` was not computed. Copies are
    :func:`dataclasses.replace` (shallow); identity (``is``) tells candidates apart.

    Examples
    --------
    >>> import dataclasses
    >>> h = Hypothesis(lms0=[(0, 5)], g=torch.tensor([5, 7]), energy=0.1, orientation=0.9)
    >>> twin = dataclasses.replace(h, trimmed=True)
    >>> twin.trimmed, h.trimmed, twin.g is h.g
    (True, False, True)
    """

    # --- seeding and refinement (correspondence augmentation on the refinement samples)
    lms0: list[tuple[int, int]] | None = None
    """Starting landmark pairs ``(source, target)``; empty for landmark-free candidates."""
    g: torch.Tensor | None = None
    """int64, (s,): target images of the refinement samples."""
    energy: float | None = None
    """Mean squared descriptor distance of the last refinement round (NaN: not refined)."""
    orientation: float | None = None
    """Orientation score of the sample map (+1 direct, -1 mirror; :mod:`.orientation`)."""
    descriptor_seed: bool = False
    """Seeded by the landmark-free descriptor functional map (:mod:`.fmap`)."""
    agree_descr: float | None = None
    """A piece's hypotheses: agreement with the landmark-free map (:mod:`.pipeline`)."""
    # --- the ZoomOut choice
    zo: ZoomOutResult | None = None
    """Its ZoomOut to the choice's size (images of the ZoomOut rows, functional map)."""
    zo_orientation: float | None = None
    """Orientation read on the ZoomOut map (clearer than on the samples)."""
    zo_tear: float | None = None
    """Share of torn neighbour pairs of the ZoomOut map (``select._Tear``)."""
    zo_score: float | None = None
    """Score before polishing (the copies kept as they were, ``select._spectral_choice``)."""
    zo_margin: float | None = None
    """The chosen map: how much worse its best rival scored (None: no rival)."""
    zo_rival: Hypothesis | None = None
    """The chosen map: that rival (a different whole map)."""
    zo_near: float | None = None
    """The chosen map: how much worse the best partly different candidate scored
    (``select._near_gap``; None: none)."""
    zo_near_rival: Hypothesis | None = None
    """The chosen map: that partly different candidate."""
    zo_tie_break: tuple[float, float] | None = None
    """An ambiguous choice: signature errors (chosen, rival), ``select._descriptor_tie_break``."""
    reoriented: bool = False
    """A reoriented twin (``select._reoriented_candidates``)."""
    trimmed: bool = False
    """An orientation-trimmed twin (``select._trimmed_candidates``)."""
    half_turn: bool = False
    """A half-turn partner (``select._half_turn_partners``)."""
    polished: bool = False
    """Polished by correspondence augmentation before the choice (``select._polish_candidates``)."""
    # --- the chosen maps' outputs
    map: torch.Tensor | Callable[[], torch.Tensor] | None = None
    """int64, (n,): the dense map, or the function computing it on first access."""
    landmarks: list[tuple[int, int]] | None = None
    """The landmark pairs reported (:attr:`.Correspondence.landmarks`)."""
    rival_map: Callable[[], torch.Tensor] | None = None
    """The dense map of ``zo_rival``, deferred (:attr:`.Correspondence.rival_map`)."""
    defect: float | None = None
    """``verify_stage``: the dense map's quality defect (``pipeline._defect``)."""
    partial_dense: str | None = None
    """A piece: which dense map was kept, ``"heat kernel"`` or ``"zoomout"``."""
    partial_dense_quality: dict[str, float] | None = None
    """A piece: the partial quality of both dense maps."""


_T = TypeVar("_T")


def _known(value: _T | None) -> _T:
    """``value``, which an earlier stage has set: a :class:`Hypothesis` field read by a stage
    after the one that sets it (refinement sets ``lms0, g, energy, orientation`` of every
    hypothesis; the ZoomOut choice ``zo`` and ``zo_orientation`` of every candidate it
    compares), or a map that the options guarantee. For the type checker; never None."""
    assert value is not None, "read before the stage that sets it"
    return value


# Precision of the intermediate refinement rounds. The descriptors are centred (the constant
# mode is removed): uncentred, float32 GEMM distances mapped 45 % of a TOSCA shape's vertices
# onto a neighbour when matched against itself; centred, 9 % (float64: none, at 1.6x the
# matching time, with no measurable accuracy gain on 32 TOSCA pairs: 85.2 % vs 84.1 % on the
# 0.08 sqrt(area) proxy, within run-to-run noise).
_REFINE_DTYPE = torch.float32


# The last round (the returned map, and the hypothesis maps the orientation test reads) runs in
# float64, so that a shape matched with itself gives the identity exactly.
_FINAL_DTYPE = torch.float64


# Eigenmodes of the refinement descriptor: the fast tail whose weight at the smallest
# refinement time is below this fraction of the slowest mode's is left out (see
# HeatKernel.spectral_basis); with adaptive times about half of the 100 go (56 kept on TOSCA
# cat0, 49 on SCAPE mesh000), with no change in the maps of 32 TOSCA pairs.
_MODE_TOL = 1e-4


# Searches of at least this many source rows (dense maps) use the exact cluster-pruned search
# (_nn_factors_pruned): 6.6x faster than the brute force on a SCAPE pair, the same map.
_PRUNE_ROWS = 2048


def _refine_factors(shape: PreparedShape, landmarks, dtype: torch.dtype,
                    log_floor: float | None = None, centre: bool = True) -> _Factors:
    """Multi-landmark descriptor of the refinement, ``t_j k_tj(l, x)`` at every other time,
    centred (constant mode removed), in factored spectral form where the eigenbasis serves
    every time (else explicit).

    With ``log_floor`` the heat kernel is taken in log scale, ``log max(k_t, floor)``
    (explicit): by Varadhan's formula ``-4 t log k_t(s, x) -> d(s, x)^2``, so each
    coordinate behaves like a geodesic distance to a landmark instead of vanishing away
    from it.

    ``centre=False`` keeps the constant mode: a partial shape's constant term is not its
    whole's (``t / r`` against ``t`` at the whole's scale), the raw ``t k_t`` are the same.
    """
    hk = shape.hk
    if log_floor is None:
        f = hk.spectral_factors(landmarks, _REFINE_TIMES, dtype=dtype, drop_constant=centre,
                                mode_tol=_MODE_TOL)
        if f is not None:
            return _Factors(f[0], f[1])
    D = heat_kernel_map(hk, landmarks, time_index=_REFINE_TIMES, dtype=dtype).to(dtype)
    tj = hk.times[_REFINE_TIMES].to(D.dtype).to(D.device)
    t = tj.repeat(D.shape[1] // tj.numel())  # landmark-major layout: t_j per column
    if log_floor is None:
        # minus the constant mode's term t_j (unit area; the same offset on every shape)
        return _Factors(D - t if centre else D)
    return _Factors(torch.log((D / t).clamp_min(log_floor)))  # undo the t-scaling first


class _Refiner:
    """Correspondence augmentation (paper Sec. 4) from landmarks ``samples`` on the source.

    Given images ``g`` of the samples on the target, one round maps source vertices by
    nearest neighbour in L2 of the multi-landmark heat kernel map ``samples -> g``. The source
    factors are computed once per match (both precisions); each round builds only the
    target's coefficients (``O(k |samples| J)``) and one factored search.
    """

    def __init__(self, src: PreparedShape, tgt: PreparedShape, samples: torch.Tensor,
                 log_floor: float | None = None, centre: bool = True) -> None:
        self.src, self.tgt, self.samples, self.log_floor = src, tgt, samples, log_floor
        self.centre = centre
        self._src: dict[torch.dtype, _Factors] = {}

    def source(self, dtype: torch.dtype) -> _Factors:
        if dtype not in self._src:
            self._src[dtype] = _refine_factors(self.src, self.samples, dtype, self.log_floor,
                                               self.centre)
        return self._src[dtype]

    def map(self, g: torch.Tensor, rows: torch.Tensor | None,
            dtype: torch.dtype = _REFINE_DTYPE) -> tuple[torch.Tensor, torch.Tensor]:
        """Images (and squared descriptor distances) of the source ``rows`` (None: all)."""
        Ft = _refine_factors(self.tgt, g, dtype, self.log_floor, self.centre)
        Fs = self.source(dtype)
        n_rows = self.src.n if rows is None else rows.numel()
        with threads(self.src.hk.num_threads):
            if n_rows >= _PRUNE_ROWS and Fs.C is not None and Ft.C is not None:
                # a dense map: exact search with cluster pruning (~1 % of the pairs)
                return _nn_factors_pruned(Fs, rows, Ft, _cluster_centres(self.tgt))
            return _nn_factors(Fs, rows, Ft)

    def augment(self, g: torch.Tensor, rows: torch.Tensor | None, iterations: int
                ) -> tuple[torch.Tensor, torch.Tensor, float]:
        """``iterations`` rounds from the sample images ``g``: the intermediate ones map the
        samples only (float32), the last one the source ``rows`` (samples first; all vertices
        when None) in float64. Returns the last round's images, the sample images fed to it
        or produced by it, and its mean squared descriptor distance."""
        for _ in range(iterations - 1):
            _, g = self.map(g, self.samples)
        d2, out = self.map(g, rows, _FINAL_DTYPE)
        if rows is not None:
            g = out[: self.samples.numel()]  # the samples are the first rows
        return out, g, float(d2.double().mean())


def _dense_final(refiner: _Refiner, g: torch.Tensor, num_threads: int | None,
                 timings: dict) -> Callable[[], torch.Tensor]:
    """The refined pipeline's last round over all source vertices, deferred."""

    def compute() -> torch.Tensor:
        t0 = time.perf_counter()
        with threads(num_threads):
            out = refiner.augment(g, None, 1)[0]
        timings["final_map"] = timings.get("final_map", 0.0) + time.perf_counter() - t0
        return out

    return compute


def _agree(V: np.ndarray, a: torch.Tensor, b: torch.Tensor, radius: float) -> float:
    """Share of the positions where two maps' images (vertex indices of ``V``, same length)
    lie within ``radius`` of each other (Euclidean, inclusive): how much two hypotheses or
    ZoomOut candidates are the same map."""
    return float(np.mean(np.linalg.norm(V[a.numpy()] - V[b.numpy()], axis=1) <= radius))


def _fixed_share(g: torch.Tensor, V: np.ndarray, radius: float, samples: torch.Tensor) -> float:
    """Share of the samples that a self-map hypothesis leaves in place: images within
    ``radius`` (Euclidean) of themselves (``g``: the images of ``samples``)."""
    return _agree(V, g, samples, radius)


def _is_identity(g: torch.Tensor, V: np.ndarray, radius: float, samples: torch.Tensor) -> bool:
    """Whether a refined self-map hypothesis is (mostly) the identity: most samples land
    within ``radius`` of themselves (its starting landmarks may not say so)."""
    return _fixed_share(g, V, radius, samples) > 0.5
