"""The per-pair task: :func:`evaluate_pair` (match, then Princeton evaluation, JSON-able record),
the picklable tasks shipped to executors (:class:`PairTask`, :class:`ShapeTask`) and what runs
them in a worker.
"""

from __future__ import annotations

import dataclasses
import math
import os
import time
import traceback
import uuid
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._arrays import to_numpy
from .caches import _geodesics, _load_dataset, _prepared, _preprocess_of, _TargetGeodesics

#: Fixed threshold grid of the per-pair cumulative curves (so curves can be averaged).
CURVE_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.round(np.linspace(0, 0.25, 51), 6))


# --------------------------------------------------------------------------------------------
# the per-pair task
# --------------------------------------------------------------------------------------------
def _barycentric_errors(geo: _TargetGeodesics, pred: np.ndarray, pair: Any,
                        src_rows: np.ndarray) -> list[np.ndarray]:
    """Errors against barycentric ground truth (SHREC'16 partial): for a true point ``g =
    sum_j w_j c_j`` on a triangle ``(c_1, c_2, c_3)`` of the target,
    ``eps(x) = sum_j w_j d_N(c_j, T(x)) / sqrt(area(N))`` — the geodesic distance field of the
    predicted vertex ``T(x)`` interpolated linearly at ``g`` (fields from the corners, as every
    other error here: the ground truth is the source side). Exact at the corners, an upper
    bound of the distance to ``g`` by at most the triangle's size elsewhere. Returns the direct
    errors, then the symmetric ones when ``pair.gt_sym_bary`` exists."""
    out = []
    for b in (pair.gt_bary, pair.gt_sym_bary):
        if b is None:
            continue
        corners = to_numpy(b.corners)[src_rows]
        w = to_numpy(b.weights)[src_rows]
        parts = geo.errors(pred, [corners[:, j] for j in range(3)])
        out.append(sum(w[:, j] * parts[j] for j in range(3)))
    return out


def _summary(err: np.ndarray) -> dict[str, float]:
    from ..evaluate import summarize

    return summarize(err)


