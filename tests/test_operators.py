"""Laplace–Beltrami operators against independent references."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import torch
import trimesh
from conftest import flat_grid, generic_sphere, torus_faces

from torchheat import Mesh, cotmatrix, laplacian, massmatrix
from torchheat.operators import cotmatrix_intrinsic


def test_cotmatrix_on_flat_grid_is_the_five_point_stencil():
    # Right triangles: the diagonal edges have cot(90 deg) = 0, axis edges weight 1/2 + 1/2.
    V, F = flat_grid(6, 5, lx=5.0, ly=4.0)  # unit cells
    W = cotmatrix(V, F).to_dense().numpy()
    n = V.shape[0]
    ref = np.zeros((n, n))
    nx, ny = 6, 5
    idx = np.arange(n).reshape(nx, ny)
    for i in range(nx):
        for j in range(ny):
            for di, dj in ((1, 0), (0, 1)):
                if i + di < nx and j + dj < ny:
                    p, q = idx[i, j], idx[i + di, j + dj]
                    on_edge = (di == 1 and (j == 0 or j == ny - 1)) or (
                        dj == 1 and (i == 0 or i == nx - 1)
                    )
                    w = 0.5 if on_edge else 1.0  # boundary edges have one triangle
                    ref[p, q] = ref[q, p] = -w
    ref -= np.diag(ref.sum(axis=1))
    np.testing.assert_allclose(W, ref, atol=1e-12)


def test_cotmatrix_symmetric_psd_and_linear_precision():
    V, F = flat_grid(9, 7)
    rng = np.random.default_rng(3)
    V[:, :2] += 0.02 * rng.standard_normal((len(V), 2))  # irregular but planar
    W = cotmatrix(V, F).to_dense().numpy()
    np.testing.assert_allclose(W, W.T, atol=1e-12)
    assert np.linalg.eigvalsh(W).min() > -1e-10
    np.testing.assert_allclose(W.sum(axis=1), 0.0, atol=1e-12)
    # a linear function is harmonic at interior vertices of a planar mesh
    f = 2.0 * V[:, 0] - 3.0 * V[:, 1]
    interior = ~Mesh(V, F).boundary_vertices().numpy()
    np.testing.assert_allclose((W @ f)[interior], 0.0, atol=1e-10)


def test_orientation_does_not_change_the_operator():
    V, F = generic_sphere(2)
    F2 = F.copy()
    F2[::3] = F2[::3, ::-1]  # flip a third of the faces
    np.testing.assert_allclose(
        cotmatrix(V, F).to_dense().numpy(), cotmatrix(V, F2).to_dense().numpy(), atol=1e-12
    )


def test_mass_matrices_sum_to_area_and_normalisation():
    V, F = generic_sphere(2)
    area = trimesh.Trimesh(V, F, process=False).area
    for kind in ("lumped", "consistent"):
        M = massmatrix(V, F, kind).to_dense().numpy()
        assert M.sum() == pytest.approx(area, rel=1e-12)
    lap = laplacian(Mesh(V, F))
    assert float(lap.mass.sum()) == pytest.approx(1.0, rel=1e-12)
    assert lap.area == pytest.approx(area, rel=1e-12)
    assert lap.W.layout == torch.sparse_csr and lap.S.layout == torch.sparse_csr


@pytest.mark.parametrize("kind", ["cotan", "fem", "robust"])
def test_sphere_spectrum_matches_l_l_plus_1(kind):
    m = trimesh.creation.icosphere(4)  # 2562 vertices
    lap = laplacian(Mesh(m.vertices, m.faces), kind=kind)
    W, M = lap.reduced()
    lam = scipy.linalg.eigh(W.toarray(), M.toarray(), eigvals_only=True, subset_by_index=[0, 15])
    # unit area: the unit sphere's l(l+1) times its area 4 pi
    ref = np.array([l_ * (l_ + 1) for l_ in range(4) for _ in range(2 * l_ + 1)]) * 4 * np.pi
    np.testing.assert_allclose(lam[1:], ref[1:], rtol=0.02)
    assert abs(lam[0]) < 1e-8


def test_flat_torus_spectrum_is_analytic():
    # unit square torus (area 1): discrete eigenvalues of the 5-point stencil,
    # (4/h^2)(sin^2(pi k h) + sin^2(pi l h)), converging to 4 pi^2 (k^2 + l^2).
    N = 24
    F = torus_faces(N)
    h = 1.0 / N
    lengths = np.tile([h, h * np.sqrt(2), h], (len(F), 1))
    # face [a, b, c] with b = a + x, c = a + x + y: edge opposite a is b-c (h),
    # opposite b is a-c (diagonal), opposite c is a-b (h); second face [a, c, d] likewise
    lengths[len(F) // 2 :] = [h, h, h * np.sqrt(2)]
    W = cotmatrix_intrinsic(lengths, F).to_dense().numpy()
    M = np.full(N * N, h * h)
    lam = np.sort(np.linalg.eigvalsh(W / np.sqrt(np.outer(M, M))))[:13]
    ks = np.arange(N)
    disc = np.sort(
        ((4 / h**2) * (np.sin(np.pi * ks * h)[:, None] ** 2 + np.sin(np.pi * ks * h)[None] ** 2))
        .ravel()
    )[:13]
    np.testing.assert_allclose(lam, disc, rtol=1e-10, atol=1e-9)
    cont = np.sort([4 * np.pi**2 * (a * a + b * b) for a in range(-3, 4) for b in range(-3, 4)])
    np.testing.assert_allclose(lam[1:13], cont[1:13], rtol=0.03)


def test_dirichlet_removes_boundary_vertices():
    V, F = flat_grid(8, 8)
    mesh = Mesh(V, F)
    lap = laplacian(mesh, boundary="dirichlet")
    bnd = mesh.boundary_vertices().numpy()
    assert lap.active.sum() == (~bnd).sum()
    W, A = lap.reduced()
    assert W.shape == (int((~bnd).sum()),) * 2
    # Dirichlet spectrum of the square [0,1]x[0,1]: pi^2 (k^2 + l^2), k, l >= 1; at unit area
    lam = scipy.linalg.eigh(W.toarray(), A.toarray(), eigvals_only=True)[0]
    assert lam == pytest.approx(2 * np.pi**2, rel=0.1)


def test_bad_arguments():
    V, F = generic_sphere(1)
    with pytest.raises(ValueError, match="kind"):
        laplacian(Mesh(V, F), kind="nope")
    with pytest.raises(ValueError, match="boundary"):
        laplacian(Mesh(V, F), boundary="robin")


_WARNINGS_SCRIPT = """
import sys, warnings
import torch
import trimesh
from torchheat import HeatKernel, Mesh, laplacian

