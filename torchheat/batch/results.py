"""The run's results file ``results.jsonl``: crash-safe appends (one ``O_APPEND`` write per
batch of lines, then ``fsync``), repair of a cut last line on load, the output folder's lock.
"""

from __future__ import annotations

import contextlib
import json
import os
import warnings
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from .._files import atomic_write

RESULTS = "results.jsonl"


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
