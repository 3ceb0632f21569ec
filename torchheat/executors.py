"""Executors beyond one process: torchheat's batch work on a Dask distributed cluster.

:class:`DaskExecutor` wraps a :class:`distributed.Client`, either of a :class:`distributed.
LocalCluster` it starts (``"local:N"``: N worker processes of one thread each, on this
machine) or of an existing scheduler (``"tcp://host:8786"``, started with Dask's own ``dask
scheduler`` / ``dask worker`` commands). It is what ``torchheat evaluate CONFIG --dask ...``
and ``executor: {dask: ...}`` in a config use, and it serves any ``map(fn, iterable)`` user
such as :meth:`torchheat.datasets.ShapeCollection.fill_cache`.

dask.distributed is an optional dependency (``pip install 'torchheat[dask]'``); it is imported
when a :class:`DaskExecutor` is made, never by ``import torchheat``. This module imports
nothing else of torchheat.

What the engine provides and torchheat relies on (see :mod:`torchheat.batch` for the rest):

* a task whose worker process dies (killed, out of memory: the nanny restarts it) is run again
  on a live worker; a task whose workers died more than ``distributed.scheduler.
  allowed-failures`` (default 3) times fails with ``KilledWorker`` instead of being retried
  for ever;
* results held by a dead worker are recomputed from their tasks (lineage);
* a dependency's result moves to the worker that runs the dependent task.

Examples
--------
>>> with DaskExecutor("local:2") as ex:  # doctest: +SKIP
...     sorted(ex.map(abs, [-1, 2, -3]))
[1, 2, 3]
"""

from __future__ import annotations

import os
import re
import sys
import time
import uuid
from collections import deque
from collections.abc import Callable, Hashable, Iterable, Iterator, Mapping, Sequence
from concurrent.futures import CancelledError
from typing import Any

__all__ = ["INSTALL_HINT", "DaskExecutor", "ExecutorError", "import_distributed",
           "parse_dask_address", "relax_malloc_trim"]

#: What to install for the Dask executor.
INSTALL_HINT = "pip install 'torchheat[dask]'  (or: pip install 'dask[distributed]')"


class ExecutorError(RuntimeError):
    """An executor that cannot run: no scheduler at the address, no workers, bad address."""


def import_distributed() -> Any:
    """``import distributed``, or an :class:`ImportError` that says what to install.

    Examples
    --------
    >>> import_distributed().__name__  # doctest: +SKIP
    'distributed'
    """
    try:
        import distributed
    except ImportError as exc:
        raise ImportError(
            f"running on Dask needs dask.distributed, which is not installed: {INSTALL_HINT}"
        ) from exc
    return distributed


def _safe(name: str) -> str:
    """A task-name fragment without characters that Dask keys or dashboards trip on."""
    return re.sub(r"[^A-Za-z0-9_.#-]", "_", str(name))[:80]


def _usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


def parse_dask_address(spec: str) -> tuple[str, int | str]:
    """Read a ``--dask`` value: ``("local", n_workers)`` or ``("remote", scheduler address)``.

    ``local`` (one worker per usable CPU) or ``local:N`` start a LocalCluster; a scheduler
    address is ``tcp://HOST:PORT`` (any ``protocol://``) or ``HOST:PORT`` (tcp).

    Raises
    ------
    ExecutorError
        On anything else, with the accepted forms.

    Examples
    --------
    >>> parse_dask_address("local:2"), parse_dask_address("10.0.0.5:8786")
    (('local', 2), ('remote', 'tcp://10.0.0.5:8786'))
    """
    s = str(spec).strip()
    m = re.fullmatch(r"local(?::(\d+))?", s)
    if m:
        n = _usable_cpus() if m.group(1) is None else int(m.group(1))
        if n < 1:
            raise ExecutorError(f"--dask {s}: a local cluster needs at least 1 worker")
        return "local", n
    if re.fullmatch(r"[a-z][a-z0-9+.-]*://\S+", s):
        return "remote", s
    if re.fullmatch(r"[^\s:/]+:\d+", s):
        return "remote", f"tcp://{s}"
    raise ExecutorError(f"--dask {s!r}: expected local, local:N (N worker processes here) or "
                        "a scheduler address tcp://HOST:PORT")


