"""Batch evaluation of the matcher over a dataset, resumable, with a pluggable executor.

A run is described by a small YAML config (see ``configs/``)::

    name: tosca5k                 # output goes to out/<name> unless `output` is given
    dataset: tosca_remeshed_5k    # a loader of torchheat.datasets
    dataset_args: {pairs: test}   # its keyword arguments (root: optional)
    task: match                   # or "symmetry" (self-maps vs. the self-symmetry gt)
    match: {method: refine}       # keyword arguments of torchheat.match / symmetry
    prepare: {k: 100}             # optional keyword arguments of torchheat.prepare
    limit: null                   # optional: only the first N pairs
    eval_points: null             # optional: evaluate on N evenly spaced gt rows only
    pictures: 3                   # colour-transfer PNGs of the first few pairs
    distortion: false             # also compute the geodesic distortion (~0.3 s / pair)

Design
------
* :func:`evaluate_pair` is one pure per-pair task (match, then evaluation) returning a JSON-able
  dict. :func:`run` maps a picklable wrapper of it over the pairs with an **executor**: the
  built-in ``map`` in-process by default, ``workers`` one-process
  :class:`concurrent.futures.ProcessPoolExecutor` s for ``workers > 1`` (torch set to one
  thread per worker; the pairs of one target on one worker), a
  :class:`torchheat.executors.DaskExecutor` (``--dask local:N`` or ``tcp://HOST:PORT``,
  ``executor: {dask: ...}``), or any object with a ``map(fn, iterable)`` method.
  The tasks shipped to an executor are tiny (dataset name, arguments, pair index, options);
  each worker loads its pair from the data folder itself (which must be visible to it, e.g.
  through ``TORCHHEAT_DATA``). Records may arrive in any order: each carries its key.
* **On Dask** each shape is a task of its own (:class:`ShapeTask`: its eigenbasis, once per
  run) and each pair task depends on its two shapes' tasks, which hand it the eigenbases
  through Dask's transfers or, with ``cache``, through the shared disk cache: an all-pairs run
  does O(shapes) eigensolves. At most 4 pair tasks per worker thread are in flight; a worker
  that dies has its tasks (and the eigenbases it held) run again elsewhere; a pair that fails
  becomes an error record; workers that cannot see the data stop the run before it starts
  (:func:`_dask_batches`, :meth:`~torchheat.executors.DaskExecutor.map_shared`).
* **Resumable, crash-safe output**: every finished pair is appended as ONE line of
  ``<output>/results.jsonl`` by this process only (``O_APPEND`` write of the whole line —
  of the lines of the records that finished together — then one ``os.fsync``). On
  start, a trailing partial line (a kill in the middle of a write) is cut off, and pairs whose
  key (pair name + hash of task and match/prepare options) is already in the file are skipped,
  so a run killed at any moment resumes without losing or duplicating a result. The other outputs
  (``summary.md``, ``summary.csv``, ``curves.png``, ``maps/``, ``pictures/``, ``config.yaml``)
  are written to a temporary file and renamed. An exclusive lock on
  ``<output>/.lock`` stops two runs from appending to the same file.
* **Process-local memo caches** (results do not depend on them, only the speed): the prepared
  source and target shapes (:func:`torchheat.prepare`, LRU of 16 each) and, per target shape,
  the geodesic solver with its distance fields (LRU of 8 targets, float32 fields up to
  ``$TORCHHEAT_FIELD_CACHE_MB`` = 512 MB per process: every field of an 11k-vertex target).
  Pending pairs are scheduled grouped by target so consecutive pairs reuse the target's
  fields, and with ``workers > 1`` the pairs of one target run on one worker
  (:class:`_AffinityPool`): a target is prepared, its self-symmetry found and its geodesic
  fields computed once per run, not once per worker.

Evaluation cost (TOSCA 5k, 2 busy cores, heat-method geodesics at ~1.9 ms per source)
------------------------------------------------------------------------------------
The Princeton error needs one distance field per distinct ground-truth image on the target.
The direct and the symmetric ground truth (flip-aware error) are evaluated together from the
union of their sources: cat0-cat2 needs 4323 fields, 7.8 s, against 10.8 s for
:func:`torchheat.evaluate.flip_aware_errors` (two passes); a later pair with the same target
takes 0.01 s (cached fields, 165 MB: the ground-truth images of a target are the same for every
source of its class). In the 10-pair run of ``configs/tosca5k.yaml`` (all targets distinct,
machine under load) evaluation took 6.5-19 s per pair (mean 12.7 s) next to 18.4 s for
prepare + match. Over all 284 test pairs (76 targets at most, scheduled grouped by target) the
evaluation amortises to ~2-3 s per pair.
The numbers are identical to :func:`~torchheat.evaluate.flip_aware_errors` (same fields).

Examples
--------
>>> from torchheat.batch import run, summarize_run  # doctest: +SKIP
>>> results = run("configs/smoke.yaml", workers=2)  # doctest: +SKIP
>>> results[0]["direct"]["under_0.25"]  # doctest: +SKIP
0.8528
"""

from __future__ import annotations

import argparse
import builtins
import concurrent.futures as cf
import contextlib
import csv
import dataclasses
import hashlib
import io
import json
import math
import os
import sys
import time
import traceback
import uuid
import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ._files import atomic_write

__all__ = [
    "CURVE_THRESHOLDS",
    "ConfigError",
    "Executor",
    "PairTask",
    "evaluate_pair",
    "load_config",
    "load_results",
    "main",
    "preprocess",
    "preprocess_main",
    "run",
    "summarize_run",
]

#: Fixed threshold grid of the per-pair cumulative curves (so curves can be averaged).
CURVE_THRESHOLDS: tuple[float, ...] = tuple(float(x) for x in np.round(np.linspace(0, 0.25, 51), 6))

_LOADERS = ("tosca_remeshed_5k", "tosca_remeshed_5k_symmetry", "scape", "tosca_hires", "kids",
            "shrec16_partial",
            "folder")
_TASKS = ("match", "symmetry")
_CONFIG_KEYS = {"name", "dataset", "dataset_args", "task", "match", "prepare", "limit",
                "eval_points", "output", "pictures", "distortion", "cache", "executor"}
_PREPARE_KEYS = {"k", "feature_time", "rtol", "kind", "boundary"}
RESULTS = "results.jsonl"


class ConfigError(ValueError):
    """A missing or invalid run configuration."""


class Executor(Protocol):
    """Anything with ``map(fn, iterable) -> iterable of results`` (order may differ)."""

    def map(self, fn: Callable[[Any], Any], iterable: Iterable[Any]) -> Iterable[Any]: ...