def evaluate_pair(
    pair: Any,
    options: Mapping[str, Any] | None = None,
    *,
    task: str = "match",
    prepare: Mapping[str, Any] | None = None,
    eval_points: int | None = None,
    distortion: bool = False,
    keep_map: bool = False,
) -> dict[str, Any]:
    """Match one pair and evaluate the map: a pure function of its arguments.

    Parameters
    ----------
    pair : torchheat.datasets.Pair
        Must carry ground truth (``gt_src``, ``gt_tgt``).
    options : mapping, optional
        Keyword arguments of :func:`torchheat.match` (``task="match"``) or
        :func:`torchheat.symmetry` (``task="symmetry"``).
    task : {"match", "symmetry"}
        ``"symmetry"``: the map is ``symmetry(pair.source.mesh).map``, judged against
        ``pair.gt_tgt`` (the self-symmetry gt of :func:`~torchheat.datasets.\
tosca_remeshed_5k_symmetry`).
    prepare : mapping, optional
        Keyword arguments of :func:`torchheat.prepare` (e.g. ``k``) for ``task="match"``.
    eval_points : int, optional
        Evaluate on this many evenly spaced ground-truth rows only (quick runs).
    distortion : bool
        Also compute :func:`torchheat.evaluate.geodesic_distortion` (100 FPS samples).
    keep_map : bool
        Add ``"_arrays": {"map", "gt_src", "errors"}`` (numpy) for pictures; not JSON-able.

    Returns
    -------
    dict
        ``name, cls, source, target, task, n_source, n_target, n_eval``;
        ``time_prepare`` (s, preparing the shapes — 0 when memoised), ``time_match`` (s, the
        :func:`~torchheat.match` call), ``time_eval`` (s), ``timings`` (the matcher's stages);
        ``eigensolves``: those run by this call (0 when the shapes' eigenpairs came cached
        or were memoised in this process);
        ``direct``: :func:`~torchheat.evaluate.summarize` of the errors against the direct
        gt (``mean, under_0.25, under_0.1, under_0.05, exact``); ``gt_contradicted``: the
        share of evaluated rows whose ground truth contradicts its neighbours'
        (:func:`~torchheat.evaluate.gt_disagreement` above 0.1) and ``consistent``: the
        ``direct`` summary on the other rows (``None`` if none); ``flip``: the same for the
        flip-aware error (direct or symmetric gt, chosen for the map as a whole) or ``None``
        without symmetric gt; ``flip_choice``: ``"direct"``, ``"symmetric"`` or ``None``;
        ``curve`` / ``flip_curve``: fractions at :data:`CURVE_THRESHOLDS`;
        ``curve_thresholds``; ``landmark`` (first pair) and ``landmarks``; ``orientation``
        (score of the returned map, NaN -> ``None``); ``distortion`` (float or ``None``).

    Examples
    --------
    >>> from torchheat import datasets
    >>> pair = datasets.tosca_remeshed_5k(classes=["wolf"])[0]  # doctest: +SKIP
    >>> r = evaluate_pair(pair, {"method": "paper"}, prepare={"k": 30})  # doctest: +SKIP
    >>> sorted(r["direct"])  # doctest: +SKIP
    ['exact', 'mean', 'under_0.05', 'under_0.1', 'under_0.25']
    """
    from ..evaluate import (
        GT_DISAGREEMENT,
        _gt_disagreement,
        cumulative_curve,
        geodesic_distortion,
    )
    from ..matching import match, symmetry

    opts = dict(options or {})
    if pair.gt_src is None or pair.gt_tgt is None:
        raise ValueError(f"pair {pair.name} has no ground truth")
    t0 = time.perf_counter()
    time_prepare = 0.0
    stats = {"eigensolves": 0}
    if task == "match":
        src = _prepared(pair.source, "source", opts, prepare or {}, stats)
        tgt = _prepared(pair.target, "target", opts, prepare or {}, stats)
        time_prepare = time.perf_counter() - t0
        t1 = time.perf_counter()
        corr = match(src, tgt, **opts)
    elif task == "symmetry":
        t1 = time.perf_counter()
        cached = getattr(pair.source, "data", None) is not None
        stats["eigensolves"] += not cached
        corr = symmetry(pair.source if cached else pair.source.mesh, **opts)
    else:
        raise ValueError(f"unknown task {task!r}; use 'match' or 'symmetry'")
    corr.map  # noqa: B018 - the dense map is computed on first access: time it here
    time_match = time.perf_counter() - t1

    t2 = time.perf_counter()
    fmap = to_numpy(corr.map).astype(np.int64)
    gs = to_numpy(pair.gt_src).astype(np.int64)
    gt = to_numpy(pair.gt_tgt).astype(np.int64)
    gsym = None if pair.gt_sym_tgt is None else to_numpy(pair.gt_sym_tgt).astype(np.int64)
    rows = np.arange(len(gs))
    if eval_points is not None and eval_points < len(gs):
        rows = np.unique(np.linspace(0, len(gs) - 1, int(eval_points)).round().astype(np.int64))
    gs_all, gt_all = gs, gt
    gs, gt = gs[rows], gt[rows]
    gsym = None if gsym is None else gsym[rows]
    geo = _geodesics(pair.target)

    def errors_of(pred: np.ndarray) -> list[np.ndarray]:
        """Errors of a map's images of the ground-truth rows: direct, then symmetric."""
        if getattr(pair, "gt_bary", None) is not None:
            return _barycentric_errors(geo, pred, pair, gs)
        return geo.errors(pred, [gt] if gsym is None else [gt, gsym])

    errs = errors_of(fmap[gs])
    direct = errs[0]
    flip_err, choice = None, None
    if gsym is not None:
        # as torchheat.evaluate.flip_aware_errors: the whole map, ties go to "direct"
        flip_err, choice = (errs[1], "symmetric") if errs[1].mean() < direct.mean() else (
            direct, "direct")
    # rows whose ground truth contradicts its neighbours' (evaluate.gt_disagreement)
    _, F_src = pair.source.mesh.numpy()
    contra = _gt_disagreement(np.asarray(F_src, dtype=np.int64), int(pair.source.mesh.n_vertices),
                              gs_all, gt_all, rows, geo.field,
                              math.sqrt(geo.solver.area)) > GT_DISAGREEMENT
    thr = np.asarray(CURVE_THRESHOLDS)
    dist = None
    if distortion:
        dist = geodesic_distortion(pair.source.mesh, pair.target.mesh, fmap,
                                   solver_src=_geodesics(pair.source).solver,
                                   solver_tgt=geo.solver)
    time_eval = time.perf_counter() - t2
    t3 = time.perf_counter()
    quality = corr.quality  # the map's own evidence (no ground truth); timed apart
    time_quality = time.perf_counter() - t3
    orient = float(corr.orientation)
    rec: dict[str, Any] = {
        "name": pair.name,
        "cls": pair.cls,
        "source": pair.source.name,
        "target": pair.target.name,
        "task": task,
        "n_source": int(pair.source.mesh.n_vertices),
        "n_target": int(pair.target.mesh.n_vertices),
        "n_eval": len(gs),
        "time_prepare": time_prepare,
        "time_match": time_match,
        "time_eval": time_eval,
        "time_quality": time_quality,
        "eigensolves": stats["eigensolves"],
        "timings": {k: float(v) for k, v in corr.info.get("timings", {}).items()},
        "direct": _summary(direct),
        # the direct errors on the rows whose ground truth agrees with its neighbours'
        "gt_contradicted": float(contra.mean()),
        "consistent": _summary(direct[~contra]) if (~contra).any() else None,
        "flip": None if flip_err is None else _summary(flip_err),
        "flip_choice": choice,
        "curve_thresholds": list(CURVE_THRESHOLDS),
        "curve": cumulative_curve(direct, thresholds=thr)[1].tolist(),
        "flip_curve": None if flip_err is None
        else cumulative_curve(flip_err, thresholds=thr)[1].tolist(),
        "landmark": [int(v) for v in corr.landmarks[0]] if corr.landmarks else None,
        "landmarks": [[int(a), int(b)] for a, b in corr.landmarks],
        "orientation": None if math.isnan(orient) else orient,
        "distortion": dist,
        "quality": None if quality is None else quality.quality,
        "suspect": None if quality is None else bool(quality.suspect),
        "defect": None if quality is None else quality.defect,
        "margin": None if quality is None else quality.margin,
        "ambiguous": None if quality is None else bool(quality.ambiguous),
        "search": corr.info.get("search"),
        "near_gap": None if corr.info.get("near_gap") is None else float(corr.info["near_gap"]),
        "tie_break": corr.info.get("tie_break"),
    }
    if quality is not None and quality.ambiguous and corr.has_rival_map:
        # the map the choice passed over, scored like the direct map (only where the choice
        # was ambiguous: its dense map costs one more nearest-neighbour search)
        rec["rival"] = _summary(errors_of(to_numpy(corr.rival_map).astype(np.int64)[gs])[0])
    part = corr.partial_summary()
    if part:  # how a partial match was made: its area ratio, the way kept and why
        rec["partial"] = part
    if keep_map:
        rec["_arrays"] = {"map": fmap, "gt_src": gs,
                          "errors": direct if flip_err is None else flip_err}
    return rec