#: glibc ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def relax_malloc_trim() -> bool:
    """Undo the cost of Dask's ``MALLOC_TRIM_THRESHOLD_`` in this worker process (Linux).

    Dask's nanny starts its workers with ``MALLOC_TRIM_THRESHOLD_=65536`` (to hand freed memory
    back to the OS). Setting it also switches off glibc's dynamic mmap threshold, so every
    allocation of 128 KiB or more is a fresh ``mmap`` whose pages fault in on first touch and
    go back on ``free``: numeric code that makes many MB-sized temporaries (a matching pair
    does) spent ~30 % more CPU time per task (BENCHMARKS.md, "Dask"). This sets the mmap
    threshold to 32 MiB and the trim threshold to 64 MiB, the values glibc's dynamic threshold
    reaches by itself. Does nothing (returns False) when the variable is not set or libc has
    no ``mallopt``.

    Examples
    --------
    >>> relax_malloc_trim() in (True, False)
    True
    """
    if "MALLOC_TRIM_THRESHOLD_" not in os.environ or not sys.platform.startswith("linux"):
        return False
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        ok = libc.mallopt(_M_MMAP_THRESHOLD, 32 << 20) and libc.mallopt(_M_TRIM_THRESHOLD,
                                                                        64 << 20)
    except (OSError, AttributeError):  # not glibc
        return False
    return bool(ok)


_RELAXED: list[bool] = []  # relax_malloc_trim() done in this (worker) process


class _Relaxed:
    """``fn`` wrapped for a Dask worker: :func:`relax_malloc_trim` once per process first."""

    def __init__(self, fn: Callable[..., Any]) -> None:
        self.fn = fn
        self.__name__ = getattr(fn, "__name__", "task")  # Dask's key prefix

    def __call__(self, *args: Any) -> Any:
        if not _RELAXED:
            relax_malloc_trim()
            _RELAXED.append(True)
        return self.fn(*args)