# --------------------------------------------------------------------------------------------
# configuration
# --------------------------------------------------------------------------------------------
def load_config(config: str | os.PathLike | Mapping[str, Any]) -> dict[str, Any]:
    """Read (YAML file) or take (mapping) a run configuration, validate it, fill defaults.

    Parameters
    ----------
    config : path-like or mapping
        A YAML file or an already parsed dict.

    Returns
    -------
    dict
        Keys ``name, dataset, dataset_args, task, match, prepare, limit, eval_points, output,
        pictures, distortion, cache, executor`` (``output`` defaults to ``out/<name>``;
        ``cache``: None or the folder of the per-shape disk cache, ``true`` meaning
        :func:`torchheat.datasets.default_cache_dir`; ``executor``: ``{}`` (in-process),
        ``{"workers": N}`` or ``{"dask": ADDRESS}``).

    Raises
    ------
    ConfigError
        With a one-line explanation.

    Examples
    --------
    >>> cfg = load_config({"name": "x", "dataset": "scape"})
    >>> cfg["task"], cfg["output"], cfg["pictures"]
    ('match', 'out/x', 3)
    """
    if isinstance(config, Mapping):
        raw: Any = dict(config)
        where = "config"
    else:
        path = Path(config)
        where = str(path)
        if not path.is_file():
            raise ConfigError(f"config file {path} not found")
        import yaml

        try:
            raw = yaml.safe_load(path.read_text())
        except yaml.YAMLError as exc:
            raise ConfigError(f"{path}: invalid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{where}: expected a mapping of settings at the top level")
    unknown = set(raw) - _CONFIG_KEYS
    if unknown:
        raise ConfigError(f"{where}: unknown keys {sorted(unknown)}; allowed: "
                          f"{sorted(_CONFIG_KEYS)}")
    cfg: dict[str, Any] = {
        "name": raw.get("name"),
        "dataset": raw.get("dataset"),
        "dataset_args": raw.get("dataset_args") or {},
        "task": raw.get("task", "match"),
        "match": raw.get("match") or {},
        "prepare": raw.get("prepare") or {},
        "limit": raw.get("limit"),
        "eval_points": raw.get("eval_points"),
        "output": raw.get("output"),
        "pictures": raw.get("pictures", 3),
        "distortion": raw.get("distortion", False),
        "cache": raw.get("cache", False),
        "executor": raw.get("executor") or {},
    }
    if not isinstance(cfg["name"], str) or not cfg["name"].strip():
        raise ConfigError(f"{where}: 'name' (a non-empty string) is required")
    if cfg["dataset"] not in _LOADERS:
        raise ConfigError(f"{where}: 'dataset' must be one of {list(_LOADERS)}, "
                          f"got {cfg['dataset']!r}")
    for key in ("dataset_args", "match", "prepare"):
        if not isinstance(cfg[key], dict):
            raise ConfigError(f"{where}: '{key}' must be a mapping")
    if cfg["task"] not in _TASKS:
        raise ConfigError(f"{where}: 'task' must be one of {list(_TASKS)}, got {cfg['task']!r}")
    bad = set(cfg["prepare"]) - _PREPARE_KEYS
    if bad:
        raise ConfigError(f"{where}: unknown prepare options {sorted(bad)}; allowed: "
                          f"{sorted(_PREPARE_KEYS)}")
    for key in ("limit", "eval_points"):
        v = cfg[key]
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
            raise ConfigError(f"{where}: '{key}' must be a positive integer or null, got {v!r}")
    p = cfg["pictures"]
    if isinstance(p, bool) or not isinstance(p, int) or p < 0:
        raise ConfigError(f"{where}: 'pictures' must be an integer >= 0, got {p!r}")
    if not isinstance(cfg["distortion"], bool):
        raise ConfigError(f"{where}: 'distortion' must be true or false")
    c = cfg["cache"]
    if c is None or c is False:
        cfg["cache"] = None
    elif c is True:
        from .datasets import default_cache_dir

        cfg["cache"] = str(default_cache_dir())
    elif isinstance(c, str) and c.strip():
        cfg["cache"] = c
    else:
        raise ConfigError(f"{where}: 'cache' must be true, false or a folder, got {c!r}")
    cfg["executor"] = _check_executor(cfg["executor"], where)
    if cfg["output"] is None:
        cfg["output"] = f"out/{cfg['name']}"
    cfg["output"] = str(cfg["output"])
    if cfg["dataset"] == "folder" and "path" not in cfg["dataset_args"]:
        raise ConfigError(f"{where}: dataset 'folder' needs dataset_args.path and .pairs")
    return cfg


