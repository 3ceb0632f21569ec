"""torchheat.eigen: torch-free eigensolves and the background workers of the command line."""

from __future__ import annotations

import subprocess
import sys
import warnings

import numpy as np
import pytest
import scipy.linalg
import scipy.sparse as sp
import scipy.sparse.linalg as sla
from conftest import ROOT, generic_sphere

from torchheat import HeatKernel, Mesh, eigen, laplacian
from torchheat.eigen import EigensolverError, EigenWorkers, cotan_eigenpairs, eigenpairs
from torchheat.heat import _check_eigenpairs

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
def test_workers_solve_one_mesh_at_two_sizes():
    # the command line's --fine: the default basis, then a larger one of the same mesh
    V, F = generic_sphere(4, seed=5)
    with EigenWorkers([(V, F), (V, F)], k=[10, 25], processes=2) as bg:
        small, large = bg.get(0), bg.get(1)
    assert small[1].shape == (len(V), 10) and large[1].shape == (len(V), 25)
    lam, _ = cotan_eigenpairs(V, F, k=25)
    assert np.allclose(large[0], lam, rtol=1e-10, atol=1e-9)
    assert np.allclose(small[0], lam[:10], rtol=1e-10, atol=1e-9)
    with pytest.raises(ValueError, match="2 meshes"):
        EigenWorkers([(V, F), (V, F)], k=[10, 25, 30], processes=0)
    # one worker for both: the larger basis extends the smaller one, which it keeps as is
    with EigenWorkers([(V, F), (V, F)], k=[10, 25], processes=1) as bg:
        small, large = bg.get(0), bg.get(1)
    assert np.array_equal(large[0][:10], small[0]) and np.array_equal(large[1][:, :10], small[1])
    assert np.allclose(large[0], lam, rtol=1e-10, atol=1e-9)
    # a third, middle size after the large one: the small basis is still held and lent to it
    with EigenWorkers([(V, F)] * 3, k=[10, 25, 15], processes=1) as bg:
        small, mid = bg.get(0), bg.get(2)
    assert np.array_equal(mid[1][:, :10], small[1])
    assert np.allclose(mid[0], lam[:15], rtol=1e-10, atol=1e-9)


def test_lenders_hold_a_basis_only_for_a_larger_solve_of_its_mesh():
    # which earlier job lends its pairs to which later one; a basis nobody extends is not held
    a, b = generic_sphere(2, seed=1), generic_sphere(2, seed=2)
    jobs = [(0, *a, 10), (1, *b, 10), (2, *a, 25), (3, *a, 15), (4, *b, 5), (5, *b, 30),
            (6, *a, 40)]
    # b30 extends b10, not the later b5; a40 extends a25 (the most pairs below its own)
    assert eigen._lenders(jobs) == {2: 0, 3: 0, 5: 1, 6: 2}
    assert eigen._lenders([(0, *a, 10), (1, *b, 20)]) == {}


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


