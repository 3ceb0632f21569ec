"""What an install that is not editable holds: a wheel built from the source tree must carry
every subpackage, the bundled meshes and the ``py.typed`` marker, and import without the source
tree beside it (the development install is editable, so the rest of the suite would not notice a
missing one)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
from conftest import ROOT


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A wheel built from a copy of the source tree (the build writes no file into it)."""
    pytest.importorskip("setuptools", minversion="77")  # the dev extra installs it
    src = tmp_path_factory.mktemp("src")
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    shutil.copytree(ROOT / "torchheat", src / "torchheat",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                    "--no-index", "-q", "-w", str(out), str(src)],
                   check=True, capture_output=True, cwd=src)
    (whl,) = out.glob("torchheat-*.whl")
    return whl


def test_wheel_holds_every_subpackage_and_the_bundled_meshes(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    packages = sorted(p.parent.relative_to(ROOT).as_posix()
                      for p in (ROOT / "torchheat").rglob("__init__.py"))
    assert "torchheat/heat" in packages  # the one a hand-written list once left out
    missing = [p for p in packages if f"{p}/__init__.py" not in names]
    assert not missing, f"subpackages missing from the wheel: {missing}"
    modules = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "torchheat").rglob("*.py"))
    assert not [m for m in modules if m not in names]
    meshes = sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "torchheat/data").glob("*"))
    assert meshes and not [m for m in meshes if m not in names]
    assert "torchheat/py.typed" in names  # the marker that the package ships its annotations


def test_wheel_imports_and_matches_without_the_source_tree(wheel: Path, tmp_path: Path) -> None:
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    # the editable install's finder is removed, so every import must come from the wheel
    code = f"""
import sys
sys.meta_path[:] = [f for f in sys.meta_path if "editable" not in repr(f).lower()]
sys.path.insert(0, {str(site)!r})
import torchheat
assert torchheat.__file__.startswith({str(site)!r}), torchheat.__file__
import torchheat.batch, torchheat.cli, torchheat.datasets, torchheat.heat, torchheat.matching
M = torchheat.load_mesh(torchheat.__path__[0] + "/data/spot.obj")
c = torchheat.match(M, M, landmark=(0, 0), method="paper")
n = c.map.numel()
assert int((c.map == __import__("torch").arange(n)).sum()) > 0.9 * n
print("ok")
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       cwd=tmp_path, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip().endswith("ok")
