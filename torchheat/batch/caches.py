"""Process-local memo caches of a batch worker (the results do not depend on them, only the
speed): eigenbases, prepared source/target shapes, per-target geodesic fields (float32),
loaded datasets.
"""

from __future__ import annotations

import json
import math
import os
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from .config import ConfigError


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
        from ..evaluate import GeodesicSolver

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
    from ..heat import threads
    from ..matching import prepare

    times = match_opts.get("times")
    kw = dict(prep_opts)
    kw["times"] = "adaptive" if times is None else times
    kw["max_features"] = match_opts.get("max_features", 50)
    key = (_shape_key(shape), json.dumps(kw, sort_keys=True, default=str))

    def make() -> Any:
        # one eigensolve per shape: each role gets a copy (its own timings) sharing the
        # caches that do not depend on the times (self-symmetries, functional-map operators:
        # a shape in both roles pays once); match re-times a target on its own private copy
        from ..matching.prepared import _role_copy

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


def _preprocess_of(prep: Mapping[str, Any]) -> Any:
    """The :class:`~torchheat.datasets.Preprocess` of a config's ``prepare`` options."""
    from ..datasets import Preprocess
    from ..eigen import DEFAULT_EIGENPAIRS

    return Preprocess(k=int(prep.get("k", DEFAULT_EIGENPAIRS)), kind=prep.get("kind", "cotan"),
                      boundary=prep.get("boundary", "neumann"))


def _load_dataset(dataset: str, args: Mapping[str, Any], cache: str | None = None,
                  prep: Mapping[str, Any] | None = None) -> Any:
    """The pair collection of a config (memoised per process). With ``cache`` (a folder) its
    shapes carry the eigenbasis, cached on disk by :class:`~torchheat.datasets.Preprocess`
    with the ``prepare`` options' ``k``, ``kind`` and ``boundary``."""
    from .. import datasets

    prep = dict(prep or {})

    def make() -> Any:
        kw = dict(args)
        if cache:
            kw["preprocess"] = _preprocess_of(prep)
            kw["cache_dir"] = cache
        if dataset == "folder":
            pairs = kw.pop("pairs", None)
            gt = kw.pop("gt")  # "identity", required by load_config
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