def test_worker_solves_on_while_its_results_wait_to_be_read(monkeypatch):
    # a pipe holds 64 KB: a worker's next solve must not wait until the parent reads the last
    # result (the parent reads only after ``import torch``); results go out from a thread
    import threading

    import threadpoolctl

    monkeypatch.setattr(threadpoolctl, "threadpool_limits", lambda n: None)  # not this process
    solved: list[int] = []
    monkeypatch.setattr(eigen, "cotan_eigenpairs",
                        lambda V, F, k, known=None: (solved.append(len(V))
                                                     or (np.zeros(k), V[:, :1])))
    release, sent, closed = threading.Event(), [], []

    class Conn:  # the parent not reading yet: every send blocks until released
        def send(self, item):
            assert release.wait(30)
            sent.append(item[0])

        def close(self):
            closed.append(True)

    jobs = [(i, np.zeros((10 + i, 3)), np.zeros((1, 3), dtype=np.int64), 4) for i in range(3)]
    child = threading.Thread(target=eigen._solve_in_child, args=(Conn(), jobs))
    child.start()
    for _ in range(3000):  # all three solved while the first result is still unread
        if len(solved) == 3:
            break
        threading.Event().wait(0.01)
    assert solved == [10, 11, 12] and sent == []
    release.set()
    child.join(30)
    assert sent == [0, 1, 2] and closed == [True]

    # the parent gone (a broken pipe): the worker stops solving and closes its end
    solved.clear()
    attempted = threading.Event()

    class Gone:
        def send(self, item):
            attempted.set()
            raise BrokenPipeError("the parent has gone")

        def close(self):
            closed.append("gone")

    def solve(V, F, k, known=None):
        solved.append(len(V))
        if len(solved) == 2:  # the first result's send has failed meanwhile
            assert attempted.wait(30)
            threading.Event().wait(0.2)
        return np.zeros(k), V[:, :1]

    monkeypatch.setattr(eigen, "cotan_eigenpairs", solve)
    eigen._solve_in_child(Gone(), jobs)
    assert solved == [10, 11] and closed[-1] == "gone"


@linux
def test_workers_nice_value_and_results():
    import os

    V, F = generic_sphere(5)  # 10k vertices, k = 100: still solving while polled
    base = os.getpriority(os.PRIO_PROCESS, 0)
    with EigenWorkers([(V, F)], k=100, processes=1, nice=5) as bg:
        pid = bg._procs[0].pid
        seen = base
        for _ in range(500):
            try:
                seen = os.getpriority(os.PRIO_PROCESS, pid)
            except OSError:  # already gone
                break
            if seen != base or not bg._procs[0].is_alive():
                break
            bg._procs[0].join(0.01)
        got = bg.get(0)
    assert seen == min(base + 5, 19)
    lam, phi = cotan_eigenpairs(V, F, k=100)
    assert np.allclose(got[0], lam, rtol=1e-10, atol=1e-9)


def test_package_and_eigen_import_without_torch():
    # the command line starts its workers before torch is imported: keep these torch-free
    code = ("import sys, torchheat, torchheat.eigen, torchheat.meshio; "
            "assert 'torch' not in sys.modules, 'torch imported'; "
            "torchheat.match; assert 'torch' in sys.modules")
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 0, res.stderr


# ------------------------------------------------------------------------------------------
# robustness: missed multiplicities, failures of each path and their fallbacks
# ------------------------------------------------------------------------------------------
def _periodic_grid(N: int = 20):
    """5-point Laplacian of the N x N periodic unit square (the flat torus) and its mass."""
    h = 1.0 / N
    T = sp.diags([2.0 * np.ones(N), -np.ones(N - 1), -np.ones(N - 1)], [0, 1, -1]).tolil()
    T[0, N - 1] = T[N - 1, 0] = -1.0
    eye = sp.identity(N)
    W = (sp.kron(T, eye) + sp.kron(eye, T)).tocsr()
    A = sp.diags(np.full(N * N, h * h)).tocsr()
    s = np.sin(np.pi * np.arange(N) / N) ** 2
    exact = np.sort(((4.0 / h**2) * (s[:, None] + s[None, :])).ravel())
    return W, A, exact


@pytest.mark.parametrize("k", [30, 60, 100])
def test_multiple_eigenvalues_are_all_found(k):
    # the flat torus has eigenvalues of multiplicity 8; plain Lanczos missed two copies of
    # 191.94 at k = 30 and k = 60 (every later mode shifted: a silently wrong heat kernel)
    W, A, exact = _periodic_grid(20)
    lam, phi = eigenpairs(W, A, k)
    assert np.allclose(lam, exact[:k], rtol=1e-9, atol=1e-8)
    assert np.allclose(phi.T @ (A @ phi), np.eye(k), atol=1e-8)


