"""The ``torchheat evaluate`` and ``torchheat preprocess`` command lines (argparse), thin layers
over :func:`~torchheat.batch.runner.run` and :func:`~torchheat.batch.runner.preprocess`.
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import contextlib
import sys
import time
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from .config import ConfigError, Executor, _check_executor, load_config
from .report import _table_rows
from .runner import _tasks, preprocess, run
from .task import _worker_init

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
    ap.add_argument("--workers", type=int, default=None,
                    help="local worker processes, one torch thread each (1: in this process, "
                         "with torch's own thread count)")
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
          + ("" if not row["gt_contradicted_pct"]
             else f"; {row['consistent_pct_under_0.25']:.1f}% on the rows whose ground truth "
                  f"agrees with its neighbours' ({row['gt_contradicted_pct']:.2f}% do not)")
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
            executor: Executor | None = None
            if "dask" in spec:
                from ..executors import DaskExecutor

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