with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    if sys.argv[1] == "torch":  # the control: torch's own construction warns
        torch.sparse_csr_tensor(torch.tensor([0, 1]), torch.tensor([0]), torch.tensor([1.0]),
                                size=(1, 1))
    else:
        s = trimesh.creation.icosphere(2)
        L = laplacian(Mesh(s.vertices, s.faces))
        L.W, L.M, L.S
        HeatKernel(Mesh(s.vertices, s.faces), times=[0.01, 1.0]).columns([0])
        # torchheat's own warnings still come through
        Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]],
             [[0, 1, 2], [0, 1, 3], [0, 1, 4]], name="fan")
for w in caught:
    print(w.category.__name__, "|", str(w.message).splitlines()[0])
"""


def test_no_torch_sparse_warnings_from_operators():
    # torch warns once per process: each case runs in a fresh interpreter
    import subprocess
    import sys

    def run(case):
        return subprocess.run([sys.executable, "-c", _WARNINGS_SCRIPT, case], check=True,
                              capture_output=True, text=True, timeout=120).stdout

    control = run("torch")
    assert "Sparse CSR tensor support is in beta" in control
    assert "Sparse invariant checks are implicitly disabled" in control
    lines = run("torchheat").splitlines()
    assert not [ln for ln in lines if "Sparse" in ln]
    assert len(lines) == 1 and lines[0].startswith("MeshWarning | fan: 1 non-manifold edge")
