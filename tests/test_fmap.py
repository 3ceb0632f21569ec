"""The descriptor functional map (torchheat.matching.fmap): its energy is minimised exactly,
its operators are right on shapes whose answers are known, and its orientation term tells a
shape's direct map from its reflection."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh
from conftest import DATA, flat_grid, generic_sphere
from scipy.optimize import fmin_l_bfgs_b
from test_matching import mirror_mesh, mirror_permutation, moved_copy

import torchheat
from torchheat.matching import fmap
from torchheat.matching.zoomout import spectral_map


def test_the_quadratic_solve_is_the_energy_minimum():
    V, F = generic_sphere(3)
    W = V * np.array([1.2, 1.0, 0.85])
    s = torchheat.prepare(torchheat.Mesh(V, F), k=40)
    t = torchheat.prepare(torchheat.Mesh(W, F), k=40)
    terms = fmap._terms(s, t, 12, 20, (1.0, 0.1, 1.0, 1.0))
    C = fmap._solve_quadratic(*terms)
    e0 = fmap._energy(C, *terms)
    rng = np.random.default_rng(0)
    for _ in range(20):  # every direction goes up (quadratic: by the curvature, > 0)
        D = rng.standard_normal(C.shape) * 1e-3
        assert fmap._energy(C + D, *terms) > e0
    # an independent optimiser (L-BFGS, finite-difference gradients) ends no lower
    x, fv, _ = fmin_l_bfgs_b(lambda v: fmap._energy(v.reshape(C.shape), *terms),
                             np.zeros(C.size), approx_grad=True, maxfun=200000)
    assert e0 <= fv + 1e-12
    assert fv < 1.05 * e0  # and it converged towards the same minimum


def test_orientation_operator_of_coordinates_on_a_plane():
    # f = x on a flat grid: n x grad f = y-axis, so <n x grad x, grad g> = dg/dy;
    # g = y gives 1 everywhere: O[1, y] = area, O[1, x] = 0
    V, F = flat_grid(10, 8, 1.0, 0.75)
    x, y = V[:, :1], V[:, 1:2]
    one = np.ones_like(x)
    op = fmap.orientation_operators(V, F, np.hstack([one, x, y]), x)[0]
    assert op[0, 2] == pytest.approx(0.75, rel=1e-9)
    assert op[0, 1] == pytest.approx(0.0, abs=1e-12)
    O_y = fmap.orientation_operators(V, F, np.hstack([one, x, y]), y)[0]
    assert O_y[0, 1] == pytest.approx(-0.75, rel=1e-9)  # n x grad y = -x-axis


def test_orientation_operators_match_a_face_by_face_reference():
    # O_q[i, j] = sum_f area_f mean_f(phi_i) <n_f x grad f_q, grad phi_j>, written out face by
    # face with numpy's cross product and a 3x3 solve for each gradient, on a curved mesh of
    # several face chunks (the operator works in chunks of _FACE_CHUNK faces)
    V, F = generic_sphere(2)
    assert len(F) > 2 * fmap._FACE_CHUNK
    rng = np.random.default_rng(3)
    phi, descr = rng.standard_normal((len(V), 5)), rng.standard_normal((len(V), 3))
    ref = np.zeros((3, 5, 5))
    for tri in F:
        P = V[tri]
        e1, e2 = P[1] - P[0], P[2] - P[0]
        nrm = np.cross(e1, e2)
        area = np.linalg.norm(nrm) / 2
        nrm = nrm / np.linalg.norm(nrm)

        def grad(vals, e1=e1, e2=e2, nrm=nrm):
            # the gradient in the face's plane: e . g = difference along each edge, n . g = 0
            return np.linalg.solve(np.stack([e1, e2, nrm]),
                                   np.stack([vals[1] - vals[0], vals[2] - vals[0],
                                             np.zeros_like(vals[0])]))

        gphi, gd = grad(phi[tri]), grad(descr[tri])  # (3, k), (3, p)
        rot = np.cross(nrm[None, :], gd.T)  # (p, 3)
        ref += area * phi[tri].mean(0)[None, :, None] * (rot @ gphi)[:, None, :]
    out = fmap.orientation_operators(V, F, phi, descr)
    assert np.abs(out - ref).max() < 1e-10 * np.abs(ref).max()


def test_orientation_operators_bits_do_not_depend_on_the_gradient_block(monkeypatch):
    # the face gradients are built in blocks of _GRADIENT_BLOCK faces and used in chunks of
    # _FACE_CHUNK: blocks of whole chunks, with a last partial block, give the same bits as
    # blocks of one chunk (the products are accumulated chunk by chunk, at the same faces)
    assert fmap._GRADIENT_BLOCK % fmap._FACE_CHUNK == 0
    V, F = generic_sphere(2)
    assert len(F) % (2 * fmap._FACE_CHUNK) != 0
    rng = np.random.default_rng(5)
    phi, descr = rng.standard_normal((len(V), 6)), rng.standard_normal((len(V), 4))
    monkeypatch.setattr(fmap, "_GRADIENT_BLOCK", fmap._FACE_CHUNK)
    ref = fmap.orientation_operators(V, F, phi, descr)
    for block in (fmap._FACE_CHUNK * 2, fmap._FACE_CHUNK * 3, 10**6):
        monkeypatch.setattr(fmap, "_GRADIENT_BLOCK", block)
        out = fmap.orientation_operators(V, F, phi, descr)
        assert np.array_equal(out, ref), block


def test_wks_is_invariant_to_renumbering_and_rigid_motion():
    V, F = generic_sphere(3)
    perm = np.random.default_rng(1).permutation(len(V))
    inv = np.argsort(perm)
    R = trimesh.transformations.rotation_matrix(0.7, [1, 2, 3])[:3, :3]
    a = torchheat.prepare(torchheat.Mesh(V, F), k=30)
    b = torchheat.prepare(torchheat.Mesh(V[perm] @ R.T * 2.0, inv[F]), k=30)
    e = np.linspace(1.0, 4.0, 8)
    wa = fmap.wave_kernel_signature(a.hk.eigenvalues, a.hk.eigenvectors, e, 0.3).numpy()
    wb = fmap.wave_kernel_signature(b.hk.eigenvalues, b.hk.eigenvectors, e, 0.3).numpy()
    np.testing.assert_allclose(wb, wa[perm], rtol=1e-6, atol=1e-9 * np.abs(wa).max())


def test_orientation_term_picks_the_direct_map_of_a_mirror_symmetric_shape():
    V, F = mirror_mesh(4)
    refl = mirror_permutation(V)
    perm = np.random.default_rng(2).permutation(len(V))
    inv = np.argsort(perm)
    src = torchheat.prepare(torchheat.Mesh(V, F), k=60)
    tgt = torchheat.prepare(torchheat.Mesh(V[perm], inv[F]), k=60)  # same shape, renumbered
    C = fmap.descriptor_functional_map(src, tgt, k=20, weights=(1.0, 0.1, 1.0, 1.0))
    _, img = spectral_map(src.hk.eigenvectors, tgt.hk.eigenvectors, C)
    truth, mirror = inv, inv[refl]  # source vertex i is target vertex inv[i]
    Vt = V[perm]
    d_true = np.linalg.norm(Vt[img.numpy()] - Vt[truth], axis=1)
    d_mirror = np.linalg.norm(Vt[img.numpy()] - Vt[mirror], axis=1)
    diag = np.linalg.norm(V.max(0) - V.min(0))
    # descriptors cannot tell the two apart; the orientation term does
    assert np.median(d_true) < 0.05 * diag
    assert np.mean(d_true < d_mirror) > 0.8
    # reversing: the same descriptors, the reflection (the shape's intrinsic symmetry)
    C = fmap.descriptor_functional_map(src, tgt, k=20, reversing=True)
    img = spectral_map(src.hk.eigenvectors, tgt.hk.eigenvectors, C)[1].numpy()
    d_true = np.linalg.norm(Vt[img] - Vt[truth], axis=1)
    d_mirror = np.linalg.norm(Vt[img] - Vt[mirror], axis=1)
    assert np.median(d_mirror) < 0.05 * diag
    assert np.mean(d_mirror < d_true) > 0.8


@pytest.fixture(scope="module")
def cow_pair():
    M = torchheat.load_mesh(DATA / "spot.obj")
    W, G, perm = moved_copy(*M.numpy(), seed=3)  # source vertex i is target vertex perm[i]
    return torchheat.prepare(M), torchheat.prepare(torchheat.Mesh(W, G)), perm


def test_descriptor_seed_is_a_candidate_and_can_be_switched_off(cow_pair):
    src, tgt, perm = cow_pair
    W, _ = tgt.mesh.numpy()
    diag = tgt.mesh.bbox_diagonal()
    for seed in (True, False):
        corr = torchheat.match(src, tgt, descriptor_seed=seed)
        assert ("descriptor_seed" in corr.info["timings"]) == seed
        err = np.linalg.norm(W[corr.map.numpy()] - W[perm], axis=1)
        assert np.mean(err < 0.05 * diag) > 0.9


def test_descriptor_candidate_steps_aside_for_a_direct_variant(cow_pair):
    """The descriptor candidate is dropped when a direct landmark candidate is nearly the same
    map (a limb apart), and kept when the agreeing candidate reads orientation-reversing."""
    from types import SimpleNamespace

    from torchheat.matching.prepared import _fps
    from torchheat.matching.refine import Hypothesis
    from torchheat.matching.select import _descriptor_candidate

    src, tgt, perm = cow_pair
    rows = _fps(src, 500)
    at_samples = torch.arange(48)
    targets = _fps(tgt, 2000)
    first = _descriptor_candidate(src, tgt, rows, at_samples, [], 60, targets, lambda im: 0.9)
    assert len(first) == 1
    images = first[0].zo.images.clone()
    # the same map with its last 30 % of samples sent to one far target vertex
    W, _ = tgt.mesh.numpy()
    far = int(np.argmax(np.linalg.norm(W - W[images[0].item()], axis=1)))
    variant = images.clone()
    variant[int(0.7 * len(variant)):] = far
    for orientation, kept in ((0.8, 0), (-0.8, 1)):
        cand = Hypothesis(zo=SimpleNamespace(images=variant), zo_orientation=orientation)
        out = _descriptor_candidate(src, tgt, rows, at_samples, [cand], 60, targets,
                                    lambda im: 0.9)
        assert len(out) == kept


def test_operators_built_once_per_shape(monkeypatch):
    """A match builds each shape's descriptor operators once: the target's self-symmetry (a
    view of it at its own times) shares the cache."""
    M = torchheat.load_mesh(DATA / "spot.obj")
    W, G, perm = moved_copy(*M.numpy(), seed=3)
    calls = []
    orig = fmap.orientation_operators
    monkeypatch.setattr(fmap, "orientation_operators",
                        lambda *a, **k: calls.append(1) or orig(*a, **k))
    s, t = torchheat.prepare(M), torchheat.prepare(torchheat.Mesh(W, G))
    corr = torchheat.match(s, t, background=False)
    assert len(calls) == 2
    assert np.mean(corr.map.numpy() == perm) > 0.95


def test_rectangular_commutativity_hessian_is_the_quadratic_form():
    # sum_q |C P_q - Q_q C|^2 for an a x b map C (Q_q: a x a, P_q: b x b), evaluated
    # directly, against vec(C)^T H vec(C) with the Kronecker-built H
    rng = np.random.default_rng(3)
    a, b, p = 4, 7, 3
    Q, P = rng.standard_normal((p, a, a)), rng.standard_normal((p, b, b))
    H = fmap._comm_hessian(Q, P)
    assert H.shape == (a * b, a * b)
    np.testing.assert_allclose(H, H.T, atol=1e-12)
    for _ in range(5):
        C = rng.standard_normal((a, b))
        direct = sum(float(((C @ P[q] - Q[q] @ C) ** 2).sum()) for q in range(p))
        assert C.ravel() @ H @ C.ravel() == pytest.approx(direct, rel=1e-10)


def test_weighted_rectangular_solve_is_the_energy_minimum():
    # the descriptor term weighed in space (gram = Phi^T W Phi, A = Phi^T W d): the solve
    # minimises sum_x w(x) |Phi[x] C B - d(x)|^2 + the other terms, checked against that
    # energy written out in space
    rng = np.random.default_rng(4)
    n, a, b, p, q = 40, 3, 5, 6, 2
    Phi, w, d = rng.standard_normal((n, a)), rng.uniform(0, 1, n), rng.standard_normal((n, p))
    B = rng.standard_normal((b, p))
    mask = rng.uniform(0, 1, (a, b))
    dc = (rng.standard_normal((q, a, a)), rng.standard_normal((q, b, b)))
    orient = (rng.standard_normal((q, a, a)), rng.standard_normal((q, b, b)))
    coef = [1.0, 0.3, 0.2, 0.1]
    gram, A = (Phi.T * w) @ Phi, (Phi.T * w) @ d
    C = fmap._solve_quadratic(coef, A, B, mask, dc, orient, gram)
    assert C.shape == (a, b)

    def energy(X):
        e = coef[0] * float((w[:, None] * (Phi @ X @ B - d) ** 2).sum())
        e += coef[1] * float((mask * X * X).sum())
        for c_, (Qs, Ps) in ((coef[2], dc), (coef[3], orient)):
            e += c_ * sum(float(((X @ Ps[i] - Qs[i] @ X) ** 2).sum()) for i in range(q))
        return e

    e0 = energy(C)
    for _ in range(20):
        assert energy(C + rng.standard_normal(C.shape) * 1e-3) > e0


def test_landmark_map_turns_a_thin_reflection_into_the_direct_map():
    from torchheat.matching.prepared import _fps
    from torchheat.matching.zoomout import zoomout

    # thin in y: the reflection moves every point by less than the shape's thickness, as a
    # body's front/back reflection does
    V, F = mirror_mesh(4, scale=(1.0, 0.12, 0.6))
    mp = mirror_permutation(V)
    W, G, perm = moved_copy(V, F, seed=3)
    S = torchheat.prepare(torchheat.Mesh(V, F), k=60)
    T = torchheat.prepare(torchheat.Mesh(W, G), k=60)
    phi_s, phi_t = S.hk.eigenvectors, T.hk.eigenvectors
    rows = _fps(S, 400)
    p = rows[:20]
    for pairs in (perm, perm[mp]):  # the direct map's point pairs, then the reflection's
        C = fmap.landmark_functional_map(S, T, p, torch.from_numpy(pairs[p.numpy()]), k=20)
        j = spectral_map(phi_s, phi_t, C, rows)[1]
        zo = zoomout(phi_s, phi_t, rows, j, rows, k_start=20, k_end=60, step=8)
        f = spectral_map(phi_s, phi_t, zo.C)[1].numpy()
        assert (f == perm).mean() > 0.99  # the direct map (a known permutation) both times
    # control: ZoomOut from the reflection's pairs alone keeps the reflection
    zo = zoomout(phi_s, phi_t, p, torch.from_numpy(perm[mp][p.numpy()]), rows, k_start=16,
                 k_end=60, step=8)
    assert (spectral_map(phi_s, phi_t, zo.C)[1].numpy() == perm[mp]).mean() > 0.99


def test_memoised_hessians_give_the_same_maps_and_are_keyed_by_direction():
    V, F = generic_sphere(3)
    s = torchheat.prepare(torchheat.Mesh(V, F), k=40)
    t = torchheat.prepare(torchheat.Mesh(V * np.array([1.2, 1.0, 0.85]), F), k=40)
    memo: dict = {}
    direct = fmap.descriptor_functional_map(s, t, k=12, memo=memo)
    assert torch.allclose(direct, fmap.descriptor_functional_map(s, t, k=12), atol=1e-12)
    assert list(memo) == [(12, 50, False)]
    rev = fmap.descriptor_functional_map(s, t, k=12, reversing=True, memo=memo)
    assert torch.allclose(rev, fmap.descriptor_functional_map(s, t, k=12, reversing=True),
                          atol=1e-12)
    assert set(memo) == {(12, 50, False), (12, 50, True)}
    assert not torch.allclose(rev, direct, atol=1e-3)  # the two directions differ
    p = torch.tensor([0, 50, 100, 150, 200, 250, 300, 350])
    lm = fmap.landmark_functional_map(s, t, p, p, k=12, memo=memo)  # reuses (12, 50, False)
    assert torch.allclose(lm, fmap.landmark_functional_map(s, t, p, p, k=12), atol=1e-12)
    assert len(memo) == 2


def test_landmark_map_refuses_bad_point_pairs():
    V, F = generic_sphere(2)
    s = torchheat.prepare(torchheat.Mesh(V, F), k=30)
    p = torch.tensor([0, 5, 9])
    with pytest.raises(ValueError, match="3 source and 2 target"):
        fmap.landmark_functional_map(s, s, p, p[:2], k=10)
    with pytest.raises(ValueError, match="0 source"):
        fmap.landmark_functional_map(s, s, p[:0], p[:0], k=10)
    with pytest.raises(ValueError, match=f"target point index out of range: 0..{s.n}"):
        fmap.landmark_functional_map(s, s, p, torch.tensor([0, 1, s.n]), k=10)
    with pytest.raises(ValueError, match="source point index out of range: -1"):
        fmap.landmark_functional_map(s, s, torch.tensor([-1, 1, 2]), p, k=10)
