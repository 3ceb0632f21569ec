"""Where a result was computed: versions, the checkout's commit, BLAS, CPU (written beside batch
summaries, since maps depend on the BLAS build in their last bits: RESULTS.md, twenty-third
session)."""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
from pathlib import Path
from typing import Any


def _git_commit() -> str | None:
    """The commit of the checkout torchheat runs from (``+dirty`` with uncommitted changes), or
    None for an installed package or without git."""
    root = Path(__file__).resolve().parents[1]
    if not (root / ".git").exists():
        return None
    try:
        sha = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                             capture_output=True, text=True, timeout=5, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain",
                                "--untracked-files=no"], capture_output=True, text=True,
                               timeout=5, check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return sha + ("+dirty" if dirty else "") if sha else None


def _cpu() -> str:
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as fh:
            for line in fh:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def provenance() -> dict[str, Any]:
    """Versions (torchheat and its git commit when run from a checkout, Python, torch, numpy,
    scipy), the BLAS numpy and scipy call (library, version, kernels), the CPU and its count,
    and the UTC time; JSON-able.

    Examples
    --------
    >>> p = provenance()
    >>> sorted(p)[:3], p["torchheat"] == __import__("torchheat").__version__
    (['blas', 'cpu', 'cpus'], True)
    """
    import numpy as np
    import scipy

    from . import __version__

    blas = []
    try:
        from threadpoolctl import threadpool_info

        for lib in threadpool_info():
            if lib.get("user_api") == "blas":
                arch = lib.get("architecture")
                item = f"{lib.get('internal_api')} {lib.get('version')}"
                blas.append(item + (f" ({arch})" if arch else ""))
    except Exception:  # noqa: BLE001 - a description only; never fail a run for it
        pass
    torch_version = sys.modules["torch"].__version__ if "torch" in sys.modules else None
    return {"torchheat": __version__, "git": _git_commit(),
            "python": platform.python_version(), "torch": torch_version,
            "numpy": np.__version__, "scipy": scipy.__version__,
            "blas": sorted(set(blas)), "cpu": _cpu(), "cpus": os.cpu_count(),
            "time_utc": datetime.datetime.now(datetime.timezone.utc).strftime(
                "%Y-%m-%d %H:%M UTC")}


def provenance_line(p: dict[str, Any] | None = None) -> str:
    """:func:`provenance` as one sentence for a summary."""
    p = provenance() if p is None else p
    git = f" (git {p['git']})" if p.get("git") else ""
    blas = ", BLAS " + "; ".join(p["blas"]) if p.get("blas") else ""
    torch = f", torch {p['torch']}" if p.get("torch") else ""
    return (f"Written by torchheat {p['torchheat']}{git}, Python {p['python']}{torch}, numpy "
            f"{p['numpy']}, scipy {p['scipy']}{blas}; {p['cpu']} x {p['cpus']}; "
            f"{p['time_utc']}.")
