"""The options of :func:`torchheat.match` that its default pipeline reads, grouped in one frozen
value (built by keyword from ``match``'s arguments)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class _Options:
    """The options of :func:`torchheat.match` that its default pipeline (``pipeline._refine``)
    reads."""

    n_candidates: int
    refine_samples: int
    refine_iterations: int
    orientation: bool
    score_samples: int | None
    mirror_hypothesis: bool
    mirror_energy_ratio: float | None
    orientation_weight: float
    fixed_weight: float
    refine_log_floor: float | None
    expand_top: int
    source_landmarks: int
    extra_candidates: int
    refine_keep: int | None
    orientation_samples: int
    num_threads: int | None
    final_map: bool
    use_hks: bool
    engine: str
    zoomout: bool = True
    zoomout_samples: int = 500
    zoomout_k: int | None = None
    zoomout_hypotheses: int = 8
    fine_k: int | None = None  # the chosen maps' last ZoomOut size (zoomout.fine_map)
    partial_ratio: float | None = None  # area(source) / area(target) of a partial match
    descriptor_seed: bool = True
    trimmed_twins: bool = True
    reoriented: bool = True
    polished: bool = True  # _spectral_choice polishes the candidates of an unclear choice
    tie_break: bool = True  # an ambiguous choice goes by the wave kernel signatures
