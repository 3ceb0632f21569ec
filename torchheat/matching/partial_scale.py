"""``partial_scale="auto"``: a piece matched at the whole's scale and as a unit-area shape, the
map that agrees best with the landmark-free partial map kept (see :func:`torchheat.match`).

The matcher itself is passed in (``match_fn``): this stage runs :func:`torchheat.match` twice
with a fixed scale, and the pipeline calls this stage, so it must not import the pipeline.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections.abc import Callable

import torch

from ..heat import threads
from ..mesh import Mesh
from .partial import _agreement, dense_partial_map
from .prepared import PreparedShape, _as_prepared, _fps
from .quality import SUSPECT_BELOW
from .result import Correspondence


def _role_copy(shape: PreparedShape) -> PreparedShape:
    """A copy whose heat kernel times can be changed; the eigenbasis, the farthest-point
    samples and the self-symmetry cache are shared."""
    view = dataclasses.replace(shape, hk=copy.copy(shape.hk))
    view.__dict__["_sym_cache"] = shape.__dict__.setdefault("_sym_cache", {})
    if "_fps_cache" in shape.__dict__:
        view.__dict__["_fps_cache"] = shape.__dict__["_fps_cache"]
    return view


def _partial_auto(source: Mesh | PreparedShape, target: Mesh | PreparedShape, kw: dict,
                  match_fn: Callable[..., Correspondence]) -> Correspondence:
    """``partial_scale="auto"``: the piece matched at the whole's scale and as a unit-area
    shape; the map that agrees best with the landmark-free map (plus half its quality) wins
    (see :func:`torchheat.match`). ``kw``: ``match``'s keyword arguments; ``match_fn``:
    ``match`` itself, called with ``partial_scale="piece"`` or ``"unit"``."""
    t0 = time.perf_counter()
    pkw = {"times": "adaptive" if kw["times"] is None else kw["times"],
           "max_features": kw["max_features"]}
    with threads(kw["num_threads"]):
        src = _as_prepared(source, **pkw)
        tgt = _as_prepared(target, **pkw)
    t_prep = time.perf_counter() - t0
    out = []  # (quality, label, corr, agreement or None)
    dense_free = None
    skipped = False
    pts = _fps(src, min(src.n, _PARTIAL_AUTO_POINTS))  # where agreements are read
    for scale, order in (("piece", kw["partial_landmarks"]), ("unit", None), ("piece", "retry")):
        if order == "retry":
            if max(x[0] for x in out) >= SUSPECT_BELOW or kw["partial_landmarks"] != "deepest":
                break
            order = "strongest"  # both maps suspect: once more from the strongest features
        corr = match_fn(src, _role_copy(tgt), **{**kw, "partial_scale": scale,
                                                 "partial_landmarks": order or "deepest"})
        label = scale if order in (None, kw["partial_landmarks"]) else f"{scale}, {order}"
        q = corr.quality.quality if corr.quality is not None else -1.0
        if dense_free is None:
            dense_free = _landmark_free_dense(src, tgt, corr)
        a = None if dense_free is None else _agreement(tgt, corr.map[pts], dense_free[pts])
        out.append((q, label, corr, a))
        if len(out) == 1 and a is not None and a + _PARTIAL_AUTO_QUALITY * q >= _PARTIAL_ENOUGH:
            skipped = True  # the piece-scale map is clearly right: the unit scale is not tried
            break
    if dense_free is None:
        best = max(out, key=lambda x: x[0])
        chosen_by = "quality"
    else:
        # measured on SHREC'16 (90 cuts, 49 holes; share of vertices within 0.15 sqrt(area)
        # of the truth): by quality 0.734 / 0.54, by agreement + 0.5 quality 0.748 / 0.56
        # (+ 0.25 quality: 0.748 / 0.57, but on the cow of the partial demo the right piece
        # map is then only 0.02 ahead; with 0.5, 0.16)
        best = max(out, key=lambda x: x[3] + _PARTIAL_AUTO_QUALITY * x[0])
        chosen_by = "agreement with the landmark-free map + 0.5 quality" + (
            " (clear at the piece's scale: unit scale not tried)" if skipped else "")
    corr = best[2]
    corr.info["partial"] = {**corr.info["partial"], "chosen_by": chosen_by,
                            "quality": {x[1]: x[0] for x in out}}
    if dense_free is not None:
        corr.info["partial"]["agreement"] = {x[1]: x[3] for x in out}
    tm = corr.info["timings"]
    tm["prepare"] = tm.get("prepare", 0.0) + t_prep
    tm["other_scale"] = sum(x[2].info["timings"].get("total", 0.0) for x in out
                            if x[2] is not corr)
    tm["total"] = time.perf_counter() - t0
    return corr


#: Weight of the quality beside the agreement when ``partial_scale="auto"`` chooses a scale
_PARTIAL_AUTO_QUALITY = 0.5


#: Source points the agreement of a partial map with the landmark-free map is read on
_PARTIAL_AUTO_POINTS = 1000


#: A piece-scale map scoring this (agreement + 0.5 quality) is kept without trying the unit
#: scale: offline on SHREC'16 (the runs behind _PARTIAL_AUTO_QUALITY) it skipped the unit
#: scale on 39 % of the cuts and 5 % of the holes and changed no choice (0.8: 61 % / 5 %,
#: no change either; kept at 0.9 for a margin)
_PARTIAL_ENOUGH = 0.9


def _landmark_free_dense(src: PreparedShape, tgt: PreparedShape, corr: Correspondence
                         ) -> torch.Tensor | None:
    """Every source vertex mapped by the landmark-free partial functional map of a
    piece-scale run (refined by rectangular ZoomOut); None if the run has none.

    The landmark-free map is coarse but unbiased: it does not depend on a landmark or on the
    scale the piece was matched at, so it can arbitrate between the piece-scale and unit-scale
    maps, whose own qualities are not comparable (a piece with many holes reads a low quality
    at the whole's scale even when right).
    """
    part = corr.info.get("partial") or {}
    C = part.get("descriptor_fmap")
    return None if C is None else dense_partial_map(src, tgt, C)
