"""The paper's landmark search (score every candidate ``q`` for ``p`` at once), dense maps from
landmarks, and the seeding of hypotheses (distinct candidates, twin landmarks, greedy extra
landmarks).
"""

from __future__ import annotations

import functools
import math
import operator
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from ..descriptors import (
    feature_points,
    heat_kernel_map,
    ring_neighbors,
)
from .nn import (
    WORK_BYTES,
    _kdtree,
    _resolve_engine,
    _rows_within,
    _tree_query,
    _TreeCache,
    nearest_neighbors,
)
from .options import _Options
from .prepared import PreparedShape, _descriptor, _fps, _memoised

__all__ = ["landmark_scores", "dense_map"]


def landmark_scores(
    source: PreparedShape,
    target: PreparedShape,
    p: int | Sequence[int],
    candidates: Sequence[int] | torch.Tensor,
    *,
    q_fixed: Sequence[int] = (),
    use_hks: bool = True,
    engine: str = "auto",
    samples: torch.Tensor | None = None,
    memory_bytes: int = WORK_BYTES,
    trees: _TreeCache | None = None,
) -> torch.Tensor:
    """Score every candidate ``q`` for the source landmark ``p``.

    ``E(p, q) = sum_x min_y ||Phi_p(x) - Phi_q(y)||_inf^2`` (divided by the number of x).

    Parameters
    ----------
    source, target : PreparedShape
    p : int or sequence of int
        Source landmark; a sequence ``[p_1, ..., p_l]`` scores the last one given the images
        ``q_fixed`` of the others (greedy extra landmarks).
    candidates : sequence of int, shape (c,)
        Target vertices to score.
    q_fixed : sequence of int
        Images of the earlier landmarks.
    use_hks : bool
        Append the HKS coordinates.
    engine : str
        See :func:`nearest_neighbors`.
    samples : torch.Tensor, optional
        Source vertices x summed over (default: all).
    memory_bytes : int
        Working-set budget: the candidates' heat-kernel columns (``c x m x J``) are
        computed in batches within it, and it is the cdist engine's block budget.
    trees : _TreeCache, optional
        The caller's cache of the candidates' k-d trees (k-d tree engine, no ``q_fixed``):
        a candidate scored again for another ``p`` of the same match (same target times)
        reuses its tree. The scores are the same with or without it.

    Returns
    -------
    torch.Tensor
        float64 scores, shape (c,) (lower is better).

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh, prepare
    >>> m = trimesh.creation.icosphere(2)
    >>> s = prepare(Mesh(m.vertices, m.faces))
    >>> landmark_scores(s, s, 0, [0, 1]).shape
    torch.Size([2])
    """
    # (numpy's stubs: np.isscalar narrows p to any numpy scalar, which int() may refuse)
    if np.isscalar(p) or isinstance(p, int | np.integer):
        ps = [int(p)]  # type: ignore[arg-type]
    else:
        ps = [int(v) for v in p]
    qf = [int(v) for v in q_fixed]
    if len(qf) != len(ps) - 1:
        raise ValueError("q_fixed must give the images of all but the last source landmark")
    cand = torch.as_tensor(candidates, dtype=torch.int64).reshape(-1)
    Dp = _descriptor(source, ps, use_hks)
    if samples is not None:
        Dp = Dp[samples]
    # the candidates' columns [c, m, J] in as few calls as fit the budget (off the spectral
    # fast path, columns() stages up to two more copies of its result)
    J = target.hk.times.numel()
    step = _rows_within(target.n * J * target.hk.dtype.itemsize, cand.numel(), memory_bytes)
    fixed = heat_kernel_map(target.hk, qf) if qf else None
    scores = torch.empty(cand.numel(), dtype=torch.float64)
    if trees is not None and not qf and _resolve_engine(engine, Dp) == "kdtree":
        # one tree per candidate q, reused across the source landmarks of a match
        at: dict[int, list[int]] = {}
        for i, q in enumerate(cand.tolist()):
            at.setdefault(q, []).append(i)

        def score(q: int, tree: object) -> None:
            d, _ = _tree_query(tree, Dp, math.inf)
            scores[at[q]] = float((d.double() ** 2).mean())

        todo = []
        for q in at:
            if (q, use_hks) in trees.trees:
                score(q, trees.trees[(q, use_hks)])
            else:
                todo.append(q)
        for c0 in range(0, len(todo), step):
            Cq = target.hk.columns(torch.tensor(todo[c0 : c0 + step]), certify=False)
            for i, q in enumerate(todo[c0 : c0 + step]):
                Dq = _candidate_descriptor(target, Cq[i], None, use_hks)

                def rows(Dq: torch.Tensor = Dq) -> np.ndarray:
                    return Dq.double().numpy()

                score(q, trees.get((q, use_hks), rows))
            del Cq
        return scores
    for c0 in range(0, cand.numel(), step):
        Cq = target.hk.columns(cand[c0 : c0 + step], certify=False)
        for i in range(Cq.shape[0]):
            Dq = _candidate_descriptor(target, Cq[i], fixed, use_hks)
            d, _ = nearest_neighbors(Dp, Dq, p=math.inf, engine=engine,
                                     memory_bytes=memory_bytes)
            scores[c0 + i] = float((d.double() ** 2).mean())
        del Cq
    return scores


