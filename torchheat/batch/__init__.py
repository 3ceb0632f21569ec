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
Stages, one module each (imports go downward only): :mod:`.config` (the YAML config),
:mod:`.results` (the JSONL file), :mod:`.caches` (per-process memo caches), :mod:`.task` (one
pair: match + evaluation), :mod:`.report` (summaries, curves, pictures), :mod:`.runner` (executors,
resume), :mod:`.commands` (the command lines).

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

# names marked `noqa: F401` are not public API: the command line, scripts and tests reach them
# as ``torchheat.batch.<name>``, as in the single-module layout
from .caches import _prepared, _TargetGeodesics, clear_caches  # noqa: F401 (all three)
from .commands import main, preprocess_main
from .config import (
    ConfigError,
    Executor,
    load_config,
    options_hash,  # noqa: F401
)
from .report import (
    _row,  # noqa: F401
    summarize_run,
)
from .results import (
    RESULTS,  # noqa: F401
    _append_lines,  # noqa: F401
    load_results,
)
from .runner import (
    _AffinityPool,  # noqa: F401
    load_pairs,
    preprocess,
    run,
)
from .task import (
    CURVE_THRESHOLDS,
    PairTask,
    ShapeTask,  # noqa: F401
    _barycentric_errors,  # noqa: F401
    _error_record,  # noqa: F401
    evaluate_pair,
)

__all__ = [
    "CURVE_THRESHOLDS",
    "ConfigError",
    "Executor",
    "PairTask",
    "evaluate_pair",
    "load_config",
    "load_pairs",
    "load_results",
    "main",
    "preprocess",
    "preprocess_main",
    "run",
    "summarize_run",
]