@pytest.mark.parametrize("k0, k", [(30, 60), (27, 100)])
def test_extension_of_known_eigenpairs_finds_the_analytic_spectrum(k0, k):
    # the flat torus (multiplicity 8): the known pairs kept as given, the next ones solved
    # with them projected out, every copy of a multiplet split by k0 found
    W, A, exact = _periodic_grid(20)
    lam0, phi0 = eigenpairs(W, A, k0)
    lam, phi = eigenpairs(W, A, k, known=(lam0, phi0))
    assert np.array_equal(lam[:k0], lam0) and np.array_equal(phi[:, :k0], phi0)
    assert np.allclose(lam, exact[:k], rtol=1e-9, atol=1e-8)
    assert np.allclose(phi.T @ (A @ phi), np.eye(k), atol=1e-8)
    R = W @ phi - (A @ phi) * lam
    assert np.abs(R).max() <= 1e-8 * lam[-1] * np.abs(A @ phi).max()


def test_extension_equals_the_full_solve_and_falls_back_when_the_known_are_not_lowest(
        monkeypatch):
    V, F = generic_sphere(4, seed=3)  # 2562 vertices: the ARPACK path
    W, A = laplacian(Mesh(V, F)).reduced()
    lam_full, phi_full = eigenpairs(W, A, 60)
    lam0, phi0 = eigenpairs(W, A, 25)
    calls = []
    monkeypatch.setattr(eigen, "_lumped", lambda *a: calls.append(a) or None)
    lam, phi = eigenpairs(W, A, 60, known=(lam0, phi0))  # no full solve asked for
    assert not calls
    assert np.allclose(lam, lam_full, rtol=1e-12, atol=0)
    assert _same_up_to_sign(phi, phi_full, 1e-7)
    monkeypatch.undo()
    # pairs 2..25 are no lowest set: the extension finds the first two below them, and the
    # full solve answers instead
    lam2, phi2 = eigenpairs(W, A, 60, known=(lam0[2:], phi0[:, 2:]))
    assert np.array_equal(lam2, lam_full) and np.array_equal(phi2, phi_full)
    # pairs of another problem (too few rows, a flat array) are not used either
    for bad in ((lam0, phi0[:100]), (lam0, lam0)):
        lam3, phi3 = eigenpairs(W, A, 60, known=bad)
        assert np.array_equal(lam3, lam_full) and np.array_equal(phi3, phi_full)


def _reference(W, A, k):
    return scipy.linalg.eigh(W.toarray(), A.toarray(), eigvals_only=True)[:k]


def _mesh_problem():
    V, F = generic_sphere(3, seed=7)  # 642 vertices, k = 20: the ARPACK path
    return laplacian(Mesh(V, F)).reduced()


def test_arpack_no_convergence_falls_back_to_a_random_start(monkeypatch):
    W, A = _mesh_problem()
    real, calls = sla.eigsh, []

    def flaky(*args, **kw):
        calls.append(kw.get("ncv"))
        if len(calls) == 1:
            raise sla.ArpackNoConvergence("forced", np.zeros(0), np.zeros((W.shape[0], 0)))
        return real(*args, **kw)

    monkeypatch.setattr(eigen.sla, "eigsh", flaky)
    lam, _ = eigenpairs(W, A, 20)
    assert calls[1] == 41  # the second attempt: 2k + 1 basis
    assert np.allclose(lam, np.maximum(_reference(W, A, 20), 0), rtol=1e-9, atol=1e-9)


def test_arpack_failing_twice_falls_back_to_lobpcg(monkeypatch):
    W, A = _mesh_problem()

    def broken(*args, **kw):
        raise sla.ArpackNoConvergence("forced", np.zeros(0), np.zeros((W.shape[0], 0)))

    monkeypatch.setattr(eigen.sla, "eigsh", broken)
    used = []
    real = sla.lobpcg
    monkeypatch.setattr(eigen.sla, "lobpcg", lambda *a, **kw: used.append(1) or real(*a, **kw))
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # no dense fallback: LOBPCG's result
        lam, phi = eigenpairs(W, A, 20)
    assert used
    assert np.allclose(lam, np.maximum(_reference(W, A, 20), 0), rtol=1e-8, atol=1e-8)
    assert np.allclose(phi.T @ (A @ phi), np.eye(20), atol=1e-7)


