"""Heat kernel columns and HKS against independent references (dense expm, expm_multiply,
an analytic flat-torus kernel), and the guarantees HeatKernel states."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import torch
from conftest import flat_grid, generic_sphere, torus_faces
from scipy.sparse.linalg import expm_multiply

from torchheat import HeatKernel, Mesh, default_times, laplacian
from torchheat.heat import chebyshev_coefficients, chebyshev_degree
from torchheat.operators import Laplacian, cotmatrix_intrinsic


def rel_errors(C: torch.Tensor, ref: np.ndarray) -> np.ndarray:
    """Relative L2 error per (source, time); C, ref: [B, n, J]."""
    C = C.double().numpy()
    return np.linalg.norm(C - ref, axis=1) / np.linalg.norm(ref, axis=1)


def dense_columns(lap: Laplacian, sources, times) -> np.ndarray:
    """k_t(p, .) = exp(-t L) A^-1 e_p with dense expm on the reduced operator."""
    W, A = lap.reduced()
    a = A.diagonal()
    L = W.toarray() / a[:, None]
    idx = np.flatnonzero(lap.active)
    pos = {int(v): i for i, v in enumerate(idx)}
    out = np.zeros((len(sources), lap.n_vertices, len(times)))
    for j, t in enumerate(times):
        E = scipy.linalg.expm(-t * L)
        for b, p in enumerate(sources):
            if p in pos:
                out[b, idx, j] = E[:, pos[p]] / a[pos[p]]
    return out


def test_chebyshev_coefficients_reproduce_exp():
    x = np.linspace(-1, 1, 101)
    for c in (0.1, 5.0, 80.0):
        K = chebyshev_degree(c, 1e-12)
        a = chebyshev_coefficients(c, K)
        np.testing.assert_allclose(
            np.polynomial.chebyshev.chebval(x, a), np.exp(-c * (x + 1)), atol=2e-12
        )
    # the degree rule of thumb measured on meshes: about 3.6 sqrt(t lambda_max) at 1e-6
    c = 0.5 * 2.0 * 1e5
    assert 3.0 < chebyshev_degree(c, 1e-6) / np.sqrt(2 * c) < 4.0


@pytest.mark.parametrize("method", ["hybrid", "chebyshev"])
@pytest.mark.parametrize("rtol", [1e-6, 1e-9])
def test_columns_match_dense_expm_at_every_time(small_mesh, method, rtol):
    hk = HeatKernel(small_mesh, rtol=rtol, method=method, k=20)
    src = [0, 41, 97, 161]
    C = hk.columns(src)
    ref = dense_columns(hk.laplacian, src, hk.times.numpy())
    err = rel_errors(C, ref)
    assert err.max() <= rtol, err.max(axis=0)
    # the reported bound is a true bound
    assert np.all(err <= hk.error_bound.numpy() * (1 + 1e-6) + 1e-12)  # + rounding
    assert hk.error_bound.max() <= rtol
    if method == "hybrid":
        assert hk.plan["spectral"].any() and not hk.plan["spectral"].all()


def test_with_times_is_a_new_solver_on_the_same_eigenbasis(small_mesh):
    hk = HeatKernel(small_mesh, rtol=1e-8, k=20)
    t0 = hk.times.clone()
    plan0 = hk.plan
    src, times = [0, 41, 97], [0.003, 0.05, 0.7]
    hk2 = hk.with_times(times)
    assert torch.equal(hk.times, t0) and np.array_equal(hk.plan["degree"], plan0["degree"])
    assert hk2.times.tolist() == times and np.shares_memory(hk2._phi_red, hk._phi_red)
    assert hk2.plan["timings"] == plan0["timings"]  # the set-up it shares
    # columns at the new times against dense expm, and the old solver still at its own
    err = rel_errors(hk2.columns(src), dense_columns(hk.laplacian, src, times))
    assert err.max() <= 1e-8
    err0 = rel_errors(hk.columns(src), dense_columns(hk.laplacian, src, t0.numpy()))
    assert err0.max() <= 1e-8
    with pytest.raises(ValueError, match="positive"):
        hk.with_times([0.1, -1.0])
    with pytest.warns(DeprecationWarning, match="with_times"):
        hk.set_times(times)  # deprecated: in place
    assert hk.times.tolist() == times


def test_truncated_spectrum_alone_is_wrong_at_small_t(small_mesh):
    hk = HeatKernel(small_mesh, method="spectral", k=20)
    src = [3, 50]
    ref = dense_columns(hk.laplacian, src, hk.times.numpy())
    err = rel_errors(hk.columns(src), ref)
    assert err[:, 0].min() > 1e-2  # t = 0.001: a 20-term spectrum is far off
    assert err[:, -1].max() < 1e-9  # t = 2: exact
    assert np.all(err <= hk.error_bound.numpy() * (1 + 1e-6) + 1e-12)  # + rounding


def test_columns_match_expm_multiply_and_the_dense_spectrum_on_a_larger_mesh():
    # small times against scipy's expm_multiply; the large ones (where expm_multiply needs
    # t |L| steps: 22 s at t = 2 here) against the full dense spectrum of the symmetric
    # operator A^-1/2 W A^-1/2 (LAPACK eigh, every mode, no truncation)
    V, F = generic_sphere(4, seed=5)  # 2562 vertices
    mesh = Mesh(V, F)
    hk = HeatKernel(mesh)
    src = [10, 2000]
    C = hk.columns(src).numpy()
    lap = hk.laplacian
    a = lap.mass_scipy.diagonal()
    times = hk.times.numpy()
    E = np.zeros((len(a), len(src)))
    E[src, range(len(src))] = 1.0 / a[src]
    L = sp.diags(1 / a) @ lap.stiffness_scipy
    s = 1 / np.sqrt(a)
    lam, U = scipy.linalg.eigh(s[:, None] * lap.stiffness_scipy.toarray() * s[None, :],
                               driver="evd")
    refs = {j: expm_multiply(-times[j] * L, E) for j in (0, 3)}
    refs |= {j: s[:, None] * (U @ (np.exp(-times[j] * lam)[:, None] * (U[src].T * s[src])))
             for j in (6, 9)}
    for j, ref in refs.items():
        for b, p in enumerate(src):
            err = np.linalg.norm(C[b, :, j] - ref[:, b]) / np.linalg.norm(ref[:, b])
            assert err <= 1e-6, (p, times[j], err)


def test_flat_torus_kernel_is_the_analytic_fourier_kernel():
    # periodic N x N grid of the unit square: the cotan operator is the 5-point stencil, whose
    # heat kernel is diagonal in the Fourier basis with symbol (4/h^2)(sin^2 + sin^2).
    N = 20
    h = 1.0 / N
    F = torus_faces(N)
    lengths = np.tile([h, h * np.sqrt(2), h], (len(F), 1))
    lengths[len(F) // 2 :] = [h, h, h * np.sqrt(2)]
    W = cotmatrix_intrinsic(lengths, F).to_dense().numpy()
    lap = Laplacian(sp.csr_matrix(W), sp.diags(np.full(N * N, h * h)).tocsr(), "cotan",
                    "neumann", np.ones(N * N, bool), 1.0, True)
    times = default_times()
    hk = HeatKernel(lap, times=times, k=30)
    p = 7 * N + 3
    C = hk.columns([p]).numpy()[0]
    ks = np.fft.fftfreq(N) * N
    sym = (4 / h**2) * (np.sin(np.pi * ks * h)[:, None] ** 2 + np.sin(np.pi * ks * h)[None] ** 2)
    for j, t in enumerate(times.numpy()):
        delta = np.zeros((N, N))
        delta[7, 3] = 1.0 / (h * h)
        ref = np.real(np.fft.ifft2(np.fft.fft2(delta) * np.exp(-t * sym))).ravel()
        assert np.linalg.norm(C[:, j] - ref) / np.linalg.norm(ref) <= 1e-6
    # at large t the kernel tends to 1 / area = 1 everywhere
    assert np.allclose(C[:, -1], 1.0, atol=1e-6)


def test_dirichlet_columns_match_dense_expm():
    V, F = flat_grid(14, 11)
    rng = np.random.default_rng(0)
    V[:, 2] = 0.1 * rng.standard_normal(len(V))  # bumpy, not flat
    mesh = Mesh(V, F)
    hk = HeatKernel(mesh, boundary="dirichlet", k=15)
    bnd = np.flatnonzero(mesh.boundary_vertices().numpy())
    src = [int(bnd[0]), 60, 80]
    assert not bnd.tolist().count(60) and not bnd.tolist().count(80)
    C = hk.columns(src)
    ref = dense_columns(hk.laplacian, src, hk.times.numpy())
    assert torch.all(C[0] == 0)  # a boundary source carries no heat
    assert torch.all(C[:, bnd] == 0)
    err = rel_errors(C[1:], ref[1:])
    assert err.max() <= 1e-6


def test_hks_full_basis_is_exact_and_truncation_is_bounded(small_mesh):
    n = small_mesh.n_vertices
    full = HeatKernel(small_mesh, k=n)  # all eigenpairs: exact
    h = full.hks().numpy()
    ref = np.stack(
        [np.diagonal(dense_columns(full.laplacian, range(n), [t])[:, :, 0])
         for t in full.times.numpy()],
        axis=1,
    )
    np.testing.assert_allclose(h, ref, rtol=1e-8)
    trunc = HeatKernel(small_mesh, k=30)
    ht = trunc.hks().numpy()
    rel = np.abs(ht - ref) / ref
    assert np.all(rel <= trunc.hks_error_bound.numpy() + 1e-12)
    assert rel[:, -1].max() < 1e-8 and rel[:, 0].max() > 1e-3


def test_batched_equals_per_source_loop(sphere_mesh):
    hk = HeatKernel(sphere_mesh, block=8)  # several blocks
    src = list(range(0, 600, 29))
    C = hk.columns(src)
    for b, p in enumerate(src[:5]):
        np.testing.assert_allclose(C[b].numpy(), hk.columns([p])[0].numpy(), rtol=1e-10,
                                   atol=1e-12)


def test_invariance_under_permutation_rigid_motion_and_scale(sphere_mesh):
    V, F = sphere_mesh.numpy()
    rng = np.random.default_rng(7)
    perm = rng.permutation(len(V))
    inv = np.argsort(perm)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    V2 = (3.0 * V[perm]) @ Q.T + np.array([1.0, -2.0, 5.0])  # scaled too: unit-area convention
    F2 = inv[F]
    src = [5, 123, 400]
    C1 = HeatKernel(sphere_mesh).columns(src).numpy()
    C2 = HeatKernel(Mesh(V2, F2)).columns(inv[src]).numpy()
    np.testing.assert_allclose(C2[:, inv, :], C1, rtol=1e-5, atol=1e-8)


def test_float32_accuracy_is_as_documented(sphere_mesh):
    src = [1, 300]
    ref = HeatKernel(sphere_mesh, rtol=1e-9).columns(src).numpy()
    with pytest.warns(UserWarning, match="float32"):
        hk = HeatKernel(sphere_mesh, dtype=torch.float32)
    C = hk.columns(src)
    assert C.dtype == torch.float32
    assert rel_errors(C, ref).max() < 1e-4
    # denormals are flushed during the float32 recurrence only, not left flushed afterwards
    tiny = torch.tensor([1e-310], dtype=torch.float64)
    assert float(tiny * 1.0) != 0.0


def test_bad_queries(small_mesh):
    hk = HeatKernel(small_mesh, times=[0.01])
    with pytest.raises(IndexError, match="out of range"):
        hk.columns([small_mesh.n_vertices])
    with pytest.raises(ValueError, match="positive"):
        HeatKernel(small_mesh, times=[0.0, 1.0])
    # a NaN or an infinite time passed the positivity test ("cannot convert float NaN" later)
    for bad in ([float("nan")], [0.1, float("inf")]):
        with pytest.raises(ValueError, match="positive finite"):
            HeatKernel(small_mesh, times=bad)
        with pytest.raises(ValueError, match="positive finite"):
            hk.with_times(bad)
    # a non-integral source was truncated to a vertex
    for bad in ([1.5], [True], [float("inf")], [1 + 0j]):  # inf and complex slipped through
        with pytest.raises(TypeError, match="integer indices"):
            hk.columns(bad)
    assert torch.equal(hk.columns([1.0, 2]), hk.columns([1, 2]))
    with pytest.raises(ValueError, match="method"):
        HeatKernel(small_mesh, method="magic")
    with pytest.raises(ValueError, match="spectral"):
        HeatKernel(laplacian(small_mesh, kind="fem"), method="chebyshev")


def test_given_eigenpairs_of_another_mesh_are_refused():
    # a stale cache or another mesh's eigenpairs (same vertex count) must not silently serve
    A, B = Mesh(*generic_sphere(3, seed=1)), Mesh(*generic_sphere(3, seed=2))
    hk = HeatKernel(A, k=20, method="spectral")
    own = (hk.eigenvalues, hk.eigenvectors)
    again = HeatKernel(A, k=20, method="spectral", eigenpairs=own)  # its own: accepted
    assert torch.equal(again.eigenvalues, hk.eigenvalues)
    with pytest.raises(ValueError, match="not those of this operator"):
        HeatKernel(B, k=20, method="spectral", eigenpairs=own)


@pytest.mark.parametrize("boundary", ["neumann", "dirichlet"])
def test_vertex_mass_is_the_eigenvectors_inner_product(boundary):
    V, F = flat_grid(14, 11)
    hk = HeatKernel(Mesh(V, F), k=12, boundary=boundary)
    a = hk.vertex_mass.numpy()
    phi = hk.eigenvectors.numpy()
    np.testing.assert_allclose(phi.T @ (a[:, None] * phi), np.eye(12), atol=1e-10)
    on_boundary = Mesh(V, F).boundary_vertices().numpy()
    if boundary == "neumann":  # the unit-area shape's lumped masses
        assert a.sum() == pytest.approx(1.0) and np.all(a > 0)
    else:  # boundary vertices are not degrees of freedom
        assert np.all(a[on_boundary] == 0) and np.all(a[~on_boundary] > 0) and a.sum() < 1
