"""Atomic file writes, shared by every module that writes results or caches.

A file is written to a temporary file in its destination directory, flushed to disk and
renamed into place (:func:`os.replace`, atomic on POSIX and Windows): a reader sees the old
file or the new one, never a partial one, and a failed write leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


def file_mode() -> int:
    """Permissions of a newly created file under the current umask (``0o666 & ~umask``;
    :func:`tempfile.mkstemp` itself creates ``0o600``, unreadable to a team sharing a
    cache)."""
    mask = os.umask(0)
    os.umask(mask)
    return 0o666 & ~mask


def _temporary(path: Path) -> Path:
    """An empty temporary file next to ``path`` (hidden, ``path``'s suffix); the directory is
    created if missing."""
    parent = path.parent if str(path.parent) else Path(".")
    parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=parent)
    os.close(fd)
    return Path(tmp)


def _publish(tmp: Path, path: Path) -> None:
    """Flush ``tmp`` to disk, give it a new file's permissions and rename it to ``path``."""
    with open(tmp, "rb+") as f:
        os.fsync(f.fileno())
    os.chmod(tmp, file_mode())
    os.replace(tmp, path)


def atomic_write(path: str | os.PathLike, write: Callable[[Path], Any]) -> Path:
    """``write(tmp)`` to a temporary file next to ``path``, then rename it into place.

    Parameters
    ----------
    path : str or os.PathLike
        Destination; its directory is created if missing.
    write : callable
        Called with the temporary file's path (same directory, same suffix as ``path``, so
        writers that pick a format by suffix keep working); writes the whole content.

    Returns
    -------
    pathlib.Path
        ``path``. The file gets the permissions a new file gets under the current umask; its
        content is fsync'ed before the rename. On any exception the temporary file is removed
        and the exception re-raised; ``path`` is untouched.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "sub" / "x.txt"
    >>> atomic_write(p, lambda t: t.write_text("hello")).read_text()
    'hello'
    """
    path = Path(path)
    tmp = _temporary(path)
    try:
        write(tmp)
        _publish(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    return path


class AtomicWrites:
    """Several files written as one: each to a temporary file first, all renamed into place
    only when every one was written (a command's map, report and picture appear together or
    not at all). Use through :func:`atomic_writes`.
    """

    def __init__(self) -> None:
        self._staged: list[tuple[Path, Path]] = []

    def stage(self, path: str | os.PathLike, write: Callable[[Path], Any]) -> None:
        """``write(tmp)`` to a temporary file next to ``path`` (as :func:`atomic_write`)."""
        path = Path(path)
        tmp = _temporary(path)
        self._staged.append((tmp, path))
        write(tmp)

    def _commit(self) -> None:
        for tmp, path in self._staged:
            _publish(tmp, path)
        self._staged = []

    def _discard(self) -> None:
        for tmp, _ in self._staged:
            with contextlib.suppress(OSError):
                os.unlink(tmp)
        self._staged = []


@contextlib.contextmanager
def atomic_writes() -> Iterator[AtomicWrites]:
    """A context in which files are staged (:meth:`AtomicWrites.stage`) and published together
    when it exits normally; on an exception none is, and the temporary files are removed.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> with atomic_writes() as out:
    ...     out.stage(d / "a.txt", lambda t: t.write_text("a"))
    ...     out.stage(d / "b.txt", lambda t: t.write_text("b"))
    >>> sorted(p.name for p in d.iterdir())
    ['a.txt', 'b.txt']
    """
    out = AtomicWrites()
    try:
        yield out
        out._commit()
    finally:
        out._discard()