def test_singular_factorisation_retries_with_another_shift(monkeypatch):
    W, A = _mesh_problem()
    real, shifts = sla.splu, []

    def singular_once(M, **kw):
        shifts.append(M.diagonal().min())
        if len(shifts) == 1:
            raise RuntimeError("Factor is exactly singular")
        return real(M, **kw)

    monkeypatch.setattr(eigen.sla, "splu", singular_once)
    lam, _ = eigenpairs(W, A, 20)
    assert len(shifts) == 2
    assert np.allclose(lam, np.maximum(_reference(W, A, 20), 0), rtol=1e-9, atol=1e-9)


def test_nan_results_fall_back_and_total_failure_is_a_clear_error(monkeypatch):
    W, A = _mesh_problem()

    def nan_eigsh(op, k, **kw):
        return np.full(k, np.nan), np.full((op.shape[0], k), np.nan)

    monkeypatch.setattr(eigen.sla, "eigsh", nan_eigsh)
    monkeypatch.setattr(eigen.sla, "lobpcg", nan_eigsh)
    # small problem: the dense solve, with a warning that says why
    with pytest.warns(RuntimeWarning, match="non-finite result"):
        lam, _ = eigenpairs(W, A, 20)
    assert np.allclose(lam, np.maximum(_reference(W, A, 20), 0), rtol=1e-9, atol=1e-9)
    # above the dense limit: an error, never a wrong basis
    monkeypatch.setattr(eigen, "DENSE_FALLBACK", 100)
    with pytest.raises(EigensolverError, match="eigensolve failed.*non-finite"):
        eigenpairs(W, A, 20)


def test_non_finite_operator_is_refused_with_the_mesh_name():
    W, A = _mesh_problem()
    W = W.tolil()
    W[3, 3] = np.inf
    with pytest.raises(EigensolverError, match="non-finite"):
        eigenpairs(W.tocsr(), A, 20)


def test_eigensolver_error_names_the_mesh(monkeypatch):
    V, F = generic_sphere(3, seed=7)
    monkeypatch.setattr(eigen, "DENSE_FALLBACK", 100)
    monkeypatch.setattr(eigen.sla, "splu", lambda M, **kw: (_ for _ in ()).throw(
        RuntimeError("Factor is exactly singular")))
    with pytest.raises(EigensolverError, match=r"^bunny\.off: the eigensolve failed"):
        HeatKernel(Mesh(V, F, name="bunny.off"), k=20, method="spectral")


def test_eigenpair_check_is_scale_aware():
    # the check is the solver's backward error: a correct solve passes on any mesh size and
    # for the constant mode (once refused on every 60k mesh), a perturbed one does not
    V, F = generic_sphere(4, seed=11)
    M = Mesh(V, F)
    hk = HeatKernel(M, k=40, method="spectral")
    lam, phi = hk.eigenvalues.numpy(), hk.eigenvectors.numpy()
    W, A = laplacian(M).reduced()
    _check_eigenpairs(W, A, lam, phi, M)  # accepted
    # eigenvalues off by one part in 1e6 (a differently normalised area): refused
    with pytest.raises(ValueError, match="backward error"):
        _check_eigenpairs(W, A, lam * (1 + 1e-6), phi, M)
    # the same mesh scaled 1000x and re-normalised gives the same operator: accepted
    W2, A2 = laplacian(Mesh(V * 1000.0, F)).reduced()
    _check_eigenpairs(W2, A2, lam, phi, M)