def _check_executor(spec: Any, where: str) -> dict[str, Any]:
    """``executor: {dask: ADDRESS}`` or ``{workers: N}`` (or nothing: in-process)."""
    if not isinstance(spec, dict) or set(spec) - {"dask", "workers"} or len(spec) > 1:
        raise ConfigError(f"{where}: 'executor' must be {{dask: ADDRESS}} (local, local:N or "
                          f"tcp://HOST:PORT) or {{workers: N}}, got {spec!r}")
    if "workers" in spec:
        n = spec["workers"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ConfigError(f"{where}: executor.workers must be an integer >= 1, got {n!r}")
    if "dask" in spec:
        from .executors import ExecutorError, parse_dask_address

        try:
            parse_dask_address(spec["dask"])
        except ExecutorError as exc:
            raise ConfigError(f"{where}: executor.dask: {exc}") from None
    return dict(spec)


def options_hash(cfg: Mapping[str, Any]) -> str:
    """Hash (12 hex characters) of what determines a pair's result: task, match, prepare and
    eval_points settings.

    Examples
    --------
    >>> a = options_hash({"task": "match", "match": {"method": "paper"}})
    >>> a == options_hash({"task": "match", "match": {"method": "paper"}, "prepare": {}})
    True
    """
    payload = json.dumps(
        {"task": cfg.get("task", "match"), "match": dict(cfg.get("match") or {}),
         "prepare": dict(cfg.get("prepare") or {}), "eval_points": cfg.get("eval_points")},
        sort_keys=True, default=str,
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:12]


# --------------------------------------------------------------------------------------------
# process-local caches (memoisation only: results never depend on them)
# --------------------------------------------------------------------------------------------
class _LRU(OrderedDict):
    def __init__(self, maxsize: int) -> None:
        super().__init__()
        self.maxsize = maxsize

    def get_or(self, key: Any, make: Callable[[], Any]) -> Any:
        if key in self:
            self.move_to_end(key)
            return self[key]
        value = make()
        self[key] = value
        while len(self) > self.maxsize:
            _, old = self.popitem(last=False)
            if hasattr(old, "release"):
                old.release()
        return value


_BASES = _LRU(16)  # per shape and preparation: the eigensolve both roles share
_PREPARED = {"source": _LRU(16), "target": _LRU(16)}
_GEODESICS = _LRU(8)
_DATASETS = _LRU(4)
_FIELD_BUDGET = int(float(os.environ.get("TORCHHEAT_FIELD_CACHE_MB", "512")) * 2**20)


class _TargetGeodesics:
    """A :class:`~torchheat.evaluate.GeodesicSolver` and the distance fields computed so far."""

    cached_bytes = 0  # over all instances alive in the process-wide LRU

    def __init__(self, mesh: Any) -> None:
        from .evaluate import GeodesicSolver

        self.solver = GeodesicSolver(mesh)
        self.fields: dict[int, np.ndarray] = {}
        self.nbytes = 0

    def release(self) -> None:
        _TargetGeodesics.cached_bytes -= self.nbytes
        self.fields.clear()
        self.nbytes = 0

    def field(self, s: int) -> np.ndarray:
        """Distances from vertex ``s`` to every vertex, float32 whether kept or not (half the
        memory of float64: a 10k-vertex target's every field fits the default budget; the
        rounding, ~6e-8 relative, is far below the heat method's own error)."""
        f = self.fields.get(s)
        if f is None:
            f = self.solver.distances(np.array([s]))[0].astype(np.float32)
            if _TargetGeodesics.cached_bytes + f.nbytes > _FIELD_BUDGET:
                for other in list(_GEODESICS.values()):  # least recently used first
                    if _TargetGeodesics.cached_bytes + f.nbytes <= _FIELD_BUDGET:
                        break
                    if other is not self:
                        other.release()
            if _TargetGeodesics.cached_bytes + f.nbytes <= _FIELD_BUDGET:
                self.fields[s] = f
                self.nbytes += f.nbytes
                _TargetGeodesics.cached_bytes += f.nbytes
        return f

    def errors(self, pred: np.ndarray, gts: Sequence[np.ndarray]) -> list[np.ndarray]:
        """``d(gt[x], pred[x]) / sqrt(area)`` for each gt array, one field per unique gt
        source over all of them (same convention as :func:`torchheat.evaluate.geodesic_errors`:
        the ground truth is the source side)."""
        k = len(pred)
        a = np.concatenate([np.asarray(g, dtype=np.int64) for g in gts])
        b = np.tile(np.asarray(pred, dtype=np.int64), len(gts))
        out = np.zeros(len(a), dtype=np.float64)
        differ = np.flatnonzero(a != b)
        order = differ[np.argsort(a[differ], kind="stable")]
        uniq, starts = np.unique(a[order], return_index=True)
        ends = np.append(starts[1:], len(order))
        for s, lo, hi in zip(uniq.tolist(), starts, ends, strict=True):
            idx = order[lo:hi]
            out[idx] = self.field(int(s))[b[idx]]
        out /= math.sqrt(self.solver.area)
        return [out[i * k:(i + 1) * k] for i in range(len(gts))]


def _shape_key(shape: Any) -> tuple[str, str, int]:
    return (shape.name, str(getattr(shape, "path", "")), int(shape.mesh.n_vertices))


def _geodesics(shape: Any) -> _TargetGeodesics:
    return _GEODESICS.get_or(_shape_key(shape), lambda: _TargetGeodesics(shape.mesh))


def _prepared(shape: Any, role: str, match_opts: Mapping[str, Any],
              prep_opts: Mapping[str, Any], stats: dict[str, int] | None = None) -> Any:
    """Prepared shape for one role. Sources are never modified by :func:`torchheat.match`;
    targets get the source's time samples (a stateless re-plan), so a target is only ever
    reused as a target. ``stats["eigensolves"]`` counts the eigensolves run here (none for a
    shape with cached eigenpairs or already prepared in this process)."""
    from .heat import threads
    from .matching import prepare

    times = match_opts.get("times")
    kw = dict(prep_opts)
    kw["times"] = "adaptive" if times is None else times
    kw["max_features"] = match_opts.get("max_features", 50)
    key = (_shape_key(shape), json.dumps(kw, sort_keys=True, default=str))

    def make() -> Any:
        # one eigensolve per shape: each role gets a copy (its own timings) sharing the
        # caches that do not depend on the times (self-symmetries, functional-map operators:
        # a shape in both roles pays once); match re-times a target on its own private copy
        from .matching.prepared import _role_copy

        return _role_copy(_BASES.get_or(key, make_base))

    def make_base() -> Any:
        cached = getattr(shape, "data", None) is not None  # eigenbasis from the disk cache
        if not cached and stats is not None:
            stats["eigensolves"] = stats.get("eigensolves", 0) + 1
        with threads(match_opts.get("num_threads")):
            return prepare(shape if cached else shape.mesh, **kw)

    return _PREPARED[role].get_or(key, make)


def clear_caches() -> None:
    """Drop the process-local caches (prepared shapes, geodesic fields, datasets)."""
    for g in _GEODESICS.values():
        g.release()
    for c in (*_PREPARED.values(), _BASES, _GEODESICS, _DATASETS):
        c.clear()


# --------------------------------------------------------------------------------------------
# the per-pair task
# --------------------------------------------------------------------------------------------
def _to_np(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


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
        corners = _to_np(b.corners)[src_rows]
        w = _to_np(b.weights)[src_rows]
        parts = geo.errors(pred, [corners[:, j] for j in range(3)])
        out.append(sum(w[:, j] * parts[j] for j in range(3)))
    return out


def _summary(err: np.ndarray) -> dict[str, float]:
    from .evaluate import summarize

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
        gt (``mean, under_0.25, under_0.1, under_0.05, exact``); ``flip``: the same for the
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
    from .evaluate import cumulative_curve, geodesic_distortion
    from .matching import match, symmetry

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
    fmap = _to_np(corr.map).astype(np.int64)
    gs = _to_np(pair.gt_src).astype(np.int64)
    gt = _to_np(pair.gt_tgt).astype(np.int64)
    gsym = None if pair.gt_sym_tgt is None else _to_np(pair.gt_sym_tgt).astype(np.int64)
    if eval_points is not None and eval_points < len(gs):
        rows = np.unique(np.linspace(0, len(gs) - 1, int(eval_points)).round().astype(np.int64))
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
    }
    if quality is not None and quality.ambiguous and corr.has_rival_map:
        # the map the choice passed over, scored like the direct map (only where the choice
        # was ambiguous: its dense map costs one more nearest-neighbour search)
        rec["rival"] = _summary(errors_of(_to_np(corr.rival_map).astype(np.int64)[gs])[0])
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


def _preprocess_of(prep: Mapping[str, Any]) -> Any:
    """The :class:`~torchheat.datasets.Preprocess` of a config's ``prepare`` options."""
    from .datasets import Preprocess
    from .eigen import DEFAULT_EIGENPAIRS

    return Preprocess(k=int(prep.get("k", DEFAULT_EIGENPAIRS)), kind=prep.get("kind", "cotan"),
                      boundary=prep.get("boundary", "neumann"))


def _load_dataset(dataset: str, args: Mapping[str, Any], cache: str | None = None,
                  prep: Mapping[str, Any] | None = None) -> Any:
    """The pair collection of a config (memoised per process). With ``cache`` (a folder) its
    shapes carry the eigenbasis, cached on disk by :class:`~torchheat.datasets.Preprocess`
    with the ``prepare`` options' ``k``, ``kind`` and ``boundary``."""
    from . import datasets

    prep = dict(prep or {})

    def make() -> Any:
        kw = dict(args)
        if cache:
            kw["preprocess"] = _preprocess_of(prep)
            kw["cache_dir"] = cache
        if dataset == "folder":
            pairs = kw.pop("pairs", None)
            gt = kw.pop("gt", "identity")
            if not pairs:
                raise ConfigError("dataset 'folder' needs dataset_args.pairs: [[a, b], ...]")
            shapes = datasets.folder(kw.pop("path"), **kw)
            return datasets.pairs_from_list(shapes, [tuple(p) for p in pairs], gt=gt)
        loader = getattr(datasets, dataset)
        try:
            return loader(**kw)
        except TypeError as exc:
            raise ConfigError(f"dataset_args for {dataset}: {exc}") from None

    return _DATASETS.get_or(_dataset_key(dataset, args, cache, prep), make)


def _dataset_key(dataset: str, args: Mapping[str, Any], cache: str | None,
                 prep: Mapping[str, Any]) -> tuple:
    extra = {k: prep.get(k) for k in ("k", "kind", "boundary")} if cache else {}
    return (dataset, json.dumps(dict(args), sort_keys=True, default=str), cache,
            json.dumps(extra, sort_keys=True))


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
    from .datasets import host_id

    rec = {"key": task.key, "options_hash": task.options_hash, **rec, "host": host_id()}
    if shapes:
        rec["shapes"] = [dict(s["meta"]) for s in shapes]
    return rec


def _pair_with_shapes(pc: Any, task: PairTask, shapes: Sequence[Mapping[str, Any]]) -> Any:
    """The pair, its shapes carrying the eigenbases their shape tasks computed: from the disk
    cache (``task.cache``: the entries must be visible here) or handed over by Dask."""
    from .datasets import host_id

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
    from .datasets import fill_cache_entry, host_id

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
            from .mesh import load_mesh

            d = _preprocess_of(dict(st.prepare))(load_mesh(shapes.paths[st.index]))
            out["data"] = {k: _to_np(v) if hasattr(v, "detach") else v for k, v in d.items()}
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
    from .datasets import worker_init

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
    from .datasets import host_id

    try:
        _load_dataset(dataset, args)
        if cache:
            Path(cache).mkdir(parents=True, exist_ok=True)
            if not os.access(cache, os.W_OK | os.X_OK):
                return f"{host_id()}: cache folder {cache} is not writable"
    except Exception as exc:  # noqa: BLE001 - reported by the client
        return f"{host_id()}: {_last_line(exc)}"
    return None


# --------------------------------------------------------------------------------------------
# results file
# --------------------------------------------------------------------------------------------
def load_results(path: str | os.PathLike, repair: bool = True) -> list[dict[str, Any]]:
    """Read ``results.jsonl``; a trailing partial line (killed mid-write) is ignored and, with
    ``repair``, cut off the file. Lines that are not valid JSON are skipped with a warning.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "r.jsonl"
    >>> _ = p.write_text('{"key": "a"}\\n{"key": "b", "x"')
    >>> [r["key"] for r in load_results(p)], p.read_text()
    (['a'], '{"key": "a"}\\n')
    """
    p = Path(path)
    if not p.is_file():
        return []
    data = p.read_bytes()
    end = data.rfind(b"\n") + 1  # 0 when there is no complete line
    if end < len(data) and repair:
        with open(p, "r+b") as f:
            f.truncate(end)
            f.flush()
            os.fsync(f.fileno())
    out = []
    for i, line in enumerate(data[:end].split(b"\n")):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            warnings.warn(f"{p}: skipping unreadable line {i + 1}", stacklevel=2)
            continue
        if isinstance(rec, dict) and "key" in rec:
            out.append(rec)
    return out


def _append_lines(path: Path, recs: Sequence[Mapping[str, Any]]) -> None:
    """Append records, one JSON line each, in one ``O_APPEND`` write and one ``fsync`` (a
    batch of records that finished together costs one fsync)."""
    data = b"".join((json.dumps(r, allow_nan=False, default=_json_default) + "\n").encode()
                    for r in recs)
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        view = memoryview(data)
        while view:
            n = os.write(fd, view)
            view = view[n:]
        os.fsync(fd)
    finally:
        os.close(fd)


def _json_default(x: Any) -> Any:
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    raise TypeError(f"not JSON serialisable: {type(x).__name__}")


def _write_text(path: Path, text: str) -> None:
    atomic_write(path, lambda t: t.write_text(text))


@contextlib.contextmanager
def _lock(output: Path) -> Iterator[None]:
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    fd = os.open(output / ".lock", os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise RuntimeError(f"another run is writing to {output} (lock held)") from None
        yield
    finally:
        os.close(fd)


# --------------------------------------------------------------------------------------------
# run
# --------------------------------------------------------------------------------------------
def _in_completion_order(executor: Any, fn: Callable, tasks: list) -> Iterator[dict]:
    if executor is None:
        yield from builtins.map(fn, tasks)
    elif isinstance(executor, cf.Executor):
        futures = [executor.submit(fn, t) for t in tasks]
        try:
            for fut in cf.as_completed(futures):
                yield fut.result()
        finally:
            for fut in futures:
                fut.cancel()
    else:
        yield from executor.map(fn, tasks)


class _AffinityPool:
    """``workers`` one-process pools that run the pairs of one target on the same worker.

    A worker prepares a target once, with everything the matcher caches on it (the
    target's self-symmetry behind the mirror hypothesis: a whole self-match) and the
    geodesic fields of its evaluation; a shared pool hands consecutive pairs of a target to
    alternating workers, each paying those costs. A free worker takes the next pair of its
    own target, else the next target nobody has started, else a pair of the target with
    the most pairs left (so no worker idles while pairs remain). One pair per worker is in
    flight; records come in completion order. Results do not depend on the scheduling.
    """

    def __init__(self, workers: int, initializer: Callable[[], None] | None = None) -> None:
        self.pools = [cf.ProcessPoolExecutor(max_workers=1, initializer=initializer)
                      for _ in range(int(workers))]

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        for pool in self.pools:
            pool.shutdown(wait=wait, cancel_futures=cancel_futures)

    def run(self, fn: Callable, tasks: Sequence, key: Callable[[Any], str]) -> Iterator[Any]:
        """``fn(task)`` of every task (``key``: its target), in completion order."""
        groups: OrderedDict[str, list] = OrderedDict()
        for t in tasks:
            groups.setdefault(key(t), []).append(t)
        started: set[str] = set()
        own: list[str | None] = [None] * len(self.pools)

        def take(w: int) -> Any:
            g = own[w]
            if g is None or not groups.get(g):
                fresh = [k for k, v in groups.items() if v and k not in started]
                busy = [k for k, v in groups.items() if v]
                if not busy:
                    return None
                g = fresh[0] if fresh else max(busy, key=lambda k: len(groups[k]))
                own[w] = g
                started.add(g)
            return groups[g].pop(0)

        running: dict[cf.Future, int] = {}
        try:
            for w, pool in enumerate(self.pools):
                t = take(w)
                if t is not None:
                    running[pool.submit(fn, t)] = w
            while running:
                done, _ = cf.wait(list(running), return_when=cf.FIRST_COMPLETED)
                for fut in done:
                    w = running.pop(fut)
                    t = take(w)
                    if t is not None:
                        running[self.pools[w].submit(fn, t)] = w
                    yield fut.result()
        finally:
            for fut in running:
                fut.cancel()


def _as_dask(executor: Any) -> Any:
    """The :class:`~torchheat.executors.DaskExecutor` of ``executor`` (one, or a
    ``distributed.Client`` wrapped), else None."""
    if executor is None:
        return None
    from .executors import DaskExecutor

    if isinstance(executor, DaskExecutor):
        return executor
    cls = type(executor)
    if cls.__module__.split(".")[0] == "distributed" and cls.__name__ == "Client":
        return DaskExecutor(executor)
    return None


def _dask_batches(ex: Any, cfg: Mapping[str, Any], todo: list[PairTask]) -> Iterator[list]:
    """Records of ``todo`` on Dask, in batches of those that finished together.

    For ``task: match`` each shape is preprocessed by a :class:`ShapeTask` of its own, once
    per run, and every pair task depends on its two shapes' tasks: an all-pairs run does one
    eigensolve per shape (plus one per shape recomputed after its worker died). The
    eigenbases reach the pair tasks through the disk cache when the config has one (entries
    written by the shape tasks, read by the pair tasks: the folder must be shared), else
    through Dask's own data transfers (nothing written; held by the workers until the last
    pair of the shape is done)."""
    pc = _load_dataset(cfg["dataset"], cfg["dataset_args"], cfg.get("cache"), cfg["prepare"])
    with_shapes = cfg["task"] == "match"
    shared: dict[int, ShapeTask] = {}

    def needs(t: PairTask) -> tuple[int, ...]:
        return tuple(dict.fromkeys(pc.pairs[t.index])) if with_shapes else ()

    for t in todo:
        for i in needs(t):
            shared.setdefault(i, ShapeTask(cfg["dataset"], _freeze(cfg["dataset_args"]), i,
                                           pc.shapes.names[i], _freeze(cfg["prepare"]),
                                           cfg.get("cache")))

    def name(x: Any) -> str:
        return f"pair-{x.name}" if isinstance(x, PairTask) else f"shape-{shared[x].name}"

    for batch in ex.map_shared(_dask_pair, todo, needs, _run_shape, shared, name=name):
        yield [rec if exc is None else _error_record(task, exc) for task, rec, exc in batch]


def _error_record(task: PairTask, exc: BaseException) -> dict[str, Any]:
    """The error record of a pair whose Dask task raised (its worker died too often, ...)."""
    msg = " ".join(_last_line(exc).split())
    if type(exc).__name__ == "KilledWorker":
        msg += " (killed, or out of memory: see the workers' logs)"
    return {"key": task.key, "name": task.name, "error": msg}


def _preflight(ex: Any, cfg: Mapping[str, Any]) -> None:
    """Every worker can import torchheat and see the data (and the cache folder), or a clear
    error before any task runs; a warning for workers with several threads."""
    from .executors import ExecutorError

    args = dict(cfg["dataset_args"])
    replies = ex.client.run(_probe_worker, cfg["dataset"], args, cfg.get("cache"),
                            on_error="return")
    bad = []
    for worker, reply in sorted(replies.items()):
        if isinstance(reply, BaseException):
            bad.append(f"{worker}: cannot run torchheat there ({_last_line(reply)}); install "
                       "torchheat (the same version) on every worker")
        elif reply is not None:
            bad.append(f"{worker} ({reply})")
    if bad:
        raise ExecutorError(f"{len(bad)} of {len(replies)} Dask workers cannot take part: "
                            + "; ".join(bad[:3]) + (" ..." if len(bad) > 3 else "")
                            + ". The dataset (and cache) folders must be visible on every "
                            "worker at the configured path or at its $TORCHHEAT_DATA")
    warning = ex.check_threads()
    if warning:
        warnings.warn(warning, stacklevel=3)


def _tasks(cfg: Mapping[str, Any]) -> list[PairTask]:
    pc = _load_dataset(cfg["dataset"], cfg["dataset_args"], cfg.get("cache"), cfg["prepare"])
    names = pc.names
    n = len(names) if cfg["limit"] is None else min(len(names), int(cfg["limit"]))
    h = options_hash(cfg)
    return [
        PairTask(cfg["dataset"], _freeze(cfg["dataset_args"]), i, names[i], f"{names[i]}#{h}",
                 h, cfg["task"], _freeze(cfg["match"]), _freeze(cfg["prepare"]),
                 cfg["eval_points"], bool(cfg["distortion"]), i < int(cfg["pictures"]),
                 cfg.get("cache"))
        for i in range(n)
    ]


def _target_of(task: PairTask) -> str:
    pc = _DATASETS.get(_dataset_key(task.dataset, dict(task.dataset_args), task.cache,
                                    dict(task.prepare)))
    if pc is None:
        return task.name
    return pc.shapes.names[pc.pairs[task.index][1]]


def run(
    config: str | os.PathLike | Mapping[str, Any],
    workers: int = 1,
    executor: Executor | None = None,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Evaluate every pair of a config, appending to ``<output>/results.jsonl``; resumable.

    Parameters
    ----------
    config : path-like or mapping
        See :func:`load_config` (a mapping may override e.g. ``output`` or ``limit``).
    workers : int
        ``> 1``: that many local worker processes (one torch thread each; the pairs of one
        target run on the same worker, see :class:`_AffinityPool`). Ignored when
        ``executor`` is given.
    executor : object with ``map(fn, iterable)``, optional
        Any executor; a :class:`concurrent.futures.Executor` is driven through ``submit`` so
        records are written as they finish. A :class:`torchheat.executors.DaskExecutor` (or a
        ``distributed.Client``) runs one task per shape and one per pair (see
        :func:`_dask_batches`). Default: the config's ``executor`` (``{dask: ADDRESS}``: a
        DaskExecutor made and closed here, ``{workers: N}``), else in-process.
    progress : bool
        tqdm progress bar on stderr.

    Returns
    -------
    list of dict
        The records of this config's pairs (dataset order), old and new; failed pairs are
        reported on stderr and left out (a re-run retries them).

    Notes
    -----
    Whatever the executor, the records are written by this process only, one line per pair
    (a pair delivered twice is written once), and a killed run resumes where it stopped.

    Examples
    --------
    >>> results = run("configs/smoke.yaml", progress=False)  # doctest: +SKIP
    >>> len(results)  # doctest: +SKIP
    3
    >>> results = run({**load_config("configs/smoke.yaml"),  # doctest: +SKIP
    ...                "executor": {"dask": "local:2"}})
    """
    from tqdm import tqdm

    cfg = load_config(config)
    out = Path(cfg["output"])
    out.mkdir(parents=True, exist_ok=True)
    failed: list[dict[str, Any]] = []
    with _lock(out), contextlib.ExitStack() as owned:
        import yaml

        _write_text(out / "config.yaml", yaml.safe_dump(cfg, sort_keys=False))
        tasks = _tasks(cfg)
        path = out / RESULTS
        by_key = {r["key"]: r for r in load_results(path)}
        todo = [t for t in tasks if t.key not in by_key]
        todo.sort(key=_target_of)  # stable: consecutive pairs share the target's fields
        dask_ex = _as_dask(executor)
        if executor is None and todo:
            if "dask" in cfg["executor"]:
                from .executors import DaskExecutor

                dask_ex = owned.enter_context(DaskExecutor(cfg["executor"]["dask"]))
            elif workers <= 1:
                workers = int(cfg["executor"].get("workers", workers))
        if dask_ex is not None:
            if todo:
                _preflight(dask_ex, cfg)
            batches = _dask_batches(dask_ex, cfg, todo)
        else:
            if executor is None and workers > 1 and len(todo) > 1:
                pool = _AffinityPool(int(workers), initializer=_worker_init)
                owned.callback(pool.shutdown, wait=True, cancel_futures=True)
                records = pool.run(_run_task, todo, key=_target_of)
            else:
                records = _in_completion_order(executor, _run_task, todo)
            batches = ([r] for r in records)
        bar = owned.enter_context(tqdm(
            total=len(tasks), initial=len(tasks) - len(todo), file=sys.stderr,
            disable=not progress, desc=cfg["name"], unit="pair", dynamic_ncols=True))
        solves = _Eigensolves()
        for recs in batches:
            fresh = []
            for rec in recs:
                if "error" in rec:
                    failed.append(rec)
                    tqdm.write(f"{rec['name']}: failed: {rec['error']}", file=sys.stderr)
                    bar.update(1)
                    continue
                arrays = rec.pop("_arrays", None)
                if arrays is not None:
                    atomic_write(out / "maps" / f"{rec['name']}.npz",
                                 lambda t, a=arrays: np.savez(t, **a))
                if rec["key"] in by_key:  # an executor delivered a pair twice
                    continue
                by_key[rec["key"]] = rec
                fresh.append(rec)
                solves.add(rec)
            if fresh:
                _append_lines(path, fresh)
                bar.update(len(fresh))
                d = fresh[-1]["direct"]
                bar.set_postfix_str(f"{fresh[-1]['name']} <0.25: {100 * d['under_0.25']:.0f}%"
                                    + solves.postfix())
        bar.close()
        results = [by_key[t.key] for t in tasks if t.key in by_key]
        if results:
            summarize_run(results, out, config=cfg)
    if todo and progress:
        print(solves.line(), file=sys.stderr)
    if failed:
        print(f"{len(failed)} of {len(tasks)} pairs failed (re-run to retry)", file=sys.stderr)
    return results


class _Eigensolves:
    """Eigensolves of a run, from its records: in pair tasks, and in shape tasks (Dask runs;
    each distinct shape-task result counted once)."""

    def __init__(self) -> None:
        self.in_pairs = 0
        self.shapes: dict[str, bool] = {}  # shape task result id -> it ran an eigensolve

    def add(self, rec: Mapping[str, Any]) -> None:
        self.in_pairs += int(rec.get("eigensolves", 0))
        for meta in rec.get("shapes") or ():
            self.shapes[meta["id"]] = bool(meta["computed"])

    def postfix(self) -> str:
        return f", {self.in_pairs + sum(self.shapes.values())} eigensolves"

    def line(self) -> str:
        n = sum(self.shapes.values())
        return (f"eigensolves this run: {n + self.in_pairs} ({n} in {len(self.shapes)} shape "
                f"tasks, {self.in_pairs} in pair tasks)")


# --------------------------------------------------------------------------------------------
# summary
# --------------------------------------------------------------------------------------------
_COLUMNS = ("level", "name", "pairs", "mean_error", "pct_under_0.25", "pct_under_0.1",
            "pct_under_0.05", "flip_pct_under_0.25", "flip_mean_error", "symmetric_choices",
            "time_match_s", "time_eval_s", "time_per_pair_s", "distortion")


def _nanmean(vals: Sequence[float | None]) -> float | None:
    v = [float(x) for x in vals if x is not None and not math.isnan(float(x))]
    return float(np.mean(v)) if v else None


def _row(level: str, name: str, recs: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    def d(key: str, scale: float = 1.0, sub: str = "direct") -> float | None:
        m = _nanmean([None if r.get(sub) is None else r[sub][key] for r in recs])
        return None if m is None else m * scale

    flips = [r for r in recs if r.get("flip") is not None]
    return {
        "level": level,
        "name": name,
        "pairs": len(recs),
        "mean_error": d("mean"),
        "pct_under_0.25": d("under_0.25", 100),
        "pct_under_0.1": d("under_0.1", 100),
        "pct_under_0.05": d("under_0.05", 100),
        "flip_pct_under_0.25": d("under_0.25", 100, "flip"),
        "flip_mean_error": d("mean", 1.0, "flip"),
        "symmetric_choices": sum(r.get("flip_choice") == "symmetric" for r in flips)
        if flips else None,
        "time_match_s": _nanmean([r.get("time_prepare", 0.0) + r["time_match"] for r in recs]),
        "time_eval_s": _nanmean([r["time_eval"] for r in recs]),
        "time_per_pair_s": _nanmean([r.get("time_prepare", 0.0) + r["time_match"]
                                     + r["time_eval"] for r in recs]),
        "distortion": _nanmean([r.get("distortion") for r in recs]),
        "quality": _nanmean([r.get("quality") for r in recs]),
        "suspect": sum(bool(r.get("suspect")) for r in recs)
        if any(r.get("suspect") is not None for r in recs) else None,
        "ambiguous": sum(bool(r.get("ambiguous")) for r in recs)
        if any(r.get("ambiguous") is not None for r in recs) else None,
        # ambiguous pairs whose rival map (Correspondence.rival_map) is right (>= 90 % < 0.25)
        "rival_right": sum((r.get("rival") or {}).get("under_0.25", 0.0) >= 0.9 for r in recs)
        if any(r.get("ambiguous") is not None for r in recs) else None,
        # maps of a staged search kept from its first stage (match(staged=True))
        "first_stage": sum(r.get("search") == "first stage" for r in recs)
        if any(r.get("search") for r in recs) else None,
    }


def _table_rows(results: Sequence[Mapping[str, Any]]) -> list[dict[str, Any]]:
    rows = [_row("overall", "all", results)]
    classes: dict[str, list] = {}
    for r in results:
        classes.setdefault(r["cls"], []).append(r)
    rows += [_row("class", c, rs) for c, rs in classes.items()]
    rows += [_row("pair", r["name"], [r]) for r in results]
    return rows


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return str(v)


def _markdown(rows: list[dict[str, Any]], title: str) -> str:
    head = ["name", "pairs", "mean err", "% <0.25", "% <0.1", "% <0.05", "flip % <0.25",
            "sym. chosen", "match s", "eval s", "s / pair"]
    keys = ["name", "pairs", "mean_error", "pct_under_0.25", "pct_under_0.1", "pct_under_0.05",
            "flip_pct_under_0.25", "symmetric_choices", "time_match_s", "time_eval_s",
            "time_per_pair_s"]
    digits = {"mean_error": 4, "pct_under_0.25": 1, "pct_under_0.1": 1, "pct_under_0.05": 1,
              "flip_pct_under_0.25": 1, "time_match_s": 2, "time_eval_s": 2,
              "time_per_pair_s": 2}
    if any(r.get("quality") is not None for r in rows):
        head += ["quality", "suspect", "ambiguous", "rival right"]
        keys += ["quality", "suspect", "ambiguous", "rival_right"]
        digits["quality"] = 2
    if any(r.get("first_stage") is not None for r in rows):
        head.append("1st stage")
        keys.append("first_stage")
    if any(r["distortion"] is not None for r in rows):
        head.append("distortion")
        keys.append("distortion")
        digits["distortion"] = 4
    lines = [f"# {title}", "",
             "Errors: geodesic distance to the ground truth / sqrt(target area) (Kim et al. "
             "2011), averaged per pair, then over pairs (every pair weighs the same). "
             "Flip-aware: the direct or the symmetric ground truth, whichever fits the whole "
             "map better. Times: prepare + match, evaluation. Quality: the map's own evidence "
             "(0..1, no ground truth; torchheat.matching.quality), suspect: maps below 0.25, "
             "ambiguous: maps whose best rival (a different whole map) scored within 0.15, "
             "rival right: ambiguous maps whose rival map is right (>= 90 % under 0.25); "
             "1st stage: maps kept from the first stage of the staged search.",
             ""]
    for level, label in (("overall", "Overall"), ("class", "Per class"), ("pair", "Per pair")):
        sel = [r for r in rows if r["level"] == level]
        if not sel:
            continue
        lines += [f"## {label}", "", "| " + " | ".join(head) + " |",
                  "|" + "---|" * len(head)]
        for r in sel:
            lines.append("| " + " | ".join(_fmt(r[k], digits.get(k, 3)) for k in keys) + " |")
        lines.append("")
    return "\n".join(lines)


def _mean_curves(results: Sequence[Mapping[str, Any]]) -> dict[str, tuple]:
    curves: dict[str, tuple] = {}
    for key, label in (("curve", "direct"), ("flip_curve", "flip-aware")):
        cs = [(r["curve_thresholds"], r[key]) for r in results if r.get(key) is not None]
        cs = [c for c in cs if list(c[0]) == list(cs[0][0])] if cs else []
        if cs:
            curves[f"{label} ({len(cs)} pairs)"] = (
                np.asarray(cs[0][0]), np.mean([np.asarray(c[1]) for c in cs], axis=0))
    return curves


def summarize_run(
    results: Sequence[Mapping[str, Any]],
    output: str | os.PathLike,
    config: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Write ``summary.md``, ``summary.csv``, ``curves.png`` (and pictures) for a run.

    Parameters
    ----------
    results : sequence of dict
        Records of :func:`evaluate_pair` / ``results.jsonl``.
    output : path-like
        Folder to write into (created).
    config : mapping, optional
        The run config; with ``pictures > 0`` and :mod:`torchheat.viz` available, colour
        transfer PNGs of the first pairs whose maps were saved (``maps/<name>.npz``) are written
        to ``pictures/``.

    Returns
    -------
    dict
        The overall row (``mean_error``, ``pct_under_0.25``, ..., ``time_per_pair_s``).

    Notes
    -----
    Per-class and overall figures are means over pairs of the per-pair figures. Percentages
    are 0-100. The CSV holds one row per level (``overall``, ``class``, ``pair``). All files
    are written atomically (temporary file + :func:`os.replace`).

    Examples
    --------
    >>> from torchheat.batch import load_results
    >>> summarize_run(load_results("out/smoke/results.jsonl"), "out/smoke")  # doctest: +SKIP
    """
    from .evaluate import plot_cumulative

    out = Path(output)
    out.mkdir(parents=True, exist_ok=True)
    if not results:
        raise ValueError("no results to summarize")
    rows = _table_rows(results)
    title = (config or {}).get("name") or out.name
    _write_text(out / "summary.md", _markdown(rows, f"{title}: {len(results)} pairs"))
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(_COLUMNS), lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: "" if r[k] is None else r[k] for k in _COLUMNS})
    _write_text(out / "summary.csv", buf.getvalue())
    curves = _mean_curves(results)
    if curves:
        atomic_write(out / "curves.png",
                     lambda t: plot_cumulative(curves, t, title=f"{title}: mean cumulative "
                                               f"error ({len(results)} pairs)"))
    if config is not None and int(config.get("pictures", 0)) > 0:
        _pictures(results, out, config)
    return rows[0]


