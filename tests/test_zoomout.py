"""Spectral refinement (ZoomOut) and map quality, against brute force, known permutations and
maps that are known to be wrong."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from conftest import DATA, SHARED, generic_sphere
from test_matching import moved_copy

from torchheat import Mesh, load_mesh, match, prepare, symmetry
from torchheat.cli import main
from torchheat.matching.prepared import _fps
from torchheat.matching.quality import map_quality
from torchheat.matching.zoomout import (
    dense_spectral_map,
    functional_map,
    lstsq,
    spectral_map,
    zoomout,
)

pytestmark = pytest.mark.filterwarnings("ignore:Sparse")


@pytest.fixture(scope="module")
def spot_pair():
    M = load_mesh(DATA / "spot.obj")
    V, F = M.numpy()
    W, G, perm = moved_copy(V, F, seed=3)
    return prepare(M), prepare(Mesh(W, G)), torch.as_tensor(perm)


def test_spectral_map_is_the_brute_force_nearest_neighbour():
    g = torch.Generator().manual_seed(0)
    phi_s, phi_t = torch.randn(300, 12, generator=g), torch.randn(400, 12, generator=g)
    C = torch.randn(10, 10, generator=g)
    d2, idx = spectral_map(phi_s, phi_t, C)
    D = torch.cdist(phi_s[:, :10], phi_t[:, :10] @ C.T)
    assert torch.equal(idx, D.argmin(1))
    assert torch.allclose(d2, D.min(1).values ** 2, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_lstsq_is_reproducible_and_the_least_squares_solution(dtype):
    # ZoomOut's functional maps: the same bits on every call (torch's default CPU driver
    # returned 27 distinct solutions in 50 calls on this system), the SVD solution's values
    g = torch.Generator().manual_seed(0)
    A = torch.randn(500, 100, dtype=torch.float64, generator=g).to(dtype)
    B = torch.randn(500, 100, dtype=torch.float64, generator=g).to(dtype)
    first = lstsq(A, B)
    assert all(torch.equal(lstsq(A.clone(), B.clone()), first) for _ in range(30))
    ref = torch.linalg.lstsq(A.double(), B.double(), driver="gelsd").solution
    assert float((first.double() - ref).abs().max()) < (1e-12 if dtype == torch.float64 else 1e-4)
    # normal equations hold: A^T (A X - B) = 0
    assert float((A.double().T @ (A.double() @ first.double() - B.double())).abs().max()) < (
        1e-10 if dtype == torch.float64 else 1e-2)


def test_lstsq_of_a_rank_deficient_system_is_the_minimum_norm_one():
    A = torch.zeros(6, 3, dtype=torch.float64)
    A[:, 0] = torch.arange(1.0, 7.0, dtype=torch.float64)
    A[:, 1] = 2 * A[:, 0]  # rank 1: QR without pivoting cannot solve it
    B = torch.arange(6.0, dtype=torch.float64)[:, None]
    X = lstsq(A, B)
    assert torch.allclose(X, torch.linalg.pinv(A) @ B, atol=1e-12)


def test_match_is_reproducible(spot_pair):
    # two runs of the whole pipeline on the same prepared pair: the same ZoomOut residuals
    # (bit for bit) and the same map
    S, T, _ = spot_pair
    a, b = match(S, T), match(S, T)
    assert torch.equal(a.map, b.map)
    assert [z[2] for z in a.info["zoomout_candidates"]] == [
        z[2] for z in b.info["zoomout_candidates"]]


def test_candidates_side_by_side_score_as_one_after_the_other(spot_pair, monkeypatch):
    # with two torch threads the ZoomOut candidates run side by side, one thread each (and
    # ahead of time while the self-symmetry runs in the background): every candidate's
    # residual and images, and the maps, are the bits of a one-thread match
    import threading

    from torchheat.heat import threads
    from torchheat.matching import select

    S, T, perm = spot_pair
    pools: list[tuple[int, int]] = []
    ran_in: set[str] = set()
    orig_run, orig_zo = select.run_each, select.zoomout

    def run_spy(jobs, n):
        pools.append((len(jobs), n))
        return orig_run(jobs, n)

    def zo_spy(*args, **kw):
        ran_in.add(threading.current_thread().name.split("_")[0])
        return orig_zo(*args, **kw)

    monkeypatch.setattr(select, "run_each", run_spy)
    monkeypatch.setattr(select, "zoomout", zo_spy)
    out = {}
    for n in (1, 2):
        with threads(n):
            Sn, Tn = prepare(Mesh(*S.mesh.numpy())), prepare(Mesh(*T.mesh.numpy()))
            out[n] = match(Sn, Tn)
            assert torch.get_num_threads() == n
    assert any(n == 2 and k >= 2 for k, n in pools)  # side by side on two threads
    assert "torchheat-job" in ran_in
    one, two = out[1], out[2]
    assert torch.equal(one.map, two.map) and torch.equal(one.map, perm)
    za, zb = one.info["zoomout_candidates"], two.info["zoomout_candidates"]
    assert len(za) == len(zb) > 1
    for a, b in zip(za, zb, strict=True):
        assert torch.equal(a[1], b[1]) and a[2] == b[2]  # images, residual: the same bits


def test_hypotheses_side_by_side_refine_as_one_after_the_other(spot_pair, monkeypatch):
    # with two torch threads (no background self-symmetry to share them with) the
    # hypotheses' rounds run side by side, one thread each: every hypothesis's energy and
    # orientation, and the maps, are the bits of a one-thread match
    from torchheat.heat import threads
    from torchheat.matching import hypotheses

    S, T, perm = spot_pair
    pools: list[tuple[int, int]] = []
    orig_run = hypotheses.run_each

    def run_spy(jobs, n):
        pools.append((len(jobs), n))
        return orig_run(jobs, n)

    monkeypatch.setattr(hypotheses, "run_each", run_spy)
    out = {}
    for n in (1, 2):
        with threads(n):
            Sn, Tn = prepare(Mesh(*S.mesh.numpy())), prepare(Mesh(*T.mesh.numpy()))
            out[n] = match(Sn, Tn, background=False)
    assert any(n == 2 and k >= 2 for k, n in pools)  # side by side on two threads
    one, two = out[1], out[2]
    assert torch.equal(one.map, two.map) and torch.equal(one.map, perm)
    ha, hb = one.info["hypotheses"], two.info["hypotheses"]
    assert len(ha) == len(hb) > 2
    for a, b in zip(ha, hb, strict=True):
        assert a[0] == b[0] and a[1] == b[1]  # landmarks, energy: the same bits
        assert a[2] == b[2] or (math.isnan(a[2]) and math.isnan(b[2]))  # orientation


def test_zoomout_recovers_a_permutation_from_a_noisy_seed(spot_pair):
    S, T, perm = spot_pair
    seeds = _fps(S, 48)
    images = perm[seeds].clone()
    images[::5] = perm[seeds[torch.randperm(48, generator=torch.Generator().manual_seed(1))[
        :10]]]  # a fifth of the seed images wrong
    assert (images != perm[seeds]).sum() >= 8
    r = zoomout(S.hk.eigenvectors, T.hk.eigenvectors, seeds, images, _fps(S, 500),
                k_start=12, k_end=100, step=8)
    assert (r.images == perm[r.rows]).float().mean() >= 0.99
    # the functional map of a permutation of an isometric copy is orthogonal
    k = r.C.shape[0]
    assert torch.linalg.norm(r.C.T @ r.C - torch.eye(k, dtype=r.C.dtype)) / math.sqrt(k) < 0.05
    dense = dense_spectral_map(S, T, r.C)  # exact pruned search = brute force
    brute = spectral_map(S.hk.eigenvectors.double(), T.hk.eigenvectors.double(), r.C)[1]
    assert torch.equal(dense, brute)
    assert (dense == perm).float().mean() >= 0.99


def test_functional_map_of_the_identity_is_the_identity(spot_pair):
    S, _, _ = spot_pair
    rows = _fps(S, 300)
    C = functional_map(S.hk.eigenvectors, S.hk.eigenvectors, rows, rows, 40)
    assert torch.allclose(C, torch.eye(40, dtype=C.dtype), atol=1e-8)


def test_quality_separates_right_from_wrong_maps(spot_pair):
    S, T, perm = spot_pair
    good = match(S, T)
    assert (good.map == perm).float().mean() >= 0.99
    assert not good.suspect and good.quality.quality > 0.6 and good.quality.defect < 0.1
    # a map forced from a wrong landmark pair: p sent far from its image
    p = int(good.landmarks[0][0])
    VT = T.mesh.numpy()[0]
    q = int(np.argmax(np.linalg.norm(VT - VT[int(perm[p])], axis=1)))
    wrong = match(S, T, method="paper", landmark=(p, q))
    assert (wrong.map == perm).float().mean() < 0.2
    assert wrong.suspect and wrong.quality.defect > 0.35
    # two shapes that are not near-isometric: far from an isometry, well below the right map
    # (it read 0.22 with 4 ZoomOut hypotheses and no mirror partners, 0.28 with the default
    # 8 + partners: just above the 0.25 `suspect` threshold, which was set on 8 TOSCA pairs)
    bad = match(S, prepare(Mesh(*generic_sphere(4, seed=2)))).quality
    assert bad.defect > 0.3 and bad.quality < 0.5 * good.quality.quality
    # the mirror of a right map reverses the orientation: suspect as a direct map
    assert map_quality(S, T, good.map, orientation=-0.8).suspect


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "tosca_remeshed_5k").exists(), reason="shared data absent")
def test_zoomout_refines_a_real_pair():
    # TOSCA cat0 -> cat1 (independently remeshed): the spectral refinement is finer than the
    # heat-kernel map it starts from (measured 0.043 -> 0.025 mean error / sqrt(area))
    from torchheat.batch import evaluate_pair
    from torchheat.datasets import tosca_remeshed_5k

    pair = tosca_remeshed_5k(root=SHARED, classes=["cat"]).pair("cat0", "cat1") \
        if hasattr(tosca_remeshed_5k, "pair") else next(
            p for p in tosca_remeshed_5k(root=SHARED, classes=["cat"]) if p.name == "cat0-cat1")
    fine = evaluate_pair(pair, {}, eval_points=300)["direct"]
    coarse = evaluate_pair(pair, {"zoomout": False}, eval_points=300)["direct"]
    assert fine["under_0.25"] >= 0.99 and fine["mean"] <= 0.035
    assert fine["mean"] < 0.8 * coarse["mean"]
    assert fine["under_0.05"] > coarse["under_0.05"]


def test_cli_report_and_no_zoomout(spot_pair, tmp_path):
    from test_cli import write_off

    S, T, perm = spot_pair
    a = write_off(tmp_path / "a.off", *S.mesh.numpy())
    b = write_off(tmp_path / "b.off", *T.mesh.numpy())
    rep = tmp_path / "r.json"
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m.txt"), "--report",
                 str(rep), "--threads", "1"]) == 0
    r = json.loads(rep.read_text())
    assert r["source"] == str(a) and r["n_source"] == S.n and r["n_target"] == T.n
    assert r["method"] == "refine" and r["zoomout"] is True and r["suspect"] is False
    assert 0.6 < r["quality"] <= 1 and r["orientation"] > 0.5
    assert all(perm[p] == q for p, q in r["landmarks"][:5])
    assert "landmark_search" in r["timings"] and "match total" in r["timings"]
    assert "descriptor_seed" in r["timings"] and "zoomout_reorient" in r["timings"]
    assert "margin" in r and r["ambiguous"] is False
    assert r["search"] in ("first stage", "full (first stage not clear)")
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m2.txt"), "--no-zoomout",
                 "--report", str(rep), "--threads", "1"]) == 0
    assert json.loads(rep.read_text())["zoomout"] is False
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m3.txt"),
                 "--no-descriptor-seed", "--report", str(rep), "--threads", "1"]) == 0
    assert "descriptor_seed" not in json.loads(rep.read_text())["timings"]
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m4.txt"),
                 "--no-reoriented", "--report", str(rep), "--threads", "1"]) == 0
    assert "zoomout_reorient" not in json.loads(rep.read_text())["timings"]
    m4 = np.loadtxt(tmp_path / "m4.txt", dtype=np.int64)
    assert (m4 == perm.numpy()).mean() >= 0.99
    m3 = np.loadtxt(tmp_path / "m3.txt", dtype=np.int64)
    assert (m3 == perm.numpy()).mean() >= 0.99
    m2 = np.loadtxt(tmp_path / "m2.txt", dtype=np.int64)
    assert (m2 == perm.numpy()).mean() >= 0.99
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m5.txt"), "--no-staged",
                 "--report", str(rep), "--threads", "1"]) == 0
    r5 = json.loads(rep.read_text())
    assert r5["search"] == "full" and "zoomout_polish" in r5["timings"]
    assert "zoomout_turn" in r5["timings"]  # the half-turn partners were considered
    m5 = np.loadtxt(tmp_path / "m5.txt", dtype=np.int64)
    assert (m5 == perm.numpy()).mean() >= 0.99
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m6.txt"), "--no-staged",
                 "--no-polished", "--report", str(rep), "--threads", "1"]) == 0
    r6 = json.loads(rep.read_text())
    assert "zoomout_polish" not in r6["timings"] and "zoomout_turn" in r6["timings"]
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m6.txt"), "--no-staged",
                 "--no-half-turns", "--report", str(rep), "--threads", "1"]) == 0
    r6 = json.loads(rep.read_text())
    assert "zoomout_polish" in r6["timings"] and "zoomout_turn" not in r6["timings"]
    assert r6["options"]["half_turns"] is False
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m7.txt"), "--no-tie-break",
                 "--report", str(rep), "--threads", "1"]) == 0
    assert (np.loadtxt(tmp_path / "m7.txt", dtype=np.int64) == perm.numpy()).mean() >= 0.99


def test_symmetry_quality_expects_a_reversing_map():
    from test_matching import mirror_mesh, mirror_permutation

    V, F = mirror_mesh(3)
    corr = symmetry(Mesh(V, F))
    assert (corr.map.numpy() == mirror_permutation(V)).mean() >= 0.95
    assert corr.orientation < -0.5 and not corr.suspect


def _default_options(**kw):
    import inspect

    from torchheat.matching.options import _Options

    defaults = {k: p.default for k, p in inspect.signature(match).parameters.items()
                if p.default is not inspect.Parameter.empty}
    fields = {f: defaults[f] for f in _Options.__dataclass_fields__ if f in defaults}
    fields.update(kw)
    return _Options(**fields)


@pytest.mark.parametrize(("mirror", "descriptor"), [(True, False), (False, False),
                                                   (False, True)])
def test_a_mirror_hypothesis_alone_yields_its_direct_partner(mirror, descriptor):
    """Seeded only with the (orientation-reversing) mirror map, the spectral choice reaches
    the direct map through the target's self-symmetry, or through the landmark-free
    descriptor candidate; without either it cannot (so the test can fail)."""
    from test_matching import mirror_mesh, mirror_permutation

    from torchheat.matching.pipeline import _symmetries_at
    from torchheat.matching.refine import Hypothesis
    from torchheat.matching.select import _spectral_choice

    V, F = mirror_mesh(3)
    mp = mirror_permutation(V)
    W, G, perm = moved_copy(V, F, seed=5)
    S, T = prepare(Mesh(V, F)), prepare(Mesh(W, G))
    T.hk = T.hk.with_times(S.hk.times)
    samples = _fps(S, 48)
    swap = torch.as_tensor(perm[mp])  # source x -> copy of its mirror image
    pool = [Hypothesis(lms0=[], g=swap[samples], energy=1.0, orientation=-1.0)]
    opt = _default_options(mirror_hypothesis=mirror, descriptor_seed=descriptor)
    direct, _, diag = _spectral_choice(
        S, T, samples, pool, opt, {},
        lambda shape, v: _symmetries_at(shape, v, opt.use_hks, opt.engine, opt.n_candidates,
                                        opt.refine_log_floor))
    truth = torch.as_tensor(perm)[direct.zo.rows]
    right = float((direct.zo.images == truth).float().mean())
    if descriptor:
        assert right > 0.95 and direct.zo_orientation > 0.5
        assert direct.descriptor_seed is True
    elif mirror:
        assert right > 0.95 and direct.zo_orientation > 0.5
        assert len(diag) >= 2  # the mirror map and its partner(s)
    else:
        assert right < 0.5 and direct.zo_orientation < 0  # the mirror map stays


def test_tear_reads_a_swap_of_two_parts_and_not_a_rigid_motion(spot_pair):
    from torchheat.matching.select import _TEAR_RADIUS, _Tear

    S, T, perm = spot_pair
    rows = _fps(S, 500)
    tear = _Tear(S, T, rows)
    direct = perm[rows]
    assert tear(direct) == 0.0  # the copy is rigidly moved: neighbours stay neighbours
    # swap the images of two far-apart groups of rows (a part mapped onto another part)
    V, _ = S.mesh.numpy()
    P = V[rows.numpy()]
    a = np.argsort(P[:, 0])[:40]  # one end of the cow
    b = np.argsort(-P[:, 0])[:40]  # the other end
    swapped = direct.clone()
    swapped[a], swapped[b] = direct[b], direct[a]
    t = tear(swapped)
    # the torn pairs: every neighbour pair with one row in a swapped group and one outside
    Q = T.mesh.numpy()[0][swapped.numpy()]
    nb = tear.b.reshape(len(P), -1)
    far = np.linalg.norm(Q[:, None] - Q[nb], axis=2) > _TEAR_RADIUS * math.sqrt(T.mesh.area())
    assert t == pytest.approx(far.mean())
    assert 0.02 < t < 0.5


def test_margin_is_the_gap_to_the_best_different_map(spot_pair):
    from torchheat.matching.quality import AMBIGUOUS_BELOW
    from torchheat.matching.refine import Hypothesis
    from torchheat.matching.select import _rival
    from torchheat.matching.zoomout import ZoomOutResult

    S, T, perm = spot_pair
    rows = _fps(S, 500)
    right = perm[rows]
    shifted = right.roll(1)  # every sample sent to another sample's image: a different map
    near = right.clone()
    near[:10] = shifted[:10]  # the same map but for 10 samples: not a rival

    def cand(images, s):
        return Hypothesis(zo=ZoomOutResult(rows, images, torch.eye(3), 1.0), zo_score=s)

    chosen = cand(right, -4.0)
    cands = [chosen, cand(near, -3.99), cand(shifted, -3.7), cand(shifted, -3.2)]
    gap, rival = _rival(chosen, cands, lambda r: r.zo_score, T)
    assert gap == pytest.approx(0.3) and rival is cands[2]  # the best of the two rivals
    assert _rival(chosen, cands[:2], lambda r: r.zo_score, T) == (None, None)  # no rival
    q = map_quality(S, T, perm, margin=0.1)
    assert q.ambiguous == (0.1 < AMBIGUOUS_BELOW) and not q.suspect
    assert not map_quality(S, T, perm).ambiguous  # no margin: never ambiguous


def test_row_basis_solves_every_prefix_as_lstsq_and_maps_as_brute_force():
    # one QR for all the sizes of a ZoomOut: each prefix's least squares and point map must be
    # those of an independent solve (lstsq of that prefix, scipy) and of plain spectral_map
    import scipy.linalg

    from torchheat.matching.zoomout import _RowBasis

    rng = np.random.default_rng(7)
    phi = torch.from_numpy(np.linalg.qr(rng.standard_normal((400, 40)))[0])
    phi_t = torch.from_numpy(np.linalg.qr(rng.standard_normal((300, 40)))[0])
    rows = torch.from_numpy(rng.choice(400, 120, replace=False))
    rb = _RowBasis(phi, rows, 40)
    assert rb.full_rank
    for k in (5, 17, 40):
        B = torch.from_numpy(rng.standard_normal((120, k)))
        ref = scipy.linalg.lstsq(phi[rows, :k].numpy(), B.numpy())[0]
        C = rb.functional_map(B)
        assert np.allclose(C.numpy(), ref, atol=1e-10)
        d2, j = rb.spectral_map(phi_t, C)
        d2_ref, j_ref = spectral_map(phi, phi_t, C, rows)
        assert torch.equal(j, j_ref) and torch.allclose(d2, d2_ref, atol=1e-10)
    # a basis of rank < k on the rows (a repeated column) falls back to lstsq: the
    # minimum-norm solution, still a least-squares minimiser
    flat = phi.clone()
    flat[:, 3] = flat[:, 2]
    rb = _RowBasis(flat, rows, 10)
    assert not rb.full_rank
    B = torch.from_numpy(rng.standard_normal((120, 10)))
    C = rb.functional_map(B)
    X = flat[rows, :10].numpy()
    ref = scipy.linalg.lstsq(X, B.numpy())[0]
    assert np.allclose(X @ C.numpy(), X @ ref, atol=1e-8)


# --- fine maps (match(fine_k=...), zoomout.fine_map) -------------------------------------------
def test_argmin_certified_is_the_float64_nearest_neighbour_on_near_ties():
    from torchheat.matching.nn import _argmin_certified

    g = torch.Generator().manual_seed(0)
    X = torch.randn(700, 200, dtype=torch.float64, generator=g)
    Y = torch.randn(900, 200, dtype=torch.float64, generator=g)
    # near ties float32 cannot resolve: targets 1e-9 apart, and queries equidistant up to 1e-10
    Y[450:] = Y[:450] + 1e-9 * torch.randn(450, 200, dtype=torch.float64, generator=g)
    X[:300] = Y[:300] + 1e-3 * torch.randn(300, 200, dtype=torch.float64, generator=g)
    mid = 0.5 * (Y[300:350] + Y[750:800])
    X[300:350] = mid + 1e-10 * torch.randn(50, 200, dtype=torch.float64, generator=g)
    # exact squared distances (differences first: no cancellation), in row chunks
    d = torch.cat([((x[:, None, :] - Y[None]) ** 2).sum(-1) for x in X.split(50)])
    best = d.min(1).values
    got = _argmin_certified(X, Y, memory_bytes=200 * 900 * 4)  # several row blocks
    # a float64-accurate nearest neighbour for every row (an exact tie may pick either)
    assert float((d.gather(1, got[:, None]).squeeze(1) - best).max()) <= 1e-12
    # ... where a plain float32 search is not
    X32, Y32 = X.float(), Y.float()
    plain = torch.cdist(X32, Y32, compute_mode="use_mm_for_euclid_dist").argmin(1)
    assert float((d.gather(1, plain[:, None]).squeeze(1) - best).max()) > 1e-9


@pytest.mark.parametrize("certified", [True, False])
def test_dense_map_is_the_float64_brute_force_by_either_search(spot_pair, monkeypatch,
                                                               certified):
    """Both searches of dense_spectral_map (certified float32 product for small pairs,
    cluster-pruned above CERTIFIED_MAX_PAIRS) give the float64 nearest neighbour, here of a
    functional map far from the identity (a random rotation of the modes after the first)."""
    import torchheat.matching.zoomout as zo

    S, T, _ = spot_pair
    k = 30
    g = torch.Generator().manual_seed(1)
    R = torch.linalg.qr(torch.randn(k - 1, k - 1, dtype=torch.float64, generator=g))[0]
    C = torch.eye(k, dtype=torch.float64)
    C[1:, 1:] = 0.7 * torch.eye(k - 1, dtype=torch.float64) + 0.3 * R
    monkeypatch.setattr(zo, "CERTIFIED_MAX_PAIRS", S.n * T.n if certified else 0)
    got = dense_spectral_map(S, T, C)
    X = S.hk.eigenvectors[:, :k].double()
    Y = T.hk.eigenvectors[:, :k].double() @ C.T
    d = torch.cat([((x[:, None, :] - Y[None]) ** 2).sum(-1) for x in X.split(256)])
    assert float((d.gather(1, got[:, None]).squeeze(1) - d.min(1).values).max()) <= 1e-13
    # the two searches agree index for index (no exact ties here)
    monkeypatch.setattr(zo, "CERTIFIED_MAX_PAIRS", 0 if certified else S.n * T.n)
    assert torch.equal(dense_spectral_map(S, T, C), got)


def test_fine_map_dense_search_is_the_same_by_either_search(spot_pair, monkeypatch):
    """fine_map's dense search takes dense_spectral_map's switch: large meshes the pruned
    search, small ones the certified product; the map is the same either way."""
    import torchheat.matching.zoomout as zo

    S, T, perm = spot_pair
    a = S.hk.vertex_mass
    C0 = S.hk.eigenvectors.T @ (a[:, None] * T.hk.eigenvectors[perm])
    C0 = C0 + 0.05 * torch.randn(C0.shape, dtype=C0.dtype,
                                 generator=torch.Generator().manual_seed(3))
    got = {}
    for limit in (0, S.n * T.n):
        monkeypatch.setattr(zo, "CERTIFIED_MAX_PAIRS", limit)
        got[limit] = zo.fine_map(S, T, C0, 120)
    (i0, c0), (i1, c1) = got.values()
    assert torch.equal(i0, i1) and torch.equal(c0, c1)
    assert float((i0 == perm).double().mean()) > 0.99


def test_argmin_certified_blocks_do_not_change_the_result(monkeypatch):
    """The certified search's cache-sized blocks (nn.CACHE_BYTES) split the rows only."""
    import torchheat.matching.nn as nn

    g = torch.Generator().manual_seed(2)
    X = torch.randn(500, 20, dtype=torch.float64, generator=g)
    Y = torch.randn(300, 20, dtype=torch.float64, generator=g)
    whole = nn._argmin_certified(X, Y)
    monkeypatch.setattr(nn, "CACHE_BYTES", 7 * 300 * 4)  # blocks of 7 rows
    assert torch.equal(nn._argmin_certified(X, Y), whole)
    assert torch.equal(whole, torch.cdist(X, Y).argmin(1))


