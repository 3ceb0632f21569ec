"""The options of :func:`torchheat.match` that its default pipeline reads, grouped in one frozen
value (built by keyword from ``match``'s arguments)."""

from __future__ import annotations

import math
import operator
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
    half_turns: bool = True  # ... and adds their half-turn partners first
    tie_break: bool = True  # an ambiguous choice goes by the wave kernel signatures


#: ``match``'s numeric options and their least meaningful values (None allowed where the
#: option has a None meaning): counts of things, sample sizes (the orientation test reads
#: triangles of samples: at least 3), weights and ratios. Below them the pipeline crashed
#: with an unrelated message (``zoomout_samples=1``: "too many indices") or, worse, returned
#: a map of no meaning without a word (``refine_samples=0``).
_LEAST: dict[str, tuple[float, bool, bool]] = {
    # name: (least value, integer, None allowed)
    "landmarks": (1, True, False),
    "n_candidates": (1, True, False),
    "refine_samples": (1, True, False),
    "refine_iterations": (0, True, False),
    "max_features": (1, True, False),
    "score_samples": (1, True, True),
    "mirror_energy_ratio": (1.0, False, True),
    "orientation_weight": (0.0, False, False),
    "fixed_weight": (0.0, False, False),
    "refine_log_floor": (0.0, False, True),
    "expand_top": (0, True, False),
    "source_landmarks": (1, True, True),
    "extra_candidates": (0, True, False),
    "refine_keep": (1, True, True),  # or "auto"
    "orientation_samples": (3, True, False),
    "num_threads": (1, True, True),
    "zoomout_samples": (3, True, False),
    "zoomout_k": (1, True, True),
    "zoomout_hypotheses": (1, True, False),
    "fine_k": (1, True, True),
    "partial_margin": (0.0, False, False),
}

#: ``prepare``'s numeric options, as :data:`_LEAST` (``prepare(k=5.5)`` solved 5 eigenpairs,
#: ``feature_time=-3`` overflowed into meaningless feature points, ``k=0`` failed on "adaptive
#: times"). ``feature_time`` and ``rtol`` must be positive: :data:`_POSITIVE`.
_PREPARE_LEAST: dict[str, tuple[float, bool, bool]] = {
    "k": (1, True, True),
    "max_features": (1, True, False),
    "feature_time": (0.0, False, False),
    "rtol": (0.0, False, False),
    "num_threads": (1, True, True),
}

#: Options that must be above their least value, not at it (a log-floor of 0 is ``log 0``)
_POSITIVE = frozenset({"refine_log_floor", "feature_time", "rtol"})


def _check_numbers(values: dict, table: dict[str, tuple[float, bool, bool]] | None = None
                   ) -> None:
    """Refuse numeric options below their least value in ``table`` (default :data:`_LEAST`,
    ``match``'s), or of the wrong kind, with a ``ValueError`` / ``TypeError`` that names the
    option; ``values``: name -> value, every name in the table."""
    table = _LEAST if table is None else table
    for name, value in values.items():
        least, integer, none_ok = table[name]
        if (value is None and none_ok) or (name == "refine_keep" and value == "auto"):
            continue
        try:
            if isinstance(value, bool) or value is None:
                raise TypeError
            v = operator.index(value) if integer else float(value)
        except (TypeError, ValueError):
            kind = "an integer" if integer else "a number"
            raise TypeError(f"{name} must be {kind}, not {value!r}") from None
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, not {value!r}")
        strict = name in _POSITIVE
        if v < least or (strict and v <= least):
            bound = ("positive" if strict else "non-negative" if least == 0
                     else f"at least {least:g}")
            raise ValueError(f"{name}={value!r}: must be {bound}")