def _pictures(results: Sequence[Mapping[str, Any]], out: Path, cfg: Mapping[str, Any]) -> None:
    try:
        from . import viz
    except ImportError:
        return
    color_transfer = getattr(viz, "color_transfer", None)
    if color_transfer is None:
        return
    pc = _load_dataset(cfg["dataset"], cfg["dataset_args"])  # meshes only: no eigensolve here
    index = {n: i for i, n in enumerate(pc.names)}
    for rec in results[: int(cfg["pictures"])]:
        png = out / "pictures" / f"{rec['name']}.png"
        maps = out / "maps" / f"{rec['name']}.npz"
        if png.exists() or not maps.is_file() or rec["name"] not in index:
            continue
        try:
            with np.load(maps) as z:
                fmap = z["map"]
            pair = pc[index[rec["name"]]]
            d = rec["direct"] if rec.get("flip") is None else rec["flip"]
            title = f"{rec['name']}: {100 * d['under_0.25']:.0f}% < 0.25"
            atomic_write(png, lambda t, p=pair, f=fmap, ti=title: color_transfer(
                p.source.mesh, p.target.mesh, f, t, title=ti))
        except Exception as exc:  # noqa: BLE001 - pictures are optional
            warnings.warn(f"picture for {rec['name']} failed: {exc}", stacklevel=2)