def test_eigenpairs_beyond_the_held_basis_follow_the_sphere_spectrum():
    import trimesh

    from torchheat.heat import HeatKernel

    s = trimesh.creation.icosphere(4)
    hk = HeatKernel(Mesh(s.vertices, s.faces), k=10)
    lam, phi = hk.eigenpairs(25)
    assert phi.shape == (hk.n, 25) and hk.eigenvalues.numel() == 10  # the solver keeps its 10
    assert torch.allclose(lam[:10], hk.eigenvalues, rtol=1e-6, atol=1e-8)
    # unit-area sphere: lambda = 4 pi l (l + 1) with multiplicity 2l + 1 (l = 0 .. 4)
    exact = torch.tensor([4 * math.pi * ell * (ell + 1) for ell in range(5)
                          for _ in range(2 * ell + 1)], dtype=torch.float64)
    assert float((lam[1:] / exact[1:] - 1).abs().max()) < 0.02 and abs(float(lam[0])) < 1e-6
    a = hk.vertex_mass
    gram = phi.T @ (a[:, None] * phi)
    assert torch.allclose(gram, torch.eye(25, dtype=torch.float64), atol=1e-8)


def test_fine_map_keeps_a_permutation_and_runs_from_the_command_line(spot_pair, tmp_path,
                                                                     capsys):
    from test_cli import write_off

    S, T, perm = spot_pair
    c = match(S, T, fine_k=140)
    assert (c.map == perm).float().mean() >= 0.99  # computed on first access
    assert c.info["fine_k"] == 140 and "fine_map" in c.info["timings"]
    assert S.caches.basis.shape == (S.n, 140)  # solved once, kept on the shape
    # the command line: --fine [K], refused where it does not apply
    a = write_off(tmp_path / "a.off", *S.mesh.numpy())
    b = write_off(tmp_path / "b.off", *T.mesh.numpy())
    rep = tmp_path / "r.json"
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m.txt"), "--fine", "120",
                 "--report", str(rep), "--threads", "1"]) == 0
    r = json.loads(rep.read_text())
    assert r["fine_k"] == 120 and "fine_map" in r["timings"]
    assert (np.loadtxt(tmp_path / "m.txt", dtype=np.int64) == perm.numpy()).mean() >= 0.99
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m2.txt"), "--fine",
                 "--no-zoomout"]) == 1
    assert not (tmp_path / "m2.txt").exists() and "--fine" in capsys.readouterr().err
    with pytest.raises(ValueError, match="fine_k"):
        match(S, T, fine_k=150, method="paper")
    # a basis of more than a quarter of the vertices is refused (a typo's 10**6 ran a dense
    # eigensolve and a ZoomOut of hours), in Python and before the command line's workers
    top = min(S.n, T.n) // 4
    with pytest.raises(ValueError, match=f"more than a quarter .* at most {top}"):
        match(S, T, fine_k=top + 1)
    assert main(["match", str(a), str(b), "-o", str(tmp_path / "m3.txt"), "--fine",
                 str(10**6)]) == 1
    err = capsys.readouterr().err
    assert "--fine 1000000: 1000000 eigenmodes" in err and f"at most {top}" in err
    assert not (tmp_path / "m3.txt").exists()


