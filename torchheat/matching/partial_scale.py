"""A piece matched two ways, the map that agrees best with the landmark-free partial map kept
(``partial_scale="auto"``, see :func:`torchheat.match`); and the second way itself,
``partial_scale="filled"``: the piece with its holes closed (:func:`filled_piece`), matched as
a whole shape.

Why two: a piece cut off by a plane is matched best at the whole's scale with small times
(:mod:`.partial`); a scan with many holes puts every vertex near a boundary, which crushes
those times, while closing its holes gives back nearly the whole surface, whose spectrum the
full pipeline matches as it matches two poses (SHREC'16, 30 holed shapes: 66 -> 80 % of points
under 0.25 sqrt(area) against the earlier second way, the holed piece at unit area).

The matcher itself is passed in (``match_fn``): this stage runs :func:`torchheat.match` twice
with a fixed scale, and the pipeline calls this stage, so it must not import the pipeline.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import torch

from ..heat import threads
from ..mesh import Mesh, MeshError
from ..topology import fill_holes
from .partial import _agreement, area_ratio, dense_partial_map
from .prepared import PreparedShape, _as_prepared, _fps, _role_copy
from .quality import MapQuality, map_quality
from .result import Correspondence, _numbering


def _prepared_pair(source: Mesh | PreparedShape, target: Mesh | PreparedShape, kw: dict
                   ) -> tuple[PreparedShape, PreparedShape, dict]:
    """Both shapes prepared as :func:`torchheat.match` would (``kw``: its arguments), and the
    preparation options used."""
    pkw = {"times": "adaptive" if kw["times"] is None else kw["times"],
           "max_features": kw["max_features"]}
    with threads(kw["num_threads"]):
        return _as_prepared(source, **pkw), _as_prepared(target, **pkw), pkw


def _partial_auto(source: Mesh | PreparedShape, target: Mesh | PreparedShape, kw: dict,
                  match_fn: Callable[..., Correspondence]) -> Correspondence:
    """``partial_scale="auto"``: the piece matched at the whole's scale and with its holes
    filled; the map that agrees best with the landmark-free map (plus half its quality) wins
    (see :func:`torchheat.match`). ``kw``: ``match``'s keyword arguments; ``match_fn``:
    ``match`` itself, called with ``partial_scale="piece"`` or ``"filled"``."""
    t0 = time.perf_counter()
    src, tgt, _ = _prepared_pair(source, target, kw)
    most = area_ratio(src.mesh, tgt.mesh) >= _PARTIAL_MOST  # the filled way is always tried
    not_tried = None
    try:
        closed = _filled_of(src).area() / tgt.mesh.area()  # may exceed 1 (cone patches)
    except MeshError as err:
        closed, not_tried = None, str(err)  # the holes cannot be closed: the piece way alone
    t_prep = time.perf_counter() - t0
    out = []  # (quality, way, corr, agreement or None)
    too_small = closed is not None and closed < _FILLED_LEAST
    dense_free = None
    skipped = False
    pts = _fps(src, min(src.n, _PARTIAL_AUTO_POINTS))  # where agreements are read
    # (a third way, the piece once more from its strongest features when both maps read
    # suspect, was dropped: on SHREC'16 it ran on 26 of 150 pieces, gave the same map on 24,
    # and was chosen once, worse than the filled map it displaced — RESULTS.md)
    for scale in ("piece", "filled"):
        if scale == "filled" and (closed is None or too_small):
            continue
        try:
            corr = match_fn(src, _role_copy(tgt), **{**kw, "partial_scale": scale})
        except MeshError as err:
            if scale != "filled":
                raise
            not_tried = str(err)  # the closed piece could not be matched: the piece way alone
            continue
        q = corr.quality.quality if corr.quality is not None else -1.0
        if dense_free is None:
            dense_free = _landmark_free_dense(src, tgt, corr)
        a = None if dense_free is None else _agreement(tgt, corr.map[pts], dense_free[pts])
        out.append((q, scale, corr, a))
        if (len(out) == 1 and not most and a is not None
                and a + _PARTIAL_AUTO_QUALITY * q >= _PARTIAL_ENOUGH):
            skipped = True  # the piece-scale map is clearly right: the filled piece is not tried
            break
    if dense_free is None:
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
        best = max(out, key=lambda x: x[3] + _PARTIAL_AUTO_QUALITY * x[0])
        chosen_by = "agreement with the landmark-free map + 0.5 quality" + (
            " (clear at the piece's scale: the filled piece not tried)" if skipped else "")
    if too_small:
        chosen_by = (f"closed, the piece would cover {100 * closed:.1f} % of the whole "
                     f"(< {100 * _FILLED_LEAST:.0f} %): too little to pass for the whole, the "
                     "filled piece not tried")
    corr = best[2]
    corr.info["partial"] = {**corr.info["partial"], "chosen_by": chosen_by,
                            "closed_ratio": closed,
                            "quality": {x[1]: x[0] for x in out}}
    for x in out:
        if "closed_quality" in x[2].info["partial"]:
            corr.info["partial"]["closed_quality"] = x[2].info["partial"]["closed_quality"]
    if dense_free is not None:
        corr.info["partial"]["agreement"] = {x[1]: x[3] for x in out}
    if not_tried is not None:
        corr.info["partial"]["chosen_by"] += f" (the filled piece failed: {not_tried})"
    tm = corr.info["timings"]
    tm["prepare"] = tm.get("prepare", 0.0) + t_prep
    tm["other_scale"] = sum(x[2].info["timings"].get("total", 0.0) for x in out
                            if x[2] is not corr)
    tm["total"] = time.perf_counter() - t0
    return corr


#: The filled way is tried only when the closed piece covers this share of the whole's area:
#: a smaller closed surface cannot pass for the whole, and its full match is then wrong far
#: more often than the piece's (SHREC'16, both ways run on all 150 pieces: of the 73 below
#: 0.6, 67 are matched as well or better at the piece's scale, and on the 6 others the
#: arbiter kept the piece way anyway; thresholds 0.5-0.65 score within 0.3 points of each
#: other). Skipping it saves the second way's eigensolve and match on 70 % of the cut pieces.
_FILLED_LEAST = 0.6


#: Weight of the quality beside the agreement when ``partial_scale="auto"`` chooses a scale
_PARTIAL_AUTO_QUALITY = 0.5


#: Source points the agreement of a partial map with the landmark-free map is read on
_PARTIAL_AUTO_POINTS = 1000


#: A piece-scale map scoring this (agreement + 0.5 quality) is kept without trying the filled
#: piece: offline on SHREC'16 (the runs behind _PARTIAL_AUTO_QUALITY, against the unit scale
#: then) it skipped the second way on 39 % of the cuts and 5 % of the holes and changed no
#: choice (0.8: 61 % / 5 %, no change either; kept at 0.9 for a margin)
_PARTIAL_ENOUGH = 0.9
#: ...unless the piece covers this much of the whole: closed, it is then nearly the whole, and
#: its full match can be finer than a piece-scale map that reads clear (a cow with eight small
#: holes, 96 % of the area: piece way 0.98 agreement + 0.5 * 0.81, 71 % of the vertices within
#: 2 % of the diagonal; filled 0.99 + 0.5 * 0.95, 100 %). On SHREC'16 one skipped pair reaches
#: it (cuts_michael_11, 90 %): the filled way is tried and loses, the map is the same.
_PARTIAL_MOST = 0.8


def _landmark_free_dense(src: PreparedShape, tgt: PreparedShape, corr: Correspondence
                         ) -> torch.Tensor | None:
    """Every source vertex mapped by the landmark-free partial functional map of a
    piece-scale run (refined by rectangular ZoomOut); None if the run has none.

    The landmark-free map is coarse but unbiased: it does not depend on a landmark or on the
    scale the piece was matched at, so it can arbitrate between the piece-scale and filled
    maps, whose own qualities are not comparable (a piece with many holes reads a low quality
    at the whole's scale even when right).
    """
    part = corr.info.get("partial") or {}
    C = part.get("descriptor_fmap")
    return None if C is None else dense_partial_map(src, tgt, C)


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
    cached = shape.__dict__.get("_filled_mesh")
    if cached is None:
        cached = shape.__dict__["_filled_mesh"] = filled_piece(shape.mesh)
    return cached


def _match_filled(source: Mesh | PreparedShape, target: Mesh | PreparedShape, kw: dict,
                  match_fn: Callable[..., Correspondence]) -> Correspondence:
    """``partial_scale="filled"``: the piece with its holes closed (:func:`filled_piece`),
    matched as a whole shape; the map of the piece's own vertices is returned, its quality
    read on the piece (its rectangular functional map, as at the piece's scale)."""
    t0 = time.perf_counter()
    src, tgt, pkw = _prepared_pair(source, target, kw)
    ratio = area_ratio(src.mesh, tgt.mesh)
    filled = _filled_of(src)
    with threads(kw["num_threads"]):
        fsrc = src if filled is src.mesh else _as_prepared(filled, **pkw)
    t_prep = time.perf_counter() - t0
    # no trimmed twins: measured, they hurt the closed pieces (SHREC'16 holes 81.4 -> 77.8 %;
    # david_10 97 -> 13 %), whose patches are not part of the whole's surface; no staged
    # search: its gate was set on whole shapes, and on closed pieces it kept wrong first-stage
    # choices (cuts 81.9 -> 81.4 %, dog_10 100 -> 63 %; holes 82.0 -> 81.6 %; twelfth session)
    full = match_fn(fsrc, _role_copy(tgt), **{**kw, "partial": False, "trimmed_twins": False,
                                              "staged": False})
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
    info["timings"]["prepare"] = info["timings"].get("prepare", 0.0) + t_prep
    info["timings"]["total"] = time.perf_counter() - t0

    def quality(corr: Correspondence) -> MapQuality:
        return map_quality(src, tgt, corr.map, ratio=ratio)

    return Correspondence(
        **_numbering(src, tgt),
        map=lambda: full.map[:n],
        landmarks=[(a, b) for a, b in full.landmarks if a < n],
        candidates=full.candidates,
        scores=full.scores,
        symmetric_map=(lambda: full.symmetric_map[:n]) if full.has_symmetric_map else None,
        symmetric_landmarks=None if full.symmetric_landmarks is None else [
            (a, b) for a, b in full.symmetric_landmarks if a < n],
        orientation=full.orientation,
        quality=quality if kw["final_map"] else None,
        info=info,
    )