# --------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------
_DASK_HELP = ("run on Dask distributed: 'local' or 'local:N' (a LocalCluster of N worker "
              "processes, one thread each, on this machine) or a scheduler address "
              "tcp://HOST:PORT (pip install 'torchheat[dask]'; README: running on a cluster)")


def main(argv: list[str] | None = None) -> int:
    """Command line: ``evaluate CONFIG [--workers N | --dask ADDRESS] [--limit N]
    [--output DIR] [--no-progress]``.

    Returns 0 on success, 1 if some pairs failed, 2 on a configuration error (or an executor
    that cannot run: no scheduler at the address, dask not installed, ...).

    Examples
    --------
    >>> main(["configs/smoke.yaml", "--no-progress"])  # doctest: +SKIP
    0
    >>> main(["configs/smoke.yaml", "--dask", "local:2"])  # doctest: +SKIP
    0
    """
    ap = argparse.ArgumentParser(
        prog="torchheat evaluate",
        description="Batch evaluation of torchheat matching over a dataset (resumable).",
    )
    ap.add_argument("config", help="YAML run configuration (see configs/)")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes")
    ap.add_argument("--dask", metavar="ADDRESS", default=None, help=_DASK_HELP)
    ap.add_argument("--limit", type=int, default=None, help="only the first N pairs")
    ap.add_argument("--output", default=None, help="output folder (default out/<name>)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore", message="Sparse", category=UserWarning)
    try:
        cfg = load_config(args.config)
        if args.limit is not None:
            if args.limit < 1:
                raise ConfigError("--limit must be >= 1")
            cfg["limit"] = args.limit
        if args.output is not None:
            cfg["output"] = args.output
        cfg["executor"] = _executor_args(cfg["executor"], args.workers, args.dask)
        t0 = time.perf_counter()
        results = run(cfg, progress=not args.no_progress)
    except (ConfigError, FileNotFoundError, RuntimeError, ImportError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not results:
        print("error: no pair finished", file=sys.stderr)
        return 1
    row = _table_rows(results)[0]
    print(f"{cfg['name']}: {len(results)} pairs, mean error {row['mean_error']:.4f}, "
          f"{row['pct_under_0.25']:.1f}% < 0.25"
          + ("" if row["flip_pct_under_0.25"] is None
             else f" (flip-aware {row['flip_pct_under_0.25']:.1f}%)")
          + f", {row['time_per_pair_s']:.1f} s/pair; wall {time.perf_counter() - t0:.0f} s "
          f"-> {cfg['output']}/summary.md")
    n_tasks = len(_tasks(cfg))
    return 0 if len(results) == n_tasks else 1


def _executor_args(spec: Mapping[str, Any], workers: int | None,
                   dask: str | None) -> dict[str, Any]:
    """The executor of a run: ``--dask`` or ``--workers`` override the config's."""
    if workers is not None and dask is not None:
        raise ConfigError("give --workers (local processes) or --dask (a Dask cluster), "
                          "not both")
    if workers is not None:
        if workers < 1:
            raise ConfigError("--workers must be >= 1")
        return {"workers": workers}
    if dask is not None:
        return _check_executor({"dask": dask}, "--dask")
    return dict(spec)


def preprocess(
    source: str | os.PathLike,
    cache: str | os.PathLike | None = None,
    executor: Any = None,
    k: int | None = None,
    progress: bool = True,
) -> list[dict[str, Any]]:
    """Fill the per-shape disk cache of a config's dataset or of a folder of meshes.

    One task per shape (:meth:`torchheat.datasets.ShapeCollection.fill_cache`); afterwards a
    run of the config with ``cache`` set, or a ``DataLoader`` over the collection with the
    same :class:`~torchheat.datasets.Preprocess` and cache folder, runs no eigensolve.

    Parameters
    ----------
    source : path-like
        A run config (its dataset, its ``prepare`` options ``k``/``kind``/``boundary`` and
        its ``cache`` folder) or a folder of meshes.
    cache : path-like, optional
        The cache folder (default: the config's ``cache``, else
        :func:`torchheat.datasets.default_cache_dir`). On a cluster: shared storage.
    executor : object with ``map``, optional
        E.g. a :class:`torchheat.executors.DaskExecutor`; default in-process.
    k : int, optional
        Eigenpairs (default: the config's ``prepare.k``, else 100).
    progress : bool
        tqdm progress bar on stderr.

    Returns
    -------
    list of dict
        Per shape: ``name``, ``path``, ``computed``, ``seconds``, ``host``.

    Examples
    --------
    >>> from torchheat.executors import DaskExecutor
    >>> with DaskExecutor("tcp://scheduler:8786") as ex:  # doctest: +SKIP
    ...     done = preprocess("configs/tosca5k.yaml", cache="/shared/cache", executor=ex)
    """
    from . import datasets

    src = Path(source)
    if not src.exists():
        raise FileNotFoundError(f"{src}: no such config file or folder of meshes")
    if src.is_dir():
        prep: dict[str, Any] = {} if k is None else {"k": int(k)}
        cache_dir = str(cache or datasets.default_cache_dir())
        shapes = datasets.folder(src, preprocess=_preprocess_of(prep), cache_dir=cache_dir)
    else:
        cfg = load_config(src)
        prep = dict(cfg["prepare"], **({} if k is None else {"k": int(k)}))
        cache_dir = str(cache or cfg["cache"] or datasets.default_cache_dir())
        shapes = _load_dataset(cfg["dataset"], cfg["dataset_args"], cache_dir, prep).shapes
    return shapes.fill_cache(executor, progress=progress)


def preprocess_main(argv: list[str] | None = None) -> int:
    """Command line: ``preprocess SOURCE [--cache DIR] [--k K] [--workers N | --dask
    ADDRESS] [--no-progress]`` (see :func:`preprocess`).

    Returns 0 on success, 2 on an error (one line on stderr).

    Examples
    --------
    >>> preprocess_main(["configs/tosca5k.yaml", "--dask", "local:2"])  # doctest: +SKIP
    0
    """
    ap = argparse.ArgumentParser(
        prog="torchheat preprocess",
        description="Compute the per-shape preprocessing (eigenpairs, HKS) of a config's "
                    "dataset or of a folder of meshes into the disk cache, one task per "
                    "shape; later runs and DataLoaders read it from there.")
    ap.add_argument("source", help="a YAML run configuration or a folder of meshes")
    ap.add_argument("--cache", default=None, metavar="DIR",
                    help="cache folder (default: the config's cache, else $TORCHHEAT_CACHE or "
                         "~/.cache/torchheat); on a cluster, storage every worker sees")
    ap.add_argument("--k", type=int, default=None, help="eigenpairs (default: the config's "
                    "prepare.k, else 100)")
    ap.add_argument("--workers", type=int, default=None, help="local worker processes")
    ap.add_argument("--dask", metavar="ADDRESS", default=None, help=_DASK_HELP)
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = ap.parse_args(argv)
    warnings.filterwarnings("ignore", message="Sparse", category=UserWarning)
    try:
        spec = _executor_args({}, args.workers, args.dask)
        with contextlib.ExitStack() as owned:
            executor = None
            if "dask" in spec:
                from .executors import DaskExecutor

                executor = owned.enter_context(DaskExecutor(spec["dask"]))
            elif spec.get("workers", 1) > 1:
                executor = owned.enter_context(cf.ProcessPoolExecutor(
                    max_workers=spec["workers"], initializer=_worker_init))
            t0 = time.perf_counter()
            done = preprocess(args.source, args.cache, executor, args.k,
                              progress=not args.no_progress)
    except (ConfigError, FileNotFoundError, RuntimeError, ImportError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    computed = [d for d in done if d["computed"]]
    where = Path(done[0]["path"]).parent if done else args.cache
    print(f"{len(done)} shapes: {len(computed)} computed, {len(done) - len(computed)} already "
          f"cached; wall {time.perf_counter() - t0:.0f} s -> {where}")
    return 0