# --------------------------------------------------------------------------------------------
# tasks shipped to executors
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PairTask:
    """A picklable unit of work: which pair of which dataset, and how to evaluate it."""

    dataset: str
    dataset_args: tuple[tuple[str, Any], ...]
    index: int
    name: str
    key: str
    options_hash: str
    task: str
    match: tuple[tuple[str, Any], ...]
    prepare: tuple[tuple[str, Any], ...]
    eval_points: int | None
    distortion: bool
    keep_map: bool
    cache: str | None = None


def _freeze(d: Mapping[str, Any]) -> tuple[tuple[str, Any], ...]:
    return tuple(sorted((str(k), v) for k, v in d.items()))


@dataclass(frozen=True)
class ShapeTask:
    """A picklable unit of shape preprocessing (Dask runs): one shape of a dataset, its
    eigenbasis computed once per run for every pair that uses it."""

    dataset: str
    dataset_args: tuple[tuple[str, Any], ...]
    index: int
    name: str
    prepare: tuple[tuple[str, Any], ...]
    cache: str | None = None


def _last_line(exc: BaseException) -> str:
    return traceback.format_exception_only(type(exc), exc)[-1].strip()


def _run_task(task: PairTask, *shapes: Mapping[str, Any]) -> dict[str, Any]:
    """Executor entry point: load the pair, evaluate it; exceptions become error records.

    ``shapes``: the results of the pair's :class:`ShapeTask` s (Dask runs), whose eigenbases
    are used instead of solving again."""
    try:
        pc = _load_dataset(task.dataset, dict(task.dataset_args), task.cache, dict(task.prepare))
        pair = _pair_with_shapes(pc, task, shapes) if shapes else pc[task.index]
        if pair.name != task.name:
            raise RuntimeError(f"pair {task.index} is {pair.name}, expected {task.name}")
        rec = evaluate_pair(pair, dict(task.match), task=task.task, prepare=dict(task.prepare),
                            eval_points=task.eval_points, distortion=task.distortion,
                            keep_map=task.keep_map)
    except Exception as exc:  # noqa: BLE001 - reported by run(), the run goes on
        return {"key": task.key, "name": task.name, "error": _last_line(exc)}
    from ..datasets import host_id

    rec = {"key": task.key, "options_hash": task.options_hash, **rec, "host": host_id()}
    if shapes:
        rec["shapes"] = [dict(s["meta"]) for s in shapes]
    return rec


