"""A piece matched two ways (``partial_scale="auto"``, see :func:`torchheat.match`): with its
holes closed (:func:`filled_piece`) and matched as a whole shape (``partial_scale="filled"``),
kept at once when that match is sure (:func:`_filled_sure`); otherwise also at the whole's
scale, and the map that agrees best with the landmark-free partial map is kept.

Why two: a piece cut off by a plane is matched best at the whole's scale with small times
(:mod:`.partial`); a scan with many holes puts every vertex near a boundary, which crushes
those times, while closing its holes gives back nearly the whole surface, whose spectrum the
full pipeline matches as it matches two poses (SHREC'16, 30 holed shapes: 66 -> 80 % of points
under 0.25 sqrt(area) against the earlier second way, the holed piece at unit area).

The matcher itself is passed in (``match_fn``): this stage runs :func:`torchheat.match` twice
with a fixed scale, and the pipeline calls this stage, so it must not import the pipeline.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from ..heat import threads
from ..mesh import Mesh, MeshError
from ..topology import FILLED_LEAST, fill_holes
from .partial import _agreement, _boundary_distance, area_ratio, dense_partial_map
from .prepared import CachedShape, PreparedShape, _as_prepared, _fps
from .quality import MapQuality, map_quality
from .refine import _known
from .result import Correspondence, _numbering
from .select import _CLEAR_MARGIN, _ZO_ORIENT_CLIP, _clear_choice


def _prepared_pair(source: Mesh | PreparedShape | CachedShape | Any,
                   target: Mesh | PreparedShape | CachedShape | Any, kw: dict
                   ) -> tuple[PreparedShape, PreparedShape, dict]:
    """Both shapes prepared as :func:`torchheat.match` would (``kw``: its arguments), and the
    preparation options used."""
    pkw = {"times": "adaptive" if kw["times"] is None else kw["times"],
           "max_features": kw["max_features"]}
    with threads(kw["num_threads"]):
        return _as_prepared(source, **pkw), _as_prepared(target, **pkw), pkw


def _partial_auto(source: Mesh | PreparedShape | CachedShape | Any,
                  target: Mesh | PreparedShape | CachedShape | Any, kw: dict,
                  match_fn: Callable[..., Correspondence]) -> Correspondence:
    """``partial_scale="auto"``: the piece matched with its holes filled and at the whole's
    scale; the filled map is kept at once when it is sure (:func:`_filled_sure`), otherwise
    the map that agrees best with the landmark-free map (plus half its quality) wins (see
    :func:`torchheat.match`). ``kw``: ``match``'s keyword arguments; ``match_fn``: ``match``
    itself, called with ``partial_scale="filled"`` or ``"piece"``."""
    t0 = time.perf_counter()
    src, tgt, _ = _prepared_pair(source, target, kw)
    not_tried = None
    try:
        closed = _filled_of(src).area() / tgt.mesh.area()  # may exceed 1 (cone patches)
    except MeshError as err:
        closed, not_tried = None, str(err)  # the holes cannot be closed: the piece way alone
    t_prep = time.perf_counter() - t0
    out = []  # (quality, way, corr)
    too_small = closed is not None and closed < _FILLED_LEAST
    sure = False
    # (a third way, the piece once more from its strongest features when both maps read
    # suspect, was dropped: on SHREC'16 it ran on 26 of 150 pieces, gave the same map on 24,
    # and was chosen once, worse than the filled map it displaced — RESULTS.md)
    for scale in ("filled", "piece"):
        if scale == "filled" and (closed is None or too_small):
            continue
        try:
            corr = match_fn(src, tgt, **{**kw, "partial_scale": scale})  # re-times a copy
        except MeshError as err:
            if scale != "filled":
                raise
            not_tried = str(err)  # the closed piece could not be matched: the piece way alone
            continue
        q = corr.quality.quality if corr.quality is not None else -1.0
        out.append((q, scale, corr))
        if scale == "filled" and _filled_sure(corr):
            sure = True  # the piece way is not tried
            break
    piece = next((x[2] for x in out if x[1] == "piece"), None)
    agreement = {}
    if piece is not None:  # agreements are read on farthest points of the piece only
        pts = _fps(src, min(src.n, _PARTIAL_AUTO_POINTS))
        free = _landmark_free_images(src, tgt, piece, pts)
        if free is not None:
            # (match refuses final_map=False here: the maps are there)
            agreement = {x[1]: _agreement(tgt, _known(x[2].map)[pts], free) for x in out}
    if sure:
        best = out[0]
        part = best[2].info["partial"]
        chosen_by = (f"the closed piece's match is clear (score margin "
                     f"{part['closed_margin']:.2f} >= {_CLEAR_MARGIN}, orientation "
                     f"{part['closed_orientation']:+.2f} >= {_ZO_ORIENT_CLIP}) and its map "
                     f"of the piece reads quality {best[0]:.2f} >= {_FILLED_SURE}: the piece's "
                     "own scale not tried")
    elif len(out) == 2 and (deep := _deep_share(src, tgt)) < _DEEP_LEAST:
        best = out[0]  # the filled way
        chosen_by = (f"{100 * deep:.0f} % of the piece's area lies {_DEEP_DISTANCE:g} "
                     f"sqrt(area) or more from its boundary (< {100 * _DEEP_LEAST:.0f} %): "
                     "the evidence at the piece's own scale is weak there, the filled map kept")
    elif not agreement:
        best = max(out, key=lambda x: x[0])
        chosen_by = "quality"
    else:
        # measured on SHREC'16 (90 cuts, 49 holes; share of vertices within 0.15 sqrt(area)
        # of the truth): by quality 0.734 / 0.54, by agreement + 0.5 quality 0.748 / 0.56
        # (+ 0.25 quality: 0.748 / 0.57, but on the cow of the partial demo the right piece
        # map is then only 0.02 ahead; with 0.5, 0.16) — against the unit scale then; with the
        # filled piece instead (RESULTS.md, seventh session) the cow reads piece 0.885, filled
        # 0.754. Not used to choose: the closed piece's own full-match quality (holed pieces
        # read 0.25-1 when right, but the capped front of the cow reads 0.43 and is wrong)
        best = max(out, key=lambda x: agreement[x[1]] + _PARTIAL_AUTO_QUALITY * x[0])
        chosen_by = "agreement with the landmark-free map + 0.5 quality"
    if too_small:
        assert closed is not None  # (too_small)
        chosen_by = (f"closed, the piece would cover {100 * closed:.1f} % of the whole "
                     f"(< {100 * _FILLED_LEAST:.0f} %): too little to pass for the whole, the "
                     "filled piece not tried")
    corr = best[2]
    corr.info["partial"] = {**corr.info["partial"], "chosen_by": chosen_by,
                            "closed_ratio": closed,
                            "quality": {x[1]: x[0] for x in out}}
    for x in out:
        for key in ("closed_quality", "closed_margin", "closed_orientation"):
            if key in x[2].info["partial"]:
                corr.info["partial"][key] = x[2].info["partial"][key]
    if agreement:
        corr.info["partial"]["agreement"] = agreement
    if not_tried is not None:
        corr.info["partial"]["chosen_by"] += f" (the filled piece failed: {not_tried})"
    tm = corr.info["timings"]
    tm["prepare"] = tm.get("prepare", 0.0) + t_prep
    tm["other_scale"] = sum(x[2].info["timings"].get("total", 0.0) for x in out
                            if x[2] is not corr)
    tm["total"] = time.perf_counter() - t0
    return corr


def _deep_share(src: PreparedShape, tgt: PreparedShape) -> float:
    """Share of the piece's area (lumped vertex masses) at least ``_DEEP_DISTANCE
    sqrt(area(whole))`` from its boundary, along edges."""
    dist = _boundary_distance(src, math.sqrt(tgt.mesh.area()))
    mass = src.hk.vertex_mass.double().numpy()
    return float(mass[dist >= _DEEP_DISTANCE].sum() / mass.sum())


def _filled_sure(corr: Correspondence) -> bool:
    """Whether the filled way's map is kept without trying the piece's own scale: the closed
    piece's match chose clearly among whole maps (score margin >= ``select._CLEAR_MARGIN``,
    orientation >= ``select._ZO_ORIENT_CLIP``: the staged search's test of a clear choice)
    and its map of the piece reads a quality of at least ``_FILLED_SURE``."""
    part = corr.info["partial"]
    return (corr.quality is not None
            and _clear_choice(part.get("closed_margin"), part.get("closed_orientation"))
            and corr.quality.quality >= _FILLED_SURE)


#: The filled way is tried only when the closed piece covers this share of the whole's area:
#: a smaller closed surface cannot pass for the whole, and its full match is then wrong far
#: more often than the piece's (SHREC'16, both ways run on all 150 pieces: of the 73 below
#: 0.6, 67 are matched as well or better at the piece's scale, and on the 6 others the
#: arbiter kept the piece way anyway; thresholds 0.5-0.65 score within 0.3 points of each
#: other). Skipping it saves the second way's eigensolve and match on 70 % of the cut pieces.
_FILLED_LEAST = FILLED_LEAST  # 0.6, defined without torch for the command line


#: Weight of the quality beside the agreement when ``partial_scale="auto"`` chooses a scale
_PARTIAL_AUTO_QUALITY = 0.5


#: Source points the agreement of a partial map with the landmark-free map is read on
_PARTIAL_AUTO_POINTS = 1000


#: The filled way's map of the piece must read at least this quality (besides a clear choice
#: of the closed match) to be kept without the piece way. Both ways run offline on SHREC'16
#: (Euclidean proxy, share within 0.25 sqrt(area) of the truth; RESULTS.md, fourteenth
#: session): the holed pieces whose filled map is sure are right (31 of 50, skipping the
#: piece way; the arbiter chose the worse way on 8 of 50 otherwise); a capped cut piece can
#: be clear and wrong (cuts_cat_4: margin 3.4, quality 0.26, 9 % right against the piece
#: way's 91 %); at 0.25 it would be kept, at 0.3 none of the 27 cut pieces with both ways is
#: changed. Between 0.3 and SUSPECT_BELOW (0.25) is the only knob here; no threshold was
#: fitted beyond it.
_FILLED_SURE = 0.3


#: When both ways ran, the filled map is kept without arbitration if less than
#: ``_DEEP_LEAST`` of the piece's area lies ``_DEEP_DISTANCE sqrt(area(whole))`` or more from
#: its boundary: the arbiter's evidence (agreement with the landmark-free map, the rectangular
#: quality) is read at the piece's own scale, whose small times see little but boundary on
#: such a piece (a scan riddled with holes). A third was set from an offline sweep (SHREC'16,
#: both ways run, Euclidean proxy, vertex counts instead of areas); measured since on all 150
#: pieces (geodesic, RESULTS.md, fourteenth session): it decides 6 holed pieces (cat_2 13 ->
#: 83 %, michael_4 42 -> 70, centaur_3 51 -> 53; horse_1 36 -> 3; two unchanged) and one cut
#: piece (dog_15 100 -> 89 %). A thin base: 0.20 would have changed cat_2 alone.
_DEEP_LEAST = 1.0 / 3.0
_DEEP_DISTANCE = 0.1


def _landmark_free_images(src: PreparedShape, tgt: PreparedShape, corr: Correspondence,
                          rows: torch.Tensor) -> torch.Tensor | None:
    """Target images of the source vertices ``rows`` under the landmark-free partial
    functional map of a piece-scale run (refined by rectangular ZoomOut); None if the run has
    none.

    The landmark-free map is coarse but unbiased: it does not depend on a landmark or on the
    scale the piece was matched at, so it can arbitrate between the piece-scale and filled
    maps, whose own qualities are not comparable (a piece with many holes reads a low quality
    at the whole's scale even when right).
    """
    part = corr.info.get("partial") or {}
    C = part.get("descriptor_fmap")
    return None if C is None else dense_partial_map(src, tgt, C, rows=rows)


def filled_piece(mesh: Mesh) -> Mesh:
    """The piece with every boundary loop closed by a patch of concentric rings around its
    centroid (:func:`torchheat.topology.fill_holes`); its own vertices come first. The mesh
    itself when it has no boundary.

    Parameters
    ----------
    mesh : Mesh
        n vertices.

    Returns
    -------
    Mesh
        ``n + h`` vertices, the first ``n`` those of ``mesh``; named "<name> (holes filled)".

    Examples
    --------
    >>> import trimesh
    >>> m = trimesh.creation.icosphere(2)
    >>> V, F = m.vertices, m.faces[m.triangles_center[:, 2] < 0.9]  # a cap cut off
    >>> closed = filled_piece(Mesh(V, F, largest_component=True))
    >>> bool(closed.boundary_vertices().any())
    False
    """
    V, F = mesh.numpy()
    V2, F2 = fill_holes(V, F)
    if len(V2) == len(V):
        return mesh
    try:
        return Mesh(V2, F2, name=f"{mesh.name or 'source'} (holes filled)")
    except MeshError as err:  # e.g. a patch face of zero area over a degenerate loop
        raise MeshError(f"{mesh.name or 'source'}: closing its holes made an invalid mesh "
                        f"({err}); match it with partial_scale='piece' (--partial-scale "
                        "piece)") from err


def _filled_of(shape: PreparedShape) -> Mesh:
    """:func:`filled_piece` of a prepared shape's mesh, computed once per shape."""
    cached = shape.caches.filled_mesh
    if cached is None:
        cached = shape.caches.filled_mesh = filled_piece(shape.mesh)
    return cached


def offer_filled(shape: PreparedShape, V: np.ndarray, F: np.ndarray, eigenpairs: tuple
                 ) -> bool:
    """Give a piece the eigenpairs of its closed mesh, solved elsewhere from arrays.

    The command line closes a piece's holes with numpy before it imports torch and solves the
    closed mesh in its background eigensolve workers (:class:`torchheat.eigen.EigenWorkers`);
    the filled way (:func:`_match_filled`) then prepares the closed piece with them instead
    of solving in-process. They are taken only if ``(V, F)`` is exactly the piece's
    :func:`filled_piece`, so the match is the same either way.

    Parameters
    ----------
    shape : PreparedShape
        The piece.
    V, F : numpy.ndarray, shapes (n + h, 3) and (m + f, 3)
        The arrays the eigenpairs belong to (:func:`torchheat.topology.fill_holes` of the
        piece's arrays).
    eigenpairs : (lam, phi)
        Shapes (k,) and (n + h, k).

    Returns
    -------
    bool
        Whether they were taken.

    Examples
    --------
    >>> import trimesh, torchheat
    >>> from torchheat.eigen import cotan_eigenpairs
    >>> from torchheat.topology import fill_holes
    >>> m = trimesh.creation.icosphere(3)
    >>> V, F = m.vertices, m.faces[m.triangles_center[:, 2] < 0.9]  # a cap cut off
    >>> piece = torchheat.prepare(torchheat.Mesh(V, F, largest_component=True))
    >>> V2, F2 = fill_holes(*piece.mesh.numpy())
    >>> offer_filled(piece, V2, F2, cotan_eigenpairs(V2, F2, 100))
    True
    """
    try:
        filled = _filled_of(shape)
    except MeshError:
        return False  # the filled way reports it
    if filled is shape.mesh:
        return False
    V0, F0 = filled.numpy()
    if not (np.array_equal(V0, V) and np.array_equal(F0, F)):
        return False
    shape.caches.filled_eigenpairs = eigenpairs
    return True


def _match_filled(source: Mesh | PreparedShape | CachedShape | Any,
                  target: Mesh | PreparedShape | CachedShape | Any, kw: dict,
                  match_fn: Callable[..., Correspondence]) -> Correspondence:
    """``partial_scale="filled"``: the piece with its holes closed (:func:`filled_piece`),
    matched as a whole shape; the map of the piece's own vertices is returned, its quality
    read on the piece (its rectangular functional map, as at the piece's scale)."""
    t0 = time.perf_counter()
    src, tgt, pkw = _prepared_pair(source, target, kw)
    ratio = area_ratio(src.mesh, tgt.mesh)
    filled = _filled_of(src)
    with threads(kw["num_threads"]):
        fsrc = src if filled is src.mesh else _as_prepared(
            filled, **pkw, eigenpairs=src.caches.filled_eigenpairs)
    t_prep = time.perf_counter() - t0
    # no trimmed twins: measured, they hurt the closed pieces (SHREC'16 holes 81.4 -> 77.8 %;
    # david_10 97 -> 13 %), whose patches are not part of the whole's surface; no staged
    # search: its gate was set on whole shapes, and on closed pieces it kept wrong first-stage
    # choices (cuts 81.9 -> 81.4 %, dog_10 100 -> 63 %; holes 82.0 -> 81.6 %; twelfth session)
    # no polished candidates either: measured, they hurt too (cuts 81.8 -> 81.2 %; twentieth
    # session)
    full = match_fn(fsrc, tgt, **{**kw, "partial": False, "trimmed_twins": False,
                                   "staged": False, "polished": False})
    n = src.n
    info = full.info
    if info.get("p") is not None and info["p"] >= n:
        info["p"] = None  # the first landmark lies on a patch: no vertex of the piece
    info["partial"] = {"ratio": ratio, "scale": "filled", "descriptor_fmap": None,
                       "filled_vertices": fsrc.n - n}
    if full.quality is not None:  # None with final_map=False
        # the closed piece against the whole, read like a full match: reported, not used to
        # choose (right maps of holed pieces read 0.25-1, but a capped cut piece can read as
        # high: the wrong map of the cow's capped front, 0.43)
        info["partial"]["closed_quality"] = full.quality.quality
        # and how clearly it was chosen among whole maps (:func:`_filled_sure`)
        info["partial"]["closed_margin"] = full.quality.margin
        info["partial"]["closed_orientation"] = full.quality.orientation
    info["timings"]["prepare"] = info["timings"].get("prepare", 0.0) + t_prep
    info["timings"]["total"] = time.perf_counter() - t0

    def quality(corr: Correspondence) -> MapQuality:  # (given with final_map only)
        return map_quality(src, tgt, _known(corr.map), ratio=ratio)

    return Correspondence(
        **_numbering(src, tgt),
        map=(lambda: _known(full.map)[:n]) if kw["final_map"] else None,
        landmarks=[(a, b) for a, b in full.landmarks if a < n],
        candidates=full.candidates,
        scores=full.scores,
        symmetric_map=((lambda: _known(full.symmetric_map)[:n]) if full.has_symmetric_map
                       else None),
        symmetric_landmarks=None if full.symmetric_landmarks is None else [
            (a, b) for a, b in full.symmetric_landmarks if a < n],
        orientation=full.orientation,
        quality=quality if kw["final_map"] else None,
        info=info,
    )
