""":func:`run`: the pending pairs of a config mapped over an executor (in-process, a process
pool with target affinity, or Dask with one task per shape), records appended as they finish;
:func:`preprocess` fills a collection's disk cache.
"""

from __future__ import annotations

import builtins
import concurrent.futures as cf
import contextlib
import copy
import dataclasses
import functools
import os
import shutil
import sys
import warnings
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._files import atomic_write
from .caches import _DATASETS, _dataset_key, _load_dataset, _preprocess_of
from .config import Executor, load_config, options_hash
from .report import summarize_run
from .results import RESULTS, _append_lines, _lock, _write_text, load_results
from .task import (
    PairTask,
    ShapeTask,
    _dask_pair,
    _error_record,
    _freeze,
    _last_line,
    _probe_worker,
    _run_shape,
    _run_task,
    _worker_init,
)


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

        return self._drive(fn, take)

    def map_unordered(self, fn: Callable, tasks: Sequence) -> Iterator[Any]:
        """``fn(task)`` of every task, each to the next free worker, in completion order."""
        queue = list(tasks)[::-1]
        return self._drive(fn, lambda w: queue.pop() if queue else None)

    def _drive(self, fn: Callable, take: Callable[[int], Any]) -> Iterator[Any]:
        """One task per worker in flight, ``take(w)`` giving worker ``w``'s next (None: no
        more); results in completion order."""
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
    from ..executors import DaskExecutor

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
    eigensolve per shape (plus one per shape recomputed after its worker died), whose
    seconds are shared out over the shape's pending pairs (``time_shapes``, added to
    ``time_prepare`` as in a local run, :func:`_solve_shapes_first`). The
    eigenbases reach the pair tasks through the disk cache when the config has one (entries
    written by the shape tasks, read by the pair tasks: the folder must be shared), else
    through Dask's own data transfers (nothing written; held by the workers until the last
    pair of the shape is done)."""
    with_shapes = cfg["task"] == "match"
    pc, shared, uses = _shape_tasks(cfg, todo if with_shapes else [], cfg.get("cache"))

    def needs(t: PairTask) -> tuple[int, ...]:
        return tuple(dict.fromkeys(pc.pairs[t.index])) if with_shapes else ()

    def name(x: Any) -> str:
        return f"pair-{x.name}" if isinstance(x, PairTask) else f"shape-{shared[x].name}"

    def shared_out(rec: dict[str, Any]) -> dict[str, Any]:
        metas = rec.get("shapes") or ()
        seconds = {m["name"]: float(m.get("seconds", 0.0)) for m in metas}
        return _with_shape_share(rec, _shape_share(list(seconds), seconds, uses))

    for batch in ex.map_shared(_dask_pair, todo, needs, _run_shape, shared, name=name):
        yield [_error_record(task, exc) if exc is not None else
               rec if "error" in rec else shared_out(rec) for task, rec, exc in batch]


def _preflight(ex: Any, cfg: Mapping[str, Any]) -> None:
    """Every worker can import torchheat and see the data (and the cache folder), or a clear
    error before any task runs; a warning for workers with several threads."""
    from ..executors import ExecutorError

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


def load_pairs(config: str | os.PathLike | Mapping[str, Any]) -> Any:
    """The pairs a batch config evaluates, as a :class:`~torchheat.datasets.PairCollection`.

    Its ``dataset`` and ``dataset_args`` (with ``cache``: shapes that carry their cached
    eigenbasis), the first ``limit`` pairs when it sets one, in the order of the run's
    records. For scripts that run something else over a config's pairs (e.g.
    ``scripts/compare_pyfm.py --set CONFIG``).

    Parameters
    ----------
    config : str, os.PathLike or mapping
        A YAML config path or its contents (checked by :func:`load_config`).

    Returns
    -------
    PairCollection
        Indexable like the run's pairs: ``pairs[i]`` is a :class:`~torchheat.datasets.Pair`
        and ``pairs.names[i]`` the name in the records.

    Examples
    --------
    >>> pairs = load_pairs("configs/scape50.yaml")  # doctest: +SKIP
    >>> len(pairs), pairs.names[0]  # doctest: +SKIP
    (50, 'mesh000-mesh001')
    """
    cfg = load_config(config)
    pc = _load_dataset(cfg["dataset"], cfg["dataset_args"], cfg.get("cache"), cfg["prepare"])
    if cfg["limit"] is None or int(cfg["limit"]) >= len(pc):
        return pc
    first = copy.copy(pc)  # the loader's own class (its ground truth), fewer pairs
    first.pairs = pc.pairs[: int(cfg["limit"])]
    return first


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
        target run on the same worker, see :class:`_AffinityPool`; a ``match`` run solves
        each shape once first, see :func:`_solve_shapes_first`). ``1``: the pairs run in
        this process, with torch's thread count as it is; a run with several threads can
        give maps that differ from the one-thread workers' in their last bits (TOSCA 284
        with two threads: one pair of 284 moved, cat2 -> cat5, mean eps 0.0288 -> 0.0287;
        ``OMP_NUM_THREADS=1`` gives the workers' maps). Ignored when ``executor`` is given.
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
        solves = _Eigensolves()
        shares: dict[str, float] = {}  # pair key -> its share of the shape phase (local runs)
        dask_ex = _as_dask(executor)
        if executor is None and todo:
            if "dask" in cfg["executor"]:
                from ..executors import DaskExecutor

                dask_ex = owned.enter_context(DaskExecutor(cfg["executor"]["dask"]))
            elif workers <= 1:
                workers = int(cfg["executor"].get("workers", workers))
        if dask_ex is not None:
            if todo:
                _preflight(dask_ex, cfg)
            batches = _dask_batches(dask_ex, cfg, todo)
        else:
            if executor is None and workers > 1 and len(todo) > 1:
                scratch = None
                if cfg["task"] == "match" and not cfg.get("cache"):
                    # the run's eigenbases, handed from the shape phase to the pairs (entries
                    # keyed by file content and parameters): removed when the run completes,
                    # after the pool has shut down (exit callbacks run LIFO); an interrupted
                    # run leaves them to its resume (the folder lock: one run at a time)
                    scratch = out / SCRATCH
                    scratch.mkdir(exist_ok=True)
                    owned.push(_remove_when_done(scratch))
                pool = _AffinityPool(int(workers), initializer=_worker_init)
                owned.callback(pool.shutdown, wait=True, cancel_futures=True)
                if cfg["task"] == "match":
                    todo, shares = _solve_shapes_first(
                        pool, cfg, todo, str(cfg.get("cache") or scratch), solves, progress)
                records = pool.run(_run_task, todo, key=_target_of)
            else:
                records = _in_completion_order(executor, _run_task, todo)
            batches = ([r] for r in records)
        bar = owned.enter_context(tqdm(
            total=len(tasks), initial=len(tasks) - len(todo), file=sys.stderr,
            disable=not progress, desc=cfg["name"], unit="pair", dynamic_ncols=True))
        for recs in batches:
            fresh = []
            for rec in recs:
                if "error" in rec:
                    failed.append(rec)
                    tqdm.write(f"{rec['name']}: failed: {rec['error']}", file=sys.stderr)
                    bar.update(1)
                    continue
                _with_shape_share(rec, shares.get(rec["key"], 0.0))
                arrays = rec.pop("_arrays", None)
                if arrays is not None:
                    atomic_write(out / "maps" / f"{rec['name']}.npz",
                                 functools.partial(np.savez, **arrays))
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


#: the scratch cache folder of a local multi-worker run without ``cache`` (in the output folder)
SCRATCH = ".eigenbases"


def _remove_when_done(folder: Path) -> Callable[..., bool]:
    """An exit callback (``ExitStack.push``) removing ``folder`` if no exception is in flight."""

    def exit_(exc_type: object, *_: object) -> bool:
        if exc_type is None:
            shutil.rmtree(folder, ignore_errors=True)
        return False

    return exit_


def _shape_tasks(cfg: Mapping[str, Any], todo: list[PairTask], cache: str | None
                 ) -> tuple[Any, dict[int, ShapeTask], dict[str, int]]:
    """The config's pair collection (with ``cache``), one :class:`ShapeTask` per shape of the
    pending pairs ``todo`` (by shape index, in order of first use) and how many of them use
    each shape (by shape name)."""
    pc = _load_dataset(cfg["dataset"], cfg["dataset_args"], cache, cfg["prepare"])
    tasks: dict[int, ShapeTask] = {}
    uses: dict[str, int] = {}
    for t in todo:
        for i in dict.fromkeys(pc.pairs[t.index]):
            st = tasks.setdefault(i, ShapeTask(cfg["dataset"], _freeze(cfg["dataset_args"]), i,
                                               pc.shapes.names[i], _freeze(cfg["prepare"]),
                                               cache))
            uses[st.name] = uses.get(st.name, 0) + 1
    return pc, tasks, uses


def _shape_share(names: Iterable[str], seconds: Mapping[str, float],
                 uses: Mapping[str, int]) -> float:
    """A pair's share of its shapes' preprocessing: each shape's seconds divided among the
    pending pairs that use it (a shape without a time counts 0)."""
    return sum(seconds.get(n, 0.0) / uses.get(n, 1) for n in names)


def _with_shape_share(rec: dict[str, Any], share: float) -> dict[str, Any]:
    """``rec`` with its shapes' preprocessing, run before the pairs, in its ``time_prepare``
    (and as ``time_shapes``), so that "prepare + match" per pair counts every eigensolve."""
    if share:
        rec["time_shapes"] = share
        rec["time_prepare"] = rec.get("time_prepare", 0.0) + share
    return rec


def _solve_shapes_first(pool: _AffinityPool, cfg: Mapping[str, Any], todo: list[PairTask],
                        cache: str, solves: _Eigensolves, progress: bool
                        ) -> tuple[list[PairTask], dict[str, float]]:
    """The shape phase of a local multi-worker ``match`` run: every shape of the pending
    pairs is prepared once (its eigensolve, written to the disk cache ``cache``: the config's
    own, else the run's scratch folder ``<output>/.eigenbases``, removed when the run
    completes and kept by an interrupted run for its resume) by the next free worker, before
    any pair runs; the pairs, returned, then read their shapes from that cache.

    Without it each worker solved every shape it met (the pairs of one target run on one
    worker, but its sources run on both): 141 eigensolves for TOSCA's 76 shapes, 43 for
    SCAPE 50's 20. The maps are the same (the workers solve with one thread either way, and a
    cached eigenbasis is the solved one, bit for bit). Also returned: each pending pair's
    share of its shapes' seconds (:func:`_shape_share`, by pair key), which :func:`run` adds
    to its record (:func:`_with_shape_share`). A shape that fails here is solved again, and
    its error reported, by its pairs."""
    from tqdm import tqdm

    pc, tasks, uses = _shape_tasks(cfg, todo, cache)
    seconds: dict[str, float] = {}
    with tqdm(total=len(tasks), file=sys.stderr, disable=not progress,
              desc=f"{cfg['name']}: shapes", unit="shape", dynamic_ncols=True) as bar:
        for res in pool.map_unordered(_run_shape, list(tasks.values())):
            meta = res.get("meta")
            if meta is not None:
                seconds[res["name"]] = float(meta.get("seconds", 0.0))
                solves.shapes[meta["id"]] = bool(meta.get("computed"))
            bar.update(1)
    shares = {t.key: _shape_share([tasks[i].name for i in dict.fromkeys(pc.pairs[t.index])],
                                  seconds, uses) for t in todo}
    return [dataclasses.replace(t, cache=cache) for t in todo], shares


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
    from .. import datasets

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