def _candidate_descriptor(target: PreparedShape, column: torch.Tensor,
                          fixed: torch.Tensor | None, use_hks: bool) -> torch.Tensor:
    """The target's descriptor for one candidate ``q``: the heat-kernel map of earlier
    landmarks' images (``fixed``), ``t_j k_tj(q, .)`` from its columns ``[m, J]``, then the HKS."""
    parts = [] if fixed is None else [fixed]
    parts.append(column * target.hk.times.to(column.dtype))
    if use_hks:
        parts.append(target.hks.to(column.dtype))
    return torch.cat(parts, dim=1)


def dense_map(
    source: PreparedShape,
    target: PreparedShape,
    landmarks: Sequence[tuple[int, int]],
    *,
    use_hks: bool = True,
    engine: str = "auto",
    p: float = math.inf,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Dense map ``f(x) = argmin_y ||Phi(x) - Phi(y)||_p`` from landmark pairs.

    Parameters
    ----------
    source, target : PreparedShape
    landmarks : sequence of (p, q)
    use_hks : bool
    engine : str
    p : float
        Norm of the nearest-neighbour search (paper: inf).

    Returns
    -------
    map : torch.Tensor, int64, shape (n,)
    dist : torch.Tensor, shape (n,)
        Descriptor distance of each vertex to its image.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh, prepare
    >>> m = trimesh.creation.icosphere(2)
    >>> s = prepare(Mesh(m.vertices, m.faces))
    >>> dense_map(s, s, [(0, 0)])[0].shape
    torch.Size([162])
    """
    ps = [int(a) for a, _ in landmarks]
    qs = [int(b) for _, b in landmarks]
    Dp = _descriptor(source, ps, use_hks)
    Dq = _descriptor(target, qs, use_hks)
    d, i = nearest_neighbors(Dp, Dq, p=p, engine=engine)
    return i, d


def _distinct(cands: torch.Tensor, V: np.ndarray, radius: float, limit: int) -> list[int]:
    """Keep candidates (in rank order) farther than ``radius`` from every kept one."""
    kept: list[int] = []
    for c in cands.tolist():
        if all(np.linalg.norm(V[c] - V[k]) > radius for k in kept):
            kept.append(int(c))
        if len(kept) >= limit:
            break
    return kept


def _sample_map(src, tgt, lms, rows, use_hks, engine) -> tuple[torch.Tensor, torch.Tensor]:
    """Images of the source vertices ``rows`` under the map of landmark pairs ``lms``."""
    ps = [a for a, _ in lms]
    qs = [b for _, b in lms]
    Dp = _descriptor(src, ps, use_hks)[rows]
    Dq = _descriptor(tgt, qs, use_hks)
    d, i = nearest_neighbors(Dp, Dq, p=math.inf, engine=engine)
    return i, d


def _ambiguity(src: PreparedShape, p: int, use_hks: bool, rows: torch.Tensor | None,
               radius: float, memory_bytes: int = WORK_BYTES) -> int | None:
    """Second source landmark if the one-point map of ``p`` is ambiguous, else None.

    The map from ``p`` alone is ambiguous when a self-isometry of the source fixes ``p``
    (e.g. ``p`` on the plane of a mirror-symmetric shape): then most vertices ``x`` have a
    *twin* ``x'``, far from ``x``, whose descriptor is ten times closer to ``x``'s than any
    mesh neighbour's. The twins are found by a 2-NN self-search of the descriptor on 256
    spread samples (the first ``rows``); if more than a quarter of them qualify, the vertex
    farthest from its twin is returned: its image separates the two maps. The descriptor
    differences along the mesh edges are taken in blocks within ``memory_bytes``.
    """
    D = _descriptor(src, [p], use_hks).double().cpu().numpy()
    V, _ = src.mesh.numpy()
    r = (_fps(src, 256) if rows is None else rows[:256]).numpy()
    dist, idx = _kdtree(D).query(D[r], k=2, p=np.inf)
    first_is_self = idx[:, 0] == r
    twin = np.where(first_is_self, idx[:, 1], idx[:, 0])
    dtwin = np.where(first_is_self, dist[:, 1], dist[:, 0])
    A = ring_neighbors(src.mesh, 1).tocoo()
    dlocal = np.full(src.n, np.inf)
    # |D[a] - D[b]|_inf over the edges: three [edges, d] arrays per block
    step = _rows_within(3 * D.shape[1] * D.itemsize, A.nnz, memory_bytes)
    for e0 in range(0, A.nnz, step):
        a, b = A.row[e0 : e0 + step], A.col[e0 : e0 + step]
        np.minimum.at(dlocal, a, np.abs(D[a] - D[b]).max(axis=1))
    sep = np.linalg.norm(V[r] - V[twin], axis=1)
    qual = (sep > radius) & (dtwin < 0.1 * dlocal[r])
    if qual.mean() <= 0.25:
        return None
    return int(r[np.argmax(np.where(qual, sep, -1.0))])


def _twin_landmark(src: PreparedShape, p: int, use_hks: bool, rows: torch.Tensor | None,
                   diam: float) -> int | None:
    """Second source landmark that separates the direct map of ``p`` from its mirror.

    If ``p`` lies on (or near) the plane of a mirror-symmetric shape, its one-point map cannot
    tell left from right: a vertex ``x`` off the plane and its mirror twin ``x'`` have nearly
    the same descriptor. Among 256 spread samples the one whose nearest descriptor among
    vertices farther than 0.2 diameters is closest is returned (e.g. one paw of a cat whose
    ``p`` is the tail tip, its twin the other paw); its two near-best images give the two
    hypotheses. Detecting whether ``p`` is on the plane is not reliable on real meshes
    (measured: the twin/neighbour descriptor ratios of on-plane and off-plane landmarks
    overlap), so the caller branches on this landmark unconditionally.

    A piece's near twin comes with it from the same search: :func:`_twins`.
    """
    return _twins(src, p, use_hks, rows, diam, None)[0]


def _twins(src: PreparedShape, p: int, use_hks: bool, rows: torch.Tensor | None,
           diam: float, reach: float | None) -> tuple[int | None, int | None]:
    """The far twin of ``p`` (:func:`_twin_landmark`) and its *near twin* (a piece's,
    :func:`_twin_seeds`) from one k-d tree search of the samples: the same rule over only the
    samples ``p``'s heat reaches, those whose heat-kernel map at the largest time is at least
    ``reach`` times ``p``'s own (None when ``reach`` is None or fewer than two samples are
    reached)."""
    D = _descriptor(src, [p], use_hks).double().cpu().numpy()
    V, _ = src.mesh.numpy()
    r = (_fps(src, 256) if rows is None else rows[:256]).numpy()
    k = min(64, src.n)
    dist, idx = _kdtree(D).query(D[r], k=k, p=np.inf)
    dist, idx = np.atleast_2d(dist), np.atleast_2d(idx)
    far = np.linalg.norm(V[idx] - V[r][:, None], axis=2) > 0.2 * diam
    has = far.any(axis=1)
    # each sample's twin distance: to its nearest descriptor beyond 0.2 diameters (inf: none)
    dtwin = np.where(has, dist[np.arange(len(r)), np.argmax(far, axis=1)], np.inf)

    def best(among: np.ndarray) -> int | None:
        if not (has & among).any():
            return None
        return int(r[int(np.argmin(np.where(among, dtwin, np.inf)))])

    near = None
    if reach is not None:
        last = src.hk.times.numel() - 1  # the landmark's heat at the largest time
        reached = D[r, last] >= reach * D[p, last]
        near = best(reached) if reached.sum() >= 2 else None
    return best(np.ones(len(r), dtype=bool)), near


def _expand(src, tgt, p, q, p2, use_hks, radius, limit=2) -> list[list[tuple[int, int]]]:
    """Landmark hypotheses from ``(p, q)``: ``[(p, q)]`` or, when ``p2`` disambiguates, one
    ``[(p, q), (p2, q2)]`` per distinct near-best image ``q2`` of ``p2``."""
    if p2 is None:
        return [[(p, q)]]
    Dp = _descriptor(src, [p], use_hks)[p2].double().cpu().numpy()
    Dq = _descriptor(tgt, [q], use_hks).double().cpu().numpy()
    k = min(64, tgt.n)
    _, nb = _kdtree(Dq).query(Dp, k=k, p=np.inf)
    W, _ = tgt.mesh.numpy()
    q2s = _distinct(torch.as_tensor(np.atleast_1d(nb)), W, radius, limit)
    return [[(p, q), (p2, int(q2))] for q2 in q2s]


def _vertex_index(value: object, n: int, what: str) -> int:
    """``value`` as a vertex index in ``[0, n)``: an integer (Python, numpy or a one-element
    tensor; a float only when integral), else a ``TypeError``; out of range an ``IndexError``
    (a float 3.7 was truncated to vertex 3 without a word)."""
    v: Any = value.item() if isinstance(value, torch.Tensor) and value.numel() == 1 else value
    if isinstance(v, float | np.floating) and float(v).is_integer():
        v = int(v)
    try:
        if isinstance(v, bool | np.bool_):
            raise TypeError
        i = operator.index(v)
    except TypeError:
        raise TypeError(f"{what} {value!r} is not a vertex index (an integer)") from None
    if not 0 <= i < n:
        raise IndexError(f"{what} {i} out of range for {n} vertices")
    return i


def _landmark_search(src: PreparedShape, tgt: PreparedShape, landmark, use_hks: bool,
                     engine: str, score_rows: torch.Tensor | None, max_features: int,
                     n_candidates: int, trees: _TreeCache | None = None
                     ) -> tuple[int, torch.Tensor, torch.Tensor]:
    """The source landmark ``p`` and every target candidate ranked by ``E(p, q)``.

    ``landmark``: None (the strongest source feature), ``p``, or a known pair ``(p, q)``.
    Candidates are the target's feature points, or, for a ``p`` that is no feature point,
    the 2-ring local minima of the HKS distance to ``p``. Returns ``(p, candidates,
    scores)``, best first.
    """
    if landmark is None:
        p = int(src.features[0])
    elif isinstance(landmark, tuple | list):
        p = _vertex_index(landmark[0], src.n, "source landmark")
    else:
        p = _vertex_index(landmark, src.n, "source landmark")
    if isinstance(landmark, tuple | list):
        q0 = _vertex_index(landmark[1], tgt.n, "target landmark")
        cands = torch.tensor([q0])
        scores = landmark_scores(src, tgt, p, cands, use_hks=use_hks, engine=engine)
    else:
        pool = tgt.features
        if not bool((src.features == p).any()):
            # a landmark that is no feature point has no feature image: candidates are
            # the 2-ring local minima of the HKS distance to p (its image is one)
            dh = (tgt.hks - src.hks[p].to(tgt.hks.dtype)).abs().amax(dim=1)
            pool = feature_points(tgt.mesh, -dh, rings=2,
                                  max_features=max(int(max_features), 2 * n_candidates))
        scores = landmark_scores(src, tgt, p, pool, use_hks=use_hks, engine=engine,
                                 samples=score_rows, trees=trees)
        order = torch.argsort(scores, stable=True)
        cands, scores = pool[order], scores[order]
    return p, cands, scores


def _farthest_feature(V: np.ndarray, feats: np.ndarray, used: Sequence[int]) -> int:
    """The feature point farthest (Euclidean) from every vertex in ``used``."""
    d = np.min(np.linalg.norm(V[feats][:, None] - V[list(used)][None], axis=2), axis=1)
    return int(feats[int(np.argmax(d))])


def _greedy_landmarks(src, tgt, lms, total, use_hks, engine):
    """Paper Sec. 4: add (p_i, q_i) among feature pairs minimising the combined error.

    Source candidates are taken in farthest-point order from the existing landmarks (the top
    HKS maxima cluster, e.g. fingertips of one hand)."""
    lms = list(lms)
    V, _ = src.mesh.numpy()
    feats = src.features.numpy()
    while len(lms) < total:
        used = [a for a, _ in lms]
        p2 = _farthest_feature(V, feats, used)
        sc = landmark_scores(src, tgt, [*used, p2], tgt.features, q_fixed=[b for _, b in lms],
                             use_hks=use_hks, engine=engine)
        lms.append((p2, int(tgt.features[int(torch.argmin(sc))])))
    return lms


def _seed_landmarks(src: PreparedShape, tgt: PreparedShape, p: int, ranked: torch.Tensor,
                    p2: int | None, use_hks: bool, limit: int,
                    expand_top: int) -> list[list[tuple[int, int]]]:
    """Landmark hypotheses of the source landmark ``p`` from its ranked target candidates.

    The first ``limit`` distinct candidates ``q`` (5 % of the target's diameter apart, in rank
    order), each giving ``[(p, q)]``; the first ``expand_top`` of them are expanded with the
    twin landmark ``p2`` when there is one (:func:`_expand`: one hypothesis per near-best
    image of ``p2``).
    """
    Vt, _ = tgt.mesh.numpy()
    radius = 0.05 * tgt.mesh.bbox_diagonal()
    return [lm for i, q in enumerate(_distinct(ranked, Vt, radius, limit))
            for lm in _expand(src, tgt, p, q, p2 if i < expand_top else None, use_hks, radius)]


# A piece's near twin is drawn among the samples where the landmark's heat-kernel map at the
# largest time is at least this share of its value at the landmark (thirty-fourth session:
# horse_7's far twin reads <= 3e-4 of it).
_NEAR_TWIN_REACH = 0.01


def _near_reach(opt: _Options) -> float | None:
    """The near twin's reach (:func:`_twin_seeds`): :data:`_NEAR_TWIN_REACH` for a partial
    match that splits candidates by twins, None otherwise (no near twin)."""
    if opt.partial_ratio is None or opt.expand_top <= 0:
        return None
    return _NEAR_TWIN_REACH


def _twin_seeds(src: PreparedShape, tgt: PreparedShape, p: int, ranked: torch.Tensor,
                p2: int | None, pn: int | None,
                opt: _Options) -> list[list[tuple[int, int]]]:
    """:func:`_seed_landmarks` of ``p`` with its twin ``p2`` and, for a partial match, also
    with its *near twin* ``pn`` (None: none): the twin among the samples ``p``'s heat
    reaches (:func:`_near_reach`, found with ``p2`` by :func:`_twins`). The near twin's
    hypotheses follow the far twin's, duplicates dropped; it is used only beside a far twin.

    A piece's far twin may lie beyond ``p``'s heat at the piece's times: its descriptor is
    its HKS alone, which the cut distorts, and neither of its images is right (horse_7 of the
    SHREC'16 cuts: the true image ranks 5907th). A near twin alone breaks pieces whose far
    twin is what separates the mirror maps (RESULTS.md, thirty-fourth session), so both
    are seeded and the choice between their maps is the usual one. Measured on the SHREC'16
    training pieces (RESULTS.md, thirty-fifth session).
    """
    hyp = _seed_landmarks(src, tgt, p, ranked, p2, opt.use_hks, opt.n_candidates,
                          opt.expand_top)
    if p2 is None or pn is None or pn == p2:
        return hyp
    extra = _seed_landmarks(src, tgt, p, ranked, pn, opt.use_hks, opt.n_candidates,
                            opt.expand_top)
    return hyp + [h for h in extra if h not in hyp]


def _feature_seeds(src: PreparedShape, tgt: PreparedShape, pe: int, opt: _Options,
                   score_rows: torch.Tensor | None, extra_rows: torch.Tensor,
                   trees: _TreeCache | None) -> list[list[tuple[int, int]]]:
    """Landmark hypotheses of a further source feature ``pe`` (``match``'s automatic search).

    Its candidates are the ``opt.extra_candidates`` target features of most similar HKS (the
    true image has nearly the same), scored by ``E(pe, q)`` on ``extra_rows``; then
    :func:`_seed_landmarks` with its own twin landmark (:func:`_twin_landmark`).
    """
    pool = tgt.features
    if pool.numel() > opt.extra_candidates:
        dh = (tgt.hks[pool] - src.hks[pe].to(tgt.hks.dtype)).abs().amax(1)
        pool = pool[torch.argsort(dh, stable=True)[:opt.extra_candidates]]
    sc = landmark_scores(src, tgt, pe, pool, use_hks=opt.use_hks, engine=opt.engine,
                         samples=extra_rows, trees=trees)
    ranked = pool[torch.argsort(sc, stable=True)]
    pe2, pen = _twins(src, pe, opt.use_hks, score_rows, src.mesh.bbox_diagonal(),
                      _near_reach(opt))
    return _twin_seeds(src, tgt, pe, ranked, pe2, pen, opt)


def _hypothesis_seeds(src: PreparedShape, tgt: PreparedShape, p: int, cands: torch.Tensor,
                      p2: int | None, auto_landmark: bool, score_rows: torch.Tensor | None,
                      opt: _Options, memo: dict | None = None) -> list[list[tuple[int, int]]]:
    """Every landmark hypothesis of ``match``'s default pipeline, in seeding order.

    Those of the landmark ``p`` (its ranked candidates ``cands``; its twin ``p2``, or one
    found by :func:`_twin_landmark` when ``opt.expand_top > 0``; for a partial match also
    its near twin, :func:`_twin_seeds`), then, for an automatic
    landmark, those of ``opt.source_landmarks - 1`` further source features, each the feature
    farthest from the ones already used (:func:`_feature_seeds`, scored on a quarter of the
    score samples: a farthest-point prefix, still spread). ``memo``: the match's memo (its
    k-d trees, and the further features' seeds, shared by the stages of a staged search).
    """
    reach, diam = _near_reach(opt), src.mesh.bbox_diagonal()
    if p2 is None and opt.expand_top > 0:
        p2, pn = _twins(src, p, opt.use_hks, score_rows, diam, reach)
    else:  # the caller's twin (or none): the near twin alone
        pn = (None if p2 is None or reach is None
              else _twins(src, p, opt.use_hks, score_rows, diam, reach)[1])
    hyp = _twin_seeds(src, tgt, p, cands, p2, pn, opt)
    if auto_landmark and opt.source_landmarks > 1:
        Vs, _ = src.mesh.numpy()
        feats = src.features.numpy()
        used = [p]
        extra_rows = _fps(src, max(100, (opt.score_samples or src.n) // 4))
        trees = None if memo is None else memo.get("trees")
        for _ in range(min(opt.source_landmarks, feats.size) - 1):
            pe = _farthest_feature(Vs, feats, used)
            used.append(pe)
            hyp += _memoised(memo, ("seeds", pe), functools.partial(
                _feature_seeds, src, tgt, pe, opt, score_rows, extra_rows, trees))
    return hyp