def _pair_with_shapes(pc: Any, task: PairTask, shapes: Sequence[Mapping[str, Any]]) -> Any:
    """The pair, its shapes carrying the eigenbases their shape tasks computed: from the disk
    cache (``task.cache``: the entries must be visible here) or handed over by Dask."""
    from ..datasets import host_id

    for s in shapes:
        if "error" in s:
            raise RuntimeError(f"preprocessing {s['name']} failed: {s['error']}")
    if task.cache:
        a, b = pc.pairs[task.index]
        for i in dict.fromkeys((a, b)):
            if not pc.shapes.is_cached(i):
                meta = next(s["meta"] for s in shapes if s["name"] == pc.shapes.names[i])
                raise RuntimeError(
                    f"the cache entry of {pc.shapes.names[i]} ({meta['path']}), written on "
                    f"{meta['host']}, is not visible on {host_id()}: the cache folder must "
                    "be on storage shared by all workers, at the same path")
        return pc[task.index]
    import torch

    pp = _preprocess_of(dict(task.prepare))
    data = {s["name"]: s["data"] for s in shapes}
    pair = pc[task.index]

    def attach(shape: Any) -> Any:
        d = {k: torch.from_numpy(v) if isinstance(v, np.ndarray) else v
             for k, v in data[shape.name].items()}
        return dataclasses.replace(shape, data=d, preprocess=pp)

    src = attach(pair.source)
    tgt = src if pair.target is pair.source else attach(pair.target)
    return dataclasses.replace(pair, source=src, target=tgt)


def _run_shape(st: ShapeTask) -> dict[str, Any]:
    """Dask task: one shape's preprocessing (the eigensolve), once per run.

    With a cache folder, the disk cache entry (computed and written if missing; the pair tasks
    read it); without, the eigenbasis itself (numpy arrays, ~4.5 MB for a 5k-vertex shape at
    k = 100), which Dask hands to the pair tasks. Errors are returned, not raised, so that
    every pair of the shape gets an error record that names it."""
    from ..datasets import fill_cache_entry, host_id

    _worker_init_once()
    try:
        t0 = time.perf_counter()
        pc = _load_dataset(st.dataset, dict(st.dataset_args), st.cache, dict(st.prepare))
        shapes = pc.shapes
        if shapes.names[st.index] != st.name:
            raise RuntimeError(f"shape {st.index} is {shapes.names[st.index]}, expected "
                               f"{st.name}")
        out: dict[str, Any] = {"name": st.name}
        if st.cache:
            meta = fill_cache_entry(shapes.cache_job(st.index))
        else:
            from ..mesh import load_mesh

            d = _preprocess_of(dict(st.prepare))(load_mesh(shapes.paths[st.index]))
            out["data"] = {k: to_numpy(v) if hasattr(v, "detach") else v for k, v in d.items()}
            meta = {"name": st.name, "computed": True, "seconds": time.perf_counter() - t0,
                    "host": host_id()}
        out["meta"] = {**meta, "id": uuid.uuid4().hex[:12]}
        return out
    except Exception as exc:  # noqa: BLE001 - becomes an error record of each pair
        return {"name": st.name, "error": _last_line(exc)}


def _dask_pair(task: PairTask, *shapes: Mapping[str, Any]) -> dict[str, Any]:
    """Dask task: one pair (:func:`_run_task` in a worker set to one thread)."""
    _worker_init_once()
    return _run_task(task, *shapes)


def _worker_init() -> None:
    from ..datasets import worker_init

    worker_init()  # torch and BLAS at one thread (oversubscribed BLAS: eigensolves 10-30x)
    warnings.filterwarnings("ignore", category=UserWarning, module="torchheat.operators")


_WORKER_READY: list[bool] = []  # set once per Dask worker process


def _worker_init_once() -> None:
    if not _WORKER_READY:
        _worker_init()
        _WORKER_READY.append(True)


def _probe_worker(dataset: str, args: Mapping[str, Any], cache: str | None) -> str | None:
    """Run on every Dask worker before a run: None, or why this worker cannot take part (the
    dataset folder or the cache folder not visible or not writable there)."""
    from ..datasets import host_id

    try:
        _load_dataset(dataset, args)
        if cache:
            Path(cache).mkdir(parents=True, exist_ok=True)
            if not os.access(cache, os.W_OK | os.X_OK):
                return f"{host_id()}: cache folder {cache} is not writable"
    except Exception as exc:  # noqa: BLE001 - reported by the client
        return f"{host_id()}: {_last_line(exc)}"
    return None


def _error_record(task: PairTask, exc: BaseException) -> dict[str, Any]:
    """The error record of a pair whose Dask task raised (its worker died too often, ...)."""
    msg = " ".join(_last_line(exc).split())
    if type(exc).__name__ == "KilledWorker":
        msg += " (killed, or out of memory: see the workers' logs)"
    return {"key": task.key, "name": task.name, "error": msg}
