"""One function in a background thread, torch threads split meanwhile; independent jobs on
the torch threads, one each.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import torch

from ..heat import threads


class _Background:
    """At most one function run in a background thread, torch's threads split meanwhile.

    A context manager, inert until :meth:`start`; :meth:`wait` joins (re-raising the
    function's exception) and gives the calling thread its threads back; leaving the context
    waits too. torch's thread count is per OS thread under OpenMP, so each side sets its own.
    """

    def __init__(self) -> None:
        self._thread: threading.Thread | None = None
        self._exc: BaseException | None = None
        self._threads = 0

    def start(self, fn: Callable[..., object], *args: object) -> None:
        nt = torch.get_num_threads()
        if nt < 2 or self._thread is not None:
            return  # nothing to split (e.g. one-thread batch workers): stay sequential
        half = nt // 2
        self._threads = nt

        def run() -> None:
            try:
                torch.set_num_threads(nt - half)
                fn(*args)
            except BaseException as exc:  # re-raised by wait()
                self._exc = exc

        torch.set_num_threads(half)
        self._thread = threading.Thread(target=run, daemon=True, name="torchheat-background")
        self._thread.start()

    @property
    def running(self) -> bool:
        """Whether the function is still running (the caller's other work is then free)."""
        return self._thread is not None and self._thread.is_alive()

    def wait(self) -> None:
        if self._thread is None:
            return
        self._thread.join()
        self._thread = None
        torch.set_num_threads(self._threads)
        if self._exc is not None:
            exc, self._exc = self._exc, None
            raise exc

    def __enter__(self) -> _Background:
        return self

    def __exit__(self, exc_type: object, *rest: object) -> None:
        if exc_type is None:
            self.wait()
            return
        with contextlib.suppress(BaseException):  # the exception in flight wins
            self.wait()


def run_each(jobs: Sequence[Callable[[], object]], n_threads: int) -> None:
    """Run independent ``jobs`` side by side on ``n_threads`` threads, one torch thread each,
    and wait for all of them (an exception of a job is re-raised; their results are their side
    effects, e.g. a memo's entries). Sequential, in order, when ``n_threads < 2``.

    Small independent jobs (a match's ZoomOut candidates) gain more this way than from
    splitting each one's GEMMs over the threads (BENCHMARKS.md, twenty-eighth session). A job
    that sets its own thread count sets it for its pool thread only (torch's count is per OS
    thread), so its result does not depend on ``n_threads``.

    Examples
    --------
    >>> out = []
    >>> run_each([lambda: out.append(1), lambda: out.append(2)], 2)
    >>> sorted(out)
    [1, 2]
    """
    if n_threads < 2 or len(jobs) < 2:
        for job in jobs:
            job()
        return

    def one(job: Callable[[], object]) -> None:
        with threads(1):
            job()

    ex = ThreadPoolExecutor(max_workers=min(int(n_threads), len(jobs)),
                            thread_name_prefix="torchheat-job")
    try:
        for f in [ex.submit(one, job) for job in jobs]:
            f.result()
    finally:  # a failed job or Ctrl-C: the jobs not started yet are dropped
        ex.shutdown(wait=True, cancel_futures=True)
