"""Memory bounds of the blocked computations (big meshes): every block stays within its
budget, and the blocked results are the unblocked ones, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import generic_sphere

from torchheat import HeatKernel, Mesh
from torchheat import heat as th
from torchheat import matching as tm
from torchheat.matching import prepare


@pytest.fixture(scope="module")
def pair():
    V, F = generic_sphere(3)  # 642 vertices
    rng = np.random.default_rng(4)
    W = V * (1.0 + 0.01 * rng.standard_normal((len(V), 1)))  # near-isometric, same order
    S, T = prepare(Mesh(V, F)), prepare(Mesh(W, F))
    T.hk = T.hk.with_times(S.hk.times)
    return S, T


def test_rows_within_budget():
    assert tm.nn._rows_within(8 * 1000, 500, 256 * 2**20) == 500  # everything fits: one block
    assert tm.nn._rows_within(8 * 1000, 500, 8 * 1000 * 7 + 5) == 7
    assert tm.nn._rows_within(8 * 1000, 500, 10) == 1  # below one row: one row at a time
    assert tm.nn._rows_within(0, 3, 10) == 3


def test_landmark_scores_in_candidate_batches(pair, monkeypatch):
    S, T = pair
    cands = torch.arange(0, T.n, 70)  # 10 candidates
    ref = tm.landmark_scores(S, T, int(S.features[0]), cands)
    sizes: list[int] = []
    orig = T.hk.columns

    def spy(sources, **kw):
        sizes.append(len(sources))
        return orig(sources, **kw)

    monkeypatch.setattr(T.hk, "columns", spy)
    col = T.n * T.hk.times.numel() * 8  # bytes per candidate's columns
    budget = 4 * col + col // 2  # four candidates per batch
    got = tm.landmark_scores(S, T, int(S.features[0]), cands, memory_bytes=budget)
    assert sizes == [4, 4, 2]
    assert max(sizes) * col <= budget
    # the same scores up to rounding (the GEMM's summation order may depend on the batch
    # width), and the same ranking
    torch.testing.assert_close(got, ref, rtol=1e-13, atol=0)
    assert torch.equal(torch.argsort(got, stable=True), torch.argsort(ref, stable=True))


def test_landmark_scores_reuse_candidate_trees(pair, monkeypatch):
    """The k-d trees of a match's candidates are built once and reused for the next source
    landmark (same scores as without the cache); a cache past its budget keeps none."""
    S, T = pair
    cands = torch.arange(0, T.n, 70)  # 10 candidates
    ps = [int(p) for p in S.features[:2]]
    refs = [tm.landmark_scores(S, T, p, cands) for p in ps]
    built: list[int] = []
    orig = tm.nn._kdtree

    def spy(Y, *args):
        built.append(len(Y))
        return orig(Y, *args)

    monkeypatch.setattr(tm.nn, "_kdtree", spy)
    trees = tm.nn._TreeCache()
    got = [tm.landmark_scores(S, T, p, cands, trees=trees) for p in ps]
    assert len(built) == 10  # one tree per candidate, for both source landmarks
    assert trees.used == 10 * 8 * T.n * (2 * T.hk.times.numel() + 2) <= trees.budget
    # twice the first candidate, and a candidate not seen yet
    more = tm.landmark_scores(S, T, ps[0], torch.cat([cands[:1], cands[:1], cands[:1] + 1]),
                              trees=trees)
    assert len(built) == 11 and float(more[0]) == float(more[1]) == float(got[0][0])
    for g, r in zip(got, refs, strict=True):
        # the same bits: a nearest distance does not depend on the tree (its leaf size)
        assert torch.equal(g, r)
    none = tm.nn._TreeCache(budget_bytes=0)
    again = tm.landmark_scores(S, T, ps[1], cands, trees=none)
    assert none.trees == {} and none.used == 0 and len(built) == 21
    torch.testing.assert_close(again, refs[1], rtol=1e-13, atol=0)


def test_pruned_search_cluster_blocks_within_budget(pair, monkeypatch):
    S, T = pair
    samples = tm.prepared._fps(S, 48)
    Fs = tm.refine._Refiner(S, T, samples).source(torch.float64)
    Ft = tm.refine._refine_factors(T, samples, torch.float64)  # the identity's sample images
    centres = tm.prepared._fps(T, 16)  # ~40 targets per cluster
    ref_d, ref_i = tm.nn._nn_factors(Fs, None, Ft)
    big_d, big_i = tm.nn._nn_factors_pruned(Fs, None, Ft, centres)
    assert torch.equal(big_i, ref_i)
    biggest: list[int] = []
    orig = torch.addmm

    def spy(*args, **kw):
        out = orig(*args, **kw)
        biggest.append(out.numel() * out.element_size())
        return out

    monkeypatch.setattr(torch, "addmm", spy)
    for budget in (2**12, 2**9, 1):
        biggest.clear()
        d, i = tm.nn._nn_factors_pruned(Fs, None, Ft, centres, memory_bytes=budget)
        # the same map; distances to rounding (a GEMM's sums may depend on its block)
        assert torch.equal(i, big_i)
        torch.testing.assert_close(d, big_d, rtol=1e-9, atol=1e-12 * float(d.max()))
        if budget >= 2**12:  # one row fits: every block within the budget
            assert 0 < max(biggest) <= budget
        else:  # below one row: one query row at a time
            assert max(biggest) <= 8 * max(16, T.n)
    # unsplit, the largest cluster's block would not have fitted 2**12 bytes: the queries
    # of a centre block (10 rows) against its largest cluster
    G = Ft.C @ Ft.C.T
    yy = ((Ft.P @ G) * Ft.P).sum(dim=1)
    _, lab = tm.nn._blocked_argmin(Ft.P, Ft.P[centres] @ G, yy, yy[centres], 2**30)
    rows = 2**12 // (3 * 16 * 8)
    assert rows * int(torch.bincount(lab).max()) * 8 > 2**12
    monkeypatch.undo()
    # a budget that fits every block gives the default's result bit for bit
    assert torch.equal(tm.nn._nn_factors_pruned(Fs, None, Ft, centres, memory_bytes=2**30)[0],
                       big_d)


def test_ambiguity_edge_blocks_give_the_same_landmark(pair):
    S, _ = pair
    diam = S.mesh.bbox_diagonal()
    for p in S.features[:4].tolist():
        ref = tm.landmarks._ambiguity(S, p, True, None, 0.05 * diam)
        for budget in (3 * 20 * 8 * 100, 1):  # 100 edges per block, one edge per block
            got = tm.landmarks._ambiguity(S, p, True, None, 0.05 * diam, memory_bytes=budget)
            assert got == ref


def test_chebyshev_blocks_within_budget(monkeypatch):
    V, F = generic_sphere(2)  # 162 vertices
    hk = HeatKernel(Mesh(V, F), times=[1e-3, 1e-2], method="chebyshev", block=64)
    src = list(range(0, 162, 7))  # 24 sources
    ref = hk.columns(src)
    degree = int(hk.plan["degree"].max())
    per_source = 162 * (th.chebyshev._staged_steps(degree) + 2 * 2 + 1) * 8
    assert th.chebyshev._chebyshev_block(162, 2, degree, 8, 64) == 64  # 1 GiB: the default
    blocks: list[int] = []
    orig = hk._chebyshev

    def spy(red, tj, degrees):
        blocks.append(red.size)
        return orig(red, tj, degrees)

    monkeypatch.setattr(hk, "_chebyshev", spy)
    monkeypatch.setattr(th.chebyshev, "CHEBYSHEV_BYTES", 5 * per_source + 1)
    got = hk.columns(src)
    assert blocks == [5, 5, 5, 5, 4]
    # columns do not depend on their block (to the last bits: the sparse product's summation
    # order may follow the block's width on some CPUs — 1.4e-14 on values ~90, Intel Xeon)
    torch.testing.assert_close(got, ref, rtol=1e-12, atol=1e-12)
