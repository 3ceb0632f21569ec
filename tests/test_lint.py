"""The code is ruff-clean (the project's standard; `make lint` runs the same check), so that a
lint error fails the suite CI runs instead of waiting for someone to run ruff by hand."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT


def _ruff() -> list[str] | None:
    exe = Path(sys.executable).parent / "ruff"
    if exe.exists():
        return [str(exe)]
    found = shutil.which("ruff")
    return [found] if found else None


def test_ruff_finds_nothing():
    ruff = _ruff()
    if ruff is None:
        pytest.skip("ruff is not installed (the dev extra installs it)")
    r = subprocess.run([*ruff, "check", "--no-cache", "torchheat", "scripts", "tests"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-1000:]