def test_offered_basis_is_kept_only_if_it_extends_the_heat_kernels():
    from torchheat.eigen import cotan_eigenpairs
    from torchheat.matching.prepared import _basis, offer_basis

    V, F = generic_sphere(3, seed=4)
    shape = prepare(Mesh(V, F), k=20)
    lam, phi = cotan_eigenpairs(V, F, k=35)
    assert not offer_basis(shape, lam[:20], phi[:, :20])  # no larger than the held one
    assert not offer_basis(shape, lam * 1.01, phi)  # another operator's (e.g. another scale)
    assert not offer_basis(shape, lam, phi[:-1])  # other vertices
    assert shape.caches.basis is None
    assert offer_basis(shape, lam, phi)
    assert torch.equal(_basis(shape, 30), torch.from_numpy(phi[:, :30]))
    assert torch.equal(_basis(shape, 12), shape.hk.eigenvectors[:, :12])  # the heat kernel's


@pytest.mark.slow
@pytest.mark.skipif(not (SHARED / "tosca_remeshed_5k").exists(), reason="shared data absent")
def test_fine_map_is_finer_on_a_real_pair():
    # TOSCA cat0 -> cat10 (independently remeshed): 100 -> 200 modes, measured 0.0167 ->
    # 0.0135 mean error / sqrt(area); the choice of the map is the same
    from torchheat.batch import evaluate_pair
    from torchheat.datasets import tosca_remeshed_5k

    pair = next(p for p in tosca_remeshed_5k(root=SHARED, classes=["cat"])
                if p.name == "cat0-cat10")
    base = evaluate_pair(pair, {}, eval_points=300)
    fine = evaluate_pair(pair, {"fine_k": 200}, eval_points=300)
    assert base["landmarks"] == fine["landmarks"]
    assert fine["direct"]["under_0.25"] >= 0.99
    assert fine["direct"]["mean"] < 0.9 * base["direct"]["mean"]


