"""torchheat.eigen: torch-free eigensolves and the background workers of the command line."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import scipy.linalg
from conftest import ROOT, generic_sphere

from torchheat import HeatKernel, Mesh, laplacian
from torchheat.eigen import EigenWorkers, cotan_eigenpairs, eigenpairs

pytestmark = pytest.mark.filterwarnings("ignore:Sparse")
linux = pytest.mark.skipif(not sys.platform.startswith("linux"),
                           reason="EigenWorkers fork only on Linux")


def test_cotan_eigenpairs_identical_to_heat_kernel():
    # the workers' solve must give exactly what HeatKernel(mesh) computes in-process
    V, F = generic_sphere(4, seed=3)  # 2562 vertices: the ARPACK path
    hk = HeatKernel(Mesh(V, F), k=60, method="spectral")
    lam, phi = cotan_eigenpairs(V, F, k=60)
    assert np.array_equal(lam, hk.eigenvalues.numpy())
    assert np.array_equal(phi, hk.eigenvectors.numpy())


@pytest.mark.parametrize("kind", ["cotan", "fem"])
def test_eigenpairs_against_dense_eigh(kind):
    # ARPACK shift-invert (lumped: symmetric form; fem: generalized) vs dense eigh
    V, F = generic_sphere(3, seed=5)  # 642 vertices: above the dense cut-off for k = 20
    lap = laplacian(Mesh(V, F), kind=kind)
    W, A = lap.reduced()
    lam, phi = eigenpairs(W, A, 20)
    ref = scipy.linalg.eigh(W.toarray(), A.toarray(), eigvals_only=True)[:20]
    assert np.allclose(lam, np.maximum(ref, 0), rtol=1e-9, atol=1e-9)
    assert np.allclose(phi.T @ (A @ phi), np.eye(20), atol=1e-9)
    R = W @ phi - (A @ phi) * lam
    assert np.abs(R).max() <= 1e-8 * lam[-1] * np.abs(A @ phi).max()


def _same_up_to_sign(a: np.ndarray, b: np.ndarray, tol: float) -> bool:
    s = np.sign(np.sum(a * b, axis=0))
    return bool(np.abs(a - b * s).max() <= tol)


@linux
def test_workers_give_the_in_process_eigenpairs():
    meshes = [generic_sphere(4, seed=s) for s in (1, 2, 3)]  # 3 meshes, 2 workers
    with EigenWorkers(meshes, k=30, processes=2) as bg:
        assert bg.running == 2
        got = [bg.get(i) for i in range(3)]
    for (V, F), res in zip(meshes, got, strict=True):
        assert res is not None
        lam, phi = cotan_eigenpairs(V, F, k=30)
        # one BLAS thread in the worker: equal up to rounding (and eigenvector signs)
        assert np.allclose(res[0], lam, rtol=1e-10, atol=1e-9)
        assert _same_up_to_sign(res[1], phi, 1e-7)


@linux
def test_workers_off_or_failing_return_none():
    V, F = generic_sphere(2)
    with EigenWorkers([(V, F)], k=5, processes=0) as bg:
        assert bg.running == 0 and bg.get(0) is None
    bad = F.copy()
    bad[0, 0] = 10**6  # index out of range: the worker's solve raises
    with EigenWorkers([(V, bad), (V, F)], k=5, processes=1) as bg:
        assert bg.get(0) is None and "IndexError" in bg.errors[0]
        assert bg.get(1) is not None  # the same worker goes on with the next mesh
    assert bg.get(7) is None  # unknown index


@linux
def test_worker_killed_returns_none():
    V, F = generic_sphere(5)  # 10k vertices: still solving when killed
    with EigenWorkers([(V, F)], k=100, processes=1) as bg:
        bg._procs[0].kill()
        assert bg.get(0) is None


@linux
def test_worker_timeout_stops_it_and_returns_none():
    V, F = generic_sphere(5)  # 10k vertices, k = 100: ~1 s, far above the 0.05 s allowed
    with EigenWorkers([(V, F)], k=100, processes=1, timeout=0.05) as bg:
        assert bg.get(0) is None and "timed out" in bg.errors[0]
        bg._procs[0].join(timeout=5)
        assert not bg._procs[0].is_alive()


def test_package_and_eigen_import_without_torch():
    # the command line starts its workers before torch is imported: keep these torch-free
    code = ("import sys, torchheat, torchheat.eigen, torchheat.meshio; "
            "assert 'torch' not in sys.modules, 'torch imported'; "
            "torchheat.match; assert 'torch' in sys.modules")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr
