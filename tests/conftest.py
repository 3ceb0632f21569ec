"""Shared test fixtures: small generic meshes whose answers are known or computable."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
DATA = ROOT / "torchheat" / "data"


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
