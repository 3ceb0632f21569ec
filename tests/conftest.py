"""Shared test fixtures: small generic meshes whose answers are known or computable."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
DATA = ROOT / "torchheat" / "data"


def load_script(name: str):
    """``scripts/<name>.py`` as a module (the scripts are not a package), registered in
    ``sys.modules`` as ``scripts.<name>`` while it runs (dataclasses look their module up)."""
    import importlib.util
    import sys

    key = f"scripts.{name}"
    spec = importlib.util.spec_from_file_location(key, ROOT / "scripts" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[key] = mod
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        del sys.modules[key]
        raise
    return mod


def generic_sphere(subdivisions: int = 3, seed: int = 0, noise: float = 0.05):
    """An ellipsoid with random radial bumps: no symmetry, irregular triangles."""
    m = trimesh.creation.icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    V = m.vertices * np.array([1.0, 0.7, 0.5])
    V = V * (1.0 + noise * rng.standard_normal((len(V), 1)))
    return V, np.asarray(m.faces, dtype=np.int64)


def flat_grid(nx: int = 12, ny: int = 9, lx: float = 1.0, ly: float = 0.75):
    """A flat rectangle triangulated with one diagonal per cell (geodesics are Euclidean)."""
    xs, ys = np.meshgrid(np.linspace(0, lx, nx), np.linspace(0, ly, ny), indexing="ij")
    V = np.stack([xs.ravel(), ys.ravel(), np.zeros(nx * ny)], axis=1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    a, b = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel()
    c, d = idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return V, F


def torus_faces(N: int):
    """Faces of an N x N periodic grid (a flat torus), one diagonal per cell."""
    idx = np.arange(N * N).reshape(N, N)
    a = idx.ravel()
    b = np.roll(idx, -1, axis=0).ravel()
    c = np.roll(np.roll(idx, -1, axis=0), -1, axis=1).ravel()
    d = np.roll(idx, -1, axis=1).ravel()
    return np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def kill_after_first_record(cmd: list[str], results: Path, env: dict | None = None,
                            timeout: float = 60.0) -> int:
    """Run ``cmd`` (a batch run) in a subprocess and SIGKILL it as soon as ``results`` holds a
    complete line; returns the number of lines then. Fails if the run ends first."""
    import signal
    import subprocess
    import time

    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        end = time.monotonic() + timeout
        while time.monotonic() < end and proc.poll() is None:
            if results.is_file() and results.read_bytes().count(b"\n") >= 1:
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run finished before it could be killed"
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.wait(timeout=30)
    return results.read_bytes().count(b"\n")


def write_off(path: Path, V: np.ndarray, F: np.ndarray, *, raw_vertices: list[str] | None = None):
    """An OFF file of V, F (or of the given vertex lines)."""
    lines = ["OFF", f"{len(V)} {len(F)} 0"]
    lines += raw_vertices if raw_vertices is not None else [
        f"{x:.17g} {y:.17g} {z:.17g}" for x, y, z in V
    ]
    lines += [f"3 {a} {b} {c}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")
    return path


def deformed_spheres(folder: Path, n: int = 4, subdivisions: int = 3) -> list[Path]:
    """``n`` OFF files of one generic sphere (same connectivity: identity ground truth), each
    bent and rescaled differently (near-isometric to each other)."""
    V, F = generic_sphere(subdivisions)
    folder.mkdir(parents=True, exist_ok=True)
    out = []
    for i in range(n):
        a = 0.15 * i
        bend = np.stack([V[:, 0], V[:, 1] + a * V[:, 0] ** 2, V[:, 2]], axis=1)
        out.append(write_off(folder / f"blob{i}.off", bend * (1 + 0.02 * i), F))
    return out


@pytest.fixture
def sphere_mesh():
    from torchheat import Mesh

    V, F = generic_sphere(3)
    return Mesh(V, F, name="generic-sphere")


@pytest.fixture
def small_mesh():
    from torchheat import Mesh

    V, F = generic_sphere(2, seed=1)
    return Mesh(V, F, name="small-generic")
