"""The package type-checks with mypy under the project's configuration (``[tool.mypy]`` in
pyproject.toml; ``make lint`` runs the same check), so that a wrong annotation fails the suite CI
runs: the package ships its annotations (``torchheat/py.typed``) for its users' type checkers."""

from __future__ import annotations

import subprocess
import sys

import pytest
from conftest import ROOT


def test_mypy_finds_nothing():
    pytest.importorskip("mypy", reason="mypy is not installed (the dev extra installs it)")
    r = subprocess.run([sys.executable, "-m", "mypy"], capture_output=True, text=True,
                       cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stdout[-5000:] + r.stderr[-1000:]