class DaskExecutor:
    """Run torchheat tasks on Dask distributed: a local cluster or an existing scheduler.

    Parameters
    ----------
    address : str or distributed.Client
        ``"local"`` / ``"local:N"``: start a :class:`distributed.LocalCluster` of N worker
        processes (default: one per usable CPU) with one thread each, closed by
        :meth:`close`; ``"tcp://HOST:PORT"``: connect to a running scheduler (its workers
        must have torchheat installed and see the data); a ready ``Client`` is used as is
        (and left open).
    timeout : float, optional
        Seconds to reach the scheduler before :class:`ExecutorError` (default: Dask's
        ``distributed.comm.timeouts.connect``, 30 s unless configured).
    workers_timeout : float
        Seconds to wait for at least one worker before :class:`ExecutorError`.
    **cluster_kwargs
        Extra :class:`distributed.LocalCluster` arguments for ``"local"`` (e.g. ``env`` for
        the workers' environment, ``memory_limit``).

    Attributes
    ----------
    client : distributed.Client
    cluster : distributed.LocalCluster or None

    Raises
    ------
    ImportError
        Without dask.distributed (the message says what to install).
    ExecutorError
        Unreachable scheduler, not a Dask scheduler, no workers, malformed address.

    Notes
    -----
    torchheat's tasks use one torch/BLAS thread each and keep per-process caches that are
    not thread-safe: give workers one thread each and more processes
    (``dask worker ADDRESS --nworkers N --nthreads 1``); :meth:`check_threads` warns
    otherwise.

    Examples
    --------
    >>> with DaskExecutor("local:2") as ex:  # doctest: +SKIP
    ...     ex.n_threads, sorted(ex.map(abs, [-1, 2]))
    (2, [1, 2])
    """

    def __init__(self, address: Any = "local", *, timeout: float | None = None,
                 workers_timeout: float = 60.0, **cluster_kwargs: Any) -> None:
        distributed = import_distributed()
        if timeout is None:
            import dask
            from dask.utils import parse_timedelta

            timeout = parse_timedelta(dask.config.get("distributed.comm.timeouts.connect"))
        self.cluster = None
        self._own_client = True
        if isinstance(address, distributed.Client):
            self.client = address
            self._own_client = False
            self.address = str(address.scheduler.address)
            return
        kind, where = parse_dask_address(address)
        if kind == "local":
            kw = {"n_workers": int(where), "threads_per_worker": 1, "processes": True,
                  "dashboard_address": ":0"}  # no fixed port
            kw.update(cluster_kwargs)
            self.cluster = distributed.LocalCluster(**kw)
            self.client = distributed.Client(self.cluster, timeout=timeout)
            self.address = f"local:{where}"
        else:
            self.address = str(where)
            try:
                self.client = distributed.Client(self.address, timeout=timeout)
            except Exception as exc:  # noqa: BLE001 - OSError, TimeoutError, garbage replies
                raise ExecutorError(
                    f"cannot reach a Dask scheduler at {self.address} within {timeout:g} s "
                    f"({type(exc).__name__}: {exc}); start one with 'dask scheduler' and "
                    "workers with 'dask worker ADDRESS --nthreads 1' (README: running on a "
                    "cluster)") from None
        try:
            self.client.wait_for_workers(1, timeout=workers_timeout)
        except Exception:  # noqa: BLE001 - TimeoutError, of dask's or the builtin one
            self.close()
            raise ExecutorError(
                f"no Dask worker joined the scheduler at {self.address} within "
                f"{workers_timeout:g} s; start some with 'dask worker {self.address} "
                "--nthreads 1'") from None

    # ---------------------------------------------------------------------------------
    @property
    def workers(self) -> dict[str, int]:
        """Worker address -> threads, as the scheduler knows them now."""
        return dict(self.client.nthreads())

    @property
    def n_threads(self) -> int:
        """Threads over all workers now (tasks that can run at once)."""
        return sum(self.workers.values())

    def check_threads(self) -> str | None:
        """A warning text if some worker runs several threads (see Notes), else None."""
        many = {w: n for w, n in self.workers.items() if n > 1}
        if not many:
            return None
        w, n = next(iter(many.items()))
        return (f"{len(many)} Dask worker(s) run several threads (e.g. {w}: {n}); torchheat's "
                "tasks want one thread per worker process: 'dask worker ADDRESS --nworkers N "
                "--nthreads 1'")

    def map(self, fn: Callable[[Any], Any], iterable: Iterable[Any]) -> Iterator[Any]:
        """``fn`` over the items on the cluster; results in **completion** order.

        A task that raises re-raises here (the remaining tasks are cancelled).
        """
        distributed = import_distributed()
        futures = self.client.map(_Relaxed(fn), list(iterable), pure=False)
        try:
            for _, result in distributed.as_completed(futures, with_results=True):
                yield result
        finally:
            self.client.cancel([f for f in futures if not f.done()])

    def map_shared(
        self,
        fn: Callable[..., Any],
        items: Sequence[Any],
        needs: Callable[[Any], Sequence[Hashable]],
        shared_fn: Callable[[Any], Any],
        shared: Mapping[Hashable, Any],
        *,
        window: int | None = None,
        name: Callable[[Any], str] = str,
        no_workers_timeout: float = 120.0,
    ) -> Iterator[list[tuple[Any, Any, BaseException | None]]]:
        """``fn(item, *[shared_fn(shared[s]) for s in needs(item)])`` for every item, each
        shared input computed **once** as a task of its own and handed to every item that
        needs it by Dask (moved between workers, recomputed if its worker dies).

        Items are submitted in order, at most ``window`` at a time (default: 4 per worker
        thread, at least 16), so the scheduler holds a bounded graph however many items there
        are; a shared input is submitted with the first item that needs it and released
        after the last one finished, so the cluster holds only those still in use.

        Parameters
        ----------
        fn : callable
            ``fn(item, *shared_results)``; must be picklable (a module-level function).
        items : sequence
            Work items, submitted in this order.
        needs : callable
            ``needs(item)``: the keys of ``shared`` the item depends on (in ``fn``'s order).
        shared_fn : callable
            Computes one shared input from ``shared[key]`` (e.g. a shape's eigenbasis).
        shared : mapping
            Key -> argument of ``shared_fn``.
        window : int, optional
            Items in flight at once.
        name : callable
            ``name(item)`` / ``name(key)``: readable task names (dashboard, logs).
        no_workers_timeout : float
            Seconds without any worker (all dead, none joining) before :class:`ExecutorError`
            is raised instead of waiting for ever.

        Yields
        ------
        list of (item, result, exception)
            Finished items, in completion order, in batches of those that finished together;
            ``exception`` is None or what ``fn`` or a shared input raised, or Dask's
            ``KilledWorker`` when the item's workers died more than
            ``distributed.scheduler.allowed-failures`` times.

        Raises
        ------
        ExecutorError
            The scheduler was lost, or no worker was left for ``no_workers_timeout`` s.

        Examples
        --------
        >>> with DaskExecutor("local:2") as ex:  # doctest: +SKIP
        ...     out = [r for batch in ex.map_shared(pow, [2, 3], lambda i: ["a"],
        ...                                         abs, {"a": -2}) for _, r, _ in batch]
        >>> sorted(out)  # doctest: +SKIP
        [4, 9]
        """
        distributed = import_distributed()
        token = uuid.uuid4().hex[:8]
        fn, shared_fn = _Relaxed(fn), _Relaxed(shared_fn)
        window = int(window or max(16, 4 * self.n_threads))
        remaining: dict[Hashable, int] = {}
        for item in items:
            for s in dict.fromkeys(needs(item)):
                remaining[s] = remaining.get(s, 0) + 1
        futures: dict[Hashable, Any] = {}  # shared inputs in use
        pending = deque(items)
        running: dict[Any, Any] = {}  # future -> item
        done = distributed.as_completed(with_results=True)  # results fetched in the background
        no_workers_since: float | None = None
        checked = time.monotonic()

        def shared_future(s: Hashable) -> Any:
            if s not in futures:  # priority 1: shared inputs run before waiting items
                futures[s] = self.client.submit(
                    shared_fn, shared[s], key=f"{_safe(name(s))}-{token}", pure=False,
                    priority=1)
            return futures[s]

        try:
            while pending or running:
                while pending and len(running) < window:
                    item = pending.popleft()
                    deps = [shared_future(s) for s in needs(item)]
                    fut = self.client.submit(fn, item, *deps, pure=False,
                                             key=f"{_safe(name(item))}-{token}")
                    running[fut] = item
                    done.add(fut)
                finished = done.next_batch(block=False)
                if not finished:
                    if time.monotonic() - checked > 2.0:
                        no_workers_since = self._check_alive(no_workers_since,
                                                             no_workers_timeout)
                        checked = time.monotonic()
                    time.sleep(0.02)
                    continue
                no_workers_since = None
                batch = []
                for fut, result in finished:
                    item = running.pop(fut)
                    batch.append((item, *self._outcome(fut, result)))
                    for s in dict.fromkeys(needs(item)):
                        remaining[s] -= 1
                        if remaining[s] == 0:
                            futures.pop(s, None)  # the last reference: Dask frees it
                yield batch
        finally:
            left = list(running) + list(futures.values())
            if left and self.client.status == "running":
                self.client.cancel(left)

    def _outcome(self, fut: Any, result: Any) -> tuple[Any, BaseException | None]:
        """``(result, None)`` or ``(None, exception)`` of a finished future."""
        if fut.status == "error":  # as_completed hands over (type, exception, traceback)
            return None, result[1]
        if fut.status == "cancelled" or isinstance(result, CancelledError):
            raise ExecutorError(f"the Dask scheduler at {self.address} cancelled task "
                                f"{fut.key} (scheduler lost or restarted); the results "
                                "written so far are kept: re-run to resume")
        return result, None

    def _check_alive(self, since: float | None, timeout: float) -> float | None:
        if self.client.status not in ("running", "connecting"):
            raise ExecutorError(f"lost the Dask scheduler at {self.address} (client "
                                f"{self.client.status}); the results written so far are "
                                "kept: re-run to resume")
        if self.workers:
            return None
        now = time.monotonic()
        if since is None:
            return now
        if now - since > timeout:
            raise ExecutorError(f"no Dask worker left at {self.address} for {timeout:g} s; "
                                "the results written so far are kept: start workers and "
                                "re-run to resume")
        return since

    def close(self) -> None:
        """Close the client (if made here) and the local cluster (if started here)."""
        if self._own_client:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
            self.cluster = None

    def __enter__(self) -> DaskExecutor:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def __repr__(self) -> str:
        try:
            workers: int | str = len(self.workers)
        except Exception:  # noqa: BLE001 - a closed client
            workers = "?"
        return f"DaskExecutor({self.address!r}, workers={workers})"