def test_prefetch_choice_fills_the_memo_while_busy_and_stops(spot_pair):
    # while the self-symmetry runs, the choice's first ZoomOuts go into the memo (the
    # descriptor candidate first), one at a time, each the bits the choice would compute;
    # it stops at the first check after the background work is done
    from torchheat.heat import threads
    from torchheat.matching.refine import Hypothesis
    from torchheat.matching.select import _ZO_TARGETS, _descriptor_zoomout, _prefetch_choice

    S, T, perm = spot_pair
    samples = _fps(S, 48)
    g_true = perm[samples]  # (the descriptor candidate's own seed on this exact copy)
    pool = [Hypothesis(lms0=[], g=torch.roll(g_true, r), energy=float(r), orientation=1.0)
            for r in (7, 13)]
    opt = _default_options()
    rows, targets = _fps(S, opt.zoomout_samples), _fps(T, _ZO_TARGETS)
    pos = torch.full((S.n,), -1, dtype=torch.int64)
    pos[rows] = torch.arange(rows.numel())

    def zo_keys(memo):
        return [k for k in memo if k[0] == "zoomout"]

    for busy_checks, n_zoomouts in ((2, 1), (3, 2), (10, 3)):
        calls = []
        memo: dict = {}
        with threads(2):
            _prefetch_choice(S, T, samples, pool, opt, memo,
                            lambda calls=calls, n=busy_checks: calls.append(1) or len(calls) <= n)
        assert len(zo_keys(memo)) == n_zoomouts  # descriptor, then the candidates in turn
        assert ("descriptor map", 30) in memo
    # everything it computed is what the choice computes on one thread, bit for bit
    with threads(1):
        ref = _descriptor_zoomout(S, T, rows, pos[samples], 100, targets, {})
    mine = memo[zo_keys(memo)[0]]
    assert torch.equal(mine.images, ref.images) and mine.residual == ref.residual
    assert torch.equal(mine.C, ref.C)
    none: dict = {}
    _prefetch_choice(S, T, samples, pool, opt, none, lambda: False)  # not busy: nothing
    assert none == {}
