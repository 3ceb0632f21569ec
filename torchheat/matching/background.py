"""One function in a background thread, torch threads split meanwhile.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable

import torch


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
