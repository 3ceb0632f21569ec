"""Landmark hypotheses refined by correspondence augmentation: the refinement samples and the
rows the orientation test reads, round 1 of every hypothesis, and further rounds (one match's
work, memoised for the stages of a staged search).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import numpy as np
import torch

from .background import run_each
from .landmarks import _sample_map
from .options import _Options
from .orientation import _orientation, _triangles
from .partial import grow_hypothesis
from .prepared import PreparedShape, _fps, _memoised
from .refine import Hypothesis, _is_identity, _Refiner


class _Hypotheses:
    """One match's refinement of landmark hypotheses (``match``'s default pipeline).

    ``samples``: the ``opt.refine_samples`` farthest-point source vertices whose images a
    hypothesis is (``g``, one target vertex per sample); ``tri``: the orientation test's
    triangles (:func:`~torchheat.matching.orientation._triangles` of
    ``opt.orientation_samples`` farthest points); ``rows``: the samples, then every other
    vertex of ``tri``, and ``pos`` their positions (-1 elsewhere); ``refiner``: the
    :class:`~torchheat.matching.refine._Refiner` of the samples. ``memo``: the match's memo
    (round 1 and refined hypotheses are deterministic given their seeds).
    """

    def __init__(self, src: PreparedShape, tgt: PreparedShape, opt: _Options,
                 memo: dict | None = None) -> None:
        self.src, self.tgt, self.opt, self.memo = src, tgt, opt, memo
        Vs, _ = src.mesh.numpy()
        self.samples = _fps(src, opt.refine_samples)
        self.tri = _triangles(Vs, _fps(src, opt.orientation_samples).numpy())
        rows = torch.as_tensor(
            np.unique(np.concatenate([self.samples.numpy(), *self.tri])), dtype=torch.int64
        )
        self.rows = torch.cat([self.samples, rows[~torch.isin(rows, self.samples)]])
        self.pos = torch.full((src.n,), -1, dtype=torch.int64)
        self.pos[self.rows] = torch.arange(self.rows.numel())
        self.refiner = _Refiner(src, tgt, self.samples, opt.refine_log_floor,
                                centre=opt.partial_ratio is None)

    def _side_by_side(self, jobs: list[Callable[[], object]]) -> None:
        """Memoised ``jobs`` (the hypotheses' rounds) side by side on the caller's torch
        threads, one each (:func:`~.background.run_each`); the loop that reads them after
        finds them in the memo. Each job computes on one thread wherever it runs, so its bits
        are those of a one-thread match. Nothing to do without a memo, on one thread (batch
        workers; the command line while the target's self-symmetry runs in the background),
        or on a GPU."""
        if self.memo is not None and self.src.hk.device.type == "cpu":
            run_each(jobs, torch.get_num_threads())

    def round1(self, lms0: list) -> tuple[float, torch.Tensor]:
        """Round 1 of the hypothesis of landmark pairs ``lms0``: its one-point (or few-point)
        map of the samples, refined once; ``(mean squared descriptor distance, images)``.
        A piece's map is right near its landmark only, so it is grown from there first
        (:func:`~torchheat.matching.partial.grow_hypothesis`)."""
        return _memoised(self.memo, ("round 1", tuple(lms0)), lambda: self._round1(lms0))

    def _round1(self, lms0: list) -> tuple[float, torch.Tensor]:
        src, tgt, opt, samples = self.src, self.tgt, self.opt, self.samples
        g0, _ = _sample_map(src, tgt, lms0, samples, opt.use_hks, opt.engine)
        if opt.partial_ratio is not None:  # right near the landmark only: grow from there
            g0 = grow_hypothesis(src, tgt, [int(lms0[0][0])], samples, g0,
                                 lambda lm: _Refiner(src, tgt, lm, opt.refine_log_floor,
                                                     centre=False))
        if opt.refine_iterations > 1:
            d2, g0 = self.refiner.map(g0, samples)
            return float(d2.double().mean()), g0
        return 0.0, g0

    def refined(self, g0: torch.Tensor, iterations: int) -> tuple[torch.Tensor, float, float]:
        """Sample images, energy and orientation of a hypothesis after ``iterations`` rounds
        of correspondence augmentation from the sample images ``g0``."""
        def compute() -> tuple[torch.Tensor, float, float]:
            f_rows, g, energy = self.refiner.augment(g0, self.rows, iterations)
            o = _orientation(self.src, self.tgt, self.tri,
                             lambda i: f_rows[self.pos[i]].numpy())
            return g, energy, o

        return _memoised(self.memo, ("refined", g0.numpy().tobytes(), iterations), compute)

    def first_round(self, hyp: list) -> list[tuple[float, int, list, torch.Tensor]]:
        """Round 1 of every landmark hypothesis of ``hyp``: ``(energy, seeding order,
        landmarks, sample images)``, lowest energy first (ties in seeding order)."""
        self._side_by_side([functools.partial(self.round1, lms0) for lms0 in hyp])
        stage: list[tuple[float, int, list, torch.Tensor]] = []
        for lms0 in hyp:
            e1, g0 = self.round1(lms0)
            stage.append((e1, len(stage), lms0, g0))
        stage.sort(key=lambda s_: (s_[0], s_[1]))
        return stage

    def refine_kept(self, stage: list, forced: list, self_match: bool
                    ) -> tuple[list[Hypothesis], list, list[torch.Tensor]]:
        """The ``opt.refine_keep`` hypotheses of ``stage`` with the lowest round-1 energies,
        and every ``forced`` one (``(landmarks, sample images)``), refined further; a
        hypothesis that starts far behind does not converge (measured: the energies of
        converged and failed hypotheses differ 5-50x).

        ``self_match`` (a shape against itself): the identity (energy 0) appears once per
        seed; one is kept, so that the pruning does not crowd out the symmetric hypotheses.
        Returns the refined hypotheses (:class:`.refine.Hypothesis`: ``lms0, g, energy,
        orientation``) and, for the diagnostics, every hypothesis ``(landmarks, energy,
        orientation)`` (the pruned ones with their round-1 energy and no orientation) with its
        sample images.
        """
        opt = self.opt
        if self_match:
            Vs, _ = self.src.mesh.numpy()
            radius = 0.05 * self.src.mesh.bbox_diagonal()
            ident = [_is_identity(s_[3], Vs, radius, self.samples) for s_ in stage]
            first = ident.index(True) if any(ident) else -1
            stage = [s_ for i, s_ in enumerate(stage) if not ident[i] or i == first]
        keep = len(stage) if opt.refine_keep is None else max(1, int(opt.refine_keep))
        results: list[Hypothesis] = []
        hypotheses: list = []
        hyp_images: list[torch.Tensor] = []
        for e1, _, lms0, g0 in stage[keep:]:
            hypotheses.append((lms0, e1, float("nan")))
            hyp_images.append(g0)
        kept = [(s_[2], s_[3]) for s_ in stage[:keep]] + forced
        iterations = max(opt.refine_iterations - 1, 1)
        self._side_by_side([functools.partial(self.refined, g0, iterations) for _, g0 in kept])
        for lms0, g0 in kept:
            g, energy, o = self.refined(g0, iterations)
            results.append(Hypothesis(lms0=lms0, g=g, energy=energy, orientation=o))
            hypotheses.append((lms0 or ["descriptor map"], energy, o))
            hyp_images.append(g)
        return results, hypotheses, hyp_images
