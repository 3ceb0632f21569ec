"""Partial shapes: a piece matched into its whole (known vertex correspondences after a rigid
motion and a permutation), the pieces of the method against independent references, the
SHREC'16 loader and its barycentric evaluation, and bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import DATA, SHARED, flat_grid, generic_sphere
from test_matching import moved_copy

from torchheat import Mesh, load_mesh, match, prepare
from torchheat.cli import main
from torchheat.matching import partial
from torchheat.matching.partial import (
    area_ratio,
    boundary_distance,
    partial_descriptor_images,
    partial_descriptor_map,
    partial_functional_map,
    partial_zoomout,
)
from torchheat.meshio import MeshError

pytestmark = pytest.mark.filterwarnings("ignore:Sparse")


def cut(mesh: Mesh, axis: int, fraction: float, name: str = "piece") -> Mesh:
    """The faces of ``mesh`` entirely below the ``fraction`` quantile of coordinate ``axis``
    (largest component; ``vertex_map`` = indices in ``mesh``)."""
    V, F = mesh.numpy()
    c = np.quantile(V[:, axis], fraction)
    return Mesh(V, F[(V[F, axis] <= c).all(axis=1)], name=name, largest_component=True)


@pytest.fixture(scope="module")
def spot_piece():
    """Two thirds of the cow Spot (cut across its length) and the whole, moved and permuted."""
    M = load_mesh(DATA / "spot.obj")
    V, F = M.numpy()
    W, G, perm = moved_copy(V, F, seed=5)
    piece = cut(M, 2, 0.66, name="spot-front")
    truth = perm[piece.vertex_map.numpy()]  # piece vertex -> vertex of the moved whole
    return piece, Mesh(W, G, name="spot-moved"), truth


def test_boundary_distance_of_a_flat_grid_is_the_distance_to_the_rectangle_edge():
    V, F = flat_grid(21, 16, 1.0, 0.75)  # grid spacing 0.05 in both directions
    d = boundary_distance(Mesh(V, F))
    x, y = V[:, 0], V[:, 1]
    exact = np.minimum.reduce([x, 1.0 - x, y, 0.75 - y])
    np.testing.assert_allclose(d, exact, atol=1e-9)  # axis-aligned edge paths are exact here
    assert np.isinf(boundary_distance(load_mesh(DATA / "spot.obj"))).all()  # closed


def test_area_ratio_and_swapped_shapes(spot_piece):
    piece, whole, _ = spot_piece
    r = area_ratio(piece, whole)
    assert r == pytest.approx(piece.area() / whole.area())
    assert 0.4 < r < 0.9
    with pytest.raises(MeshError, match="source must be the piece"):
        area_ratio(Mesh(whole.vertices * 2.0, whole.faces, name="big"), piece)


def test_piece_descriptors_at_scaled_times_equal_the_whole_scale_ones():
    """t k_t is scale-invariant: the unit-area piece at t / r equals the piece at the whole's
    scale at t — checked against a dense expm of the operator at the whole's scale."""
    import scipy.linalg as sla

    from torchheat import laplacian
    from torchheat.heat import HeatKernel

    whole = Mesh(*generic_sphere(3), name="sphere")
    piece = cut(whole, 0, 0.6)
    r = area_ratio(piece, whole)
    t = np.array([0.002, 0.01])
    hk = HeatKernel(piece, times=t / r, k=piece.n_vertices - 1, method="spectral")
    p = 17
    got = hk.columns([p]).numpy()  # [1, n, J] unit-area kernel k'(p, x) at t / r
    lap = laplacian(piece, normalize=False)
    W = lap.stiffness_scipy.toarray()
    a = np.asarray(lap.mass_scipy.diagonal()) / whole.area()  # mass at the whole's scale
    for j, tj in enumerate(t):
        K = sla.expm(-tj * W / a[:, None]) / a[None, :]  # exp(-tL) A^-1, L = A^-1 W
        want = tj * K[:, p]
        np.testing.assert_allclose((t[j] / r) * got[0, :, j], want, rtol=2e-3,
                                   atol=1e-6 * want.max())


def test_partial_zoomout_on_a_piece_recovers_the_vertex_correspondence(spot_piece):
    piece, whole, truth = spot_piece
    ps, pt = prepare(piece, k=60), prepare(whole, k=60)
    r = area_ratio(piece, whole)
    rows = torch.arange(piece.n_vertices)
    seed = torch.as_tensor(np.random.default_rng(0).choice(piece.n_vertices, 60, replace=False))
    res = partial_zoomout(ps.hk.eigenvectors, pt.hk.eigenvectors, seed,
                          torch.as_tensor(truth)[seed], rows, r, k_start=12, k_end=60, step=8)
    assert res.C.shape == (math.ceil(r * 60), 60)
    W, _ = whole.numpy()
    err = np.linalg.norm(W[res.images.numpy()] - W[truth], axis=1) / whole.bbox_diagonal()
    inner = boundary_distance(piece, math.sqrt(whole.area())) > 0.1
    # measured: 89.5 % of the vertices away from the cut within ~1.5 edge lengths (3 % of the
    # diagonal), median 1.2 %, mean 1.7 %; the error concentrates along the cut
    assert np.mean(err[inner] < 0.03) > 0.85
    assert np.median(err) < 0.015 and err.mean() < 0.025
    # the rectangular least squares is the plain one on random data
    g = torch.Generator().manual_seed(1)
    A, B = torch.randn(50, 6, generator=g, dtype=torch.float64), torch.randn(
        70, 9, generator=g, dtype=torch.float64)
    idx = torch.randint(0, 70, (50,), generator=g)
    C = partial_functional_map(A, B, torch.arange(50), idx, 4, 9)
    np.testing.assert_allclose(C.numpy(), np.linalg.lstsq(A[:, :4].numpy(), B[idx].numpy(),
                                                           rcond=None)[0], atol=1e-10)


def test_dense_partial_map_of_some_rows_is_the_brute_force_and_the_full_maps_rows(spot_piece):
    # the pruned search against a float64 brute force over every vertex of the whole, on all
    # rows and on a subset (the arbiter of partial_scale="auto" reads farthest points only)
    piece, whole, _ = spot_piece
    ps, pt = prepare(piece), prepare(whole)
    C = partial_descriptor_map(ps, pt, area_ratio(piece, whole))
    k_s, k_t = C.shape
    X = ps.hk.eigenvectors[:, :k_s].double() @ C.double()
    Y = pt.hk.eigenvectors[:, :k_t].double()
    brute = torch.cdist(X, Y).argmin(dim=1)
    full = partial.dense_partial_map(ps, pt, C)
    rows = torch.as_tensor(np.random.default_rng(3).choice(ps.n, 300, replace=False))
    some = partial.dense_partial_map(ps, pt, C, rows=rows)
    assert full.shape == (ps.n,) and some.shape == (300,)
    assert torch.equal(some, full[rows])
    assert (full == brute).float().mean() > 0.999  # (exact ties aside)


def test_partial_descriptor_map_places_a_piece_without_landmarks(spot_piece):
    # the landmark-free rectangular functional map (WKS at the whole's scale, orientation
    # term): measured 63 % of the vertices beyond 0.05 sqrt(area) from the cut within 10 %
    # of the diagonal, median 6 % (without the orientation term 56 %, 8 %); a random map
    # puts ~2 % there
    piece, whole, truth = spot_piece
    ps, pt = prepare(piece), prepare(whole)
    r = area_ratio(piece, whole)
    C = partial_descriptor_map(ps, pt, r)
    assert tuple(C.shape) == (math.ceil(r * 24), 24)  # ceil(r k) modes of the piece
    d = boundary_distance(piece, math.sqrt(whole.area()))
    rows = torch.as_tensor(np.flatnonzero(d > 0.05))
    W, _ = whole.numpy()
    err = np.linalg.norm(W[partial_descriptor_images(ps, pt, C, rows).numpy()]
                         - W[truth[rows.numpy()]], axis=1) / whole.bbox_diagonal()
    assert np.mean(err < 0.1) > 0.5 and np.median(err) < 0.08
    # a ratio that puts the piece's first eigenvalue beyond the whole's last: refused, named
    lam_s, lam_t = ps.hk.eigenvalues.double(), pt.hk.eigenvalues.double()
    tiny = float(lam_s[1] / lam_t[-1]) / 2  # lambda_1 / tiny = 2 lambda_max(whole)
    assert partial.shared_band(ps, pt, r) is not None and partial.shared_band(ps, pt, tiny) is None
    with pytest.raises(ValueError, match="spot-front: .*share no band"):
        partial_descriptor_map(ps, pt, tiny)


def test_interior_view_samples_the_interior_and_leaves_the_source_alone(spot_piece):
    # the piece way draws landmarks and samples from a view of the source whose sample order
    # is the interior's; the source's own samples (shared with its other copies) are untouched
    from torchheat.matching.prepared import _fps

    piece, whole, _ = spot_piece
    ps, pt = prepare(piece), prepare(whole)
    before = _fps(ps, 300).clone()
    setup = partial._setup(ps, pt, partial.PARTIAL_MARGIN)
    view = partial._interior_view(ps, setup)
    assert setup.interior[_fps(view, 100).numpy()].all()
    assert not setup.interior[before.numpy()].all()  # the plain samples reach the cut
    assert torch.equal(_fps(ps, 300), before) and view.caches is not ps.caches
    assert setup.interior[view.features.numpy()].all()


def test_match_partial_maps_a_piece_into_its_moved_whole(spot_piece):
    piece, whole, truth = spot_piece
    corr = match(piece, whole, partial=True)
    W, _ = whole.numpy()
    err = np.linalg.norm(W[corr.map.numpy()] - W[truth], axis=1) / whole.bbox_diagonal()
    assert corr.map.shape == (piece.n_vertices,)
    assert np.mean(err < 0.05) > 0.9, np.mean(err < 0.05)
    q = corr.quality
    assert not q.suspect and q.orientation > 0.5
    # one scale: the ratio the piece's times are divided by is its true share of the area
    info = corr.info["partial"]
    assert info["ratio"] == pytest.approx(piece.area() / whole.area(), rel=1e-9)
    assert set(info["quality"]) >= {"piece", "filled"}
    assert info["closed_margin"] < 0.75  # the capped front is not matched clearly: both ways
    # the scale is chosen by agreement with the landmark-free map + 0.5 quality
    qual, agree = info["quality"], info["agreement"]
    assert set(agree) == set(qual) and all(0.0 <= a <= 1.0 for a in agree.values())
    won = max(qual, key=lambda s: agree[s] + 0.5 * qual[s])
    assert qual[won] == pytest.approx(q.quality)
    assert agree[won] > 0.3  # the right map agrees with the coarse landmark-free one


def test_final_map_false_leaves_the_maps_none_and_says_where_it_cannot(spot_piece):
    """``final_map=False``: no dense map, yet the result prints and reports (its vertex
    count known without the map); the filled way gives None too; the two stages that choose
    by the dense maps (a partial match's "auto", ``verify_stage``) refuse it."""
    import json

    piece, whole, _ = spot_piece
    S, T = prepare(load_mesh(DATA / "spot.obj")), prepare(whole)
    corr = match(S, T, final_map=False)
    assert corr.map is None and corr.quality is None and corr.landmarks
    assert "map=None" in repr(corr)
    rep = json.loads(json.dumps(corr.report()))
    assert rep["n_source"] == S.n == corr.n_source and rep["n_target"] == T.n
    filled = match(piece, T, partial=True, partial_scale="filled", final_map=False)
    assert filled.map is None and filled.n_source == piece.n_vertices
    assert filled.landmarks and all(a < piece.n_vertices for a, _ in filled.landmarks)
    with pytest.raises(ValueError, match="final_map=True"):
        match(piece, T, partial=True, final_map=False)
    with pytest.raises(ValueError, match="final_map=True"):
        match(S, T, verify_stage=True, final_map=False)
    assert match(S, T).n_source == S.n  # with a map: the same count


def test_partial_auto_skips_the_filled_piece_when_closed_it_is_too_small(spot_piece):
    # the front 45 % of the cow: closed, it covers 55 % of the whole (< 60 %), too little to
    # pass for the whole; only the piece way runs
    from torchheat.matching.partial_scale import _FILLED_LEAST, filled_piece

    _, whole, _ = spot_piece
    M = load_mesh(DATA / "spot.obj")
    small = cut(M, 2, 0.45, name="spot-front-small")
    closed = filled_piece(small).area() / whole.area()
    assert 0.5 < closed < _FILLED_LEAST
    corr = match(small, whole, partial=True)
    info = corr.info["partial"]
    assert info["scale"] == "piece" and "filled" not in info["quality"]
    assert info["closed_ratio"] == pytest.approx(closed, rel=1e-9)
    assert f"would cover {100 * closed:.1f} % of the whole" in info["chosen_by"]
    assert "not tried" in info["chosen_by"]
    V, F = M.numpy()
    W, G, perm = moved_copy(V, F, seed=5)  # the same motion as spot_piece's whole
    truth = perm[small.vertex_map.numpy()]
    err = np.linalg.norm(W[corr.map.numpy()] - W[truth], axis=1) / whole.bbox_diagonal()
    assert np.mean(err < 0.05) > 0.8, np.mean(err < 0.05)


@pytest.fixture(scope="module")
def spot_holed():
    """The cow Spot with eight holes punched in it (the two-rings of far-apart vertices,
    ~13 % of the area), and the whole, moved and permuted."""
    from torchheat.descriptors import farthest_point_sampling

    M = load_mesh(DATA / "spot.obj")
    V, F = M.numpy()
    W, G, perm = moved_copy(V, F, seed=7)
    seeds = farthest_point_sampling(V, 8).numpy()
    ring = np.unique(F[np.isin(F, seeds).any(axis=1)])
    holed = Mesh(V, F[~np.isin(F, ring).any(axis=1)], name="spot-holed",
                 largest_component=True)
    return holed, Mesh(W, G, name="spot-moved"), perm[holed.vertex_map.numpy()]


def test_filled_piece_closes_the_holes_and_maps_the_piece(spot_holed, monkeypatch):
    from torchheat.matching import select
    from torchheat.matching.partial_scale import filled_piece
    from torchheat.topology import boundary_loops

    twins = []  # the filled way runs without trimmed twins (measured to hurt closed pieces)
    real = select._trimmed_candidates
    monkeypatch.setattr(select, "_trimmed_candidates",
                        lambda *a, **k: twins.append(1) or real(*a, **k))

    holed, whole, truth = spot_holed
    filled = filled_piece(holed)
    V, F = filled.numpy()
    assert len(boundary_loops(holed.numpy()[1], holed.n_vertices)) == 8
    assert boundary_loops(F, len(V)) == [] and np.array_equal(V[:holed.n_vertices],
                                                               holed.numpy()[0])
    assert filled_piece(whole) is whole  # closed: nothing to fill
    corr = match(holed, whole, partial=True, partial_scale="filled")
    assert corr.map.shape == (holed.n_vertices,)  # the piece's own vertices only
    assert all(a < holed.n_vertices for a, _ in corr.landmarks)
    assert corr.info["partial"]["scale"] == "filled"
    assert twins == []
    assert corr.info["search"] == "full"  # the staged search is for whole shapes only
    assert corr.info["partial"]["filled_vertices"] == filled.n_vertices - holed.n_vertices
    W, _ = whole.numpy()
    err = np.linalg.norm(W[corr.map.numpy()] - W[truth], axis=1) / whole.bbox_diagonal()
    assert np.mean(err < 0.05) > 0.9, np.mean(err < 0.05)
    assert not corr.suspect
    # the symmetric alternative is the piece's too
    assert not corr.has_symmetric_map or corr.symmetric_map.shape == (holed.n_vertices,)
    with pytest.raises(ValueError, match="'filled'"):
        match(holed, whole, partial=True, partial_scale="holes")


def test_partial_auto_keeps_a_sure_filled_map_without_the_piece_way(spot_holed, monkeypatch):
    # closed, the holed cow is nearly the whole: its match chooses clearly (margin >= 0.75,
    # direct orientation) and its map of the piece reads a high quality, so the piece's own
    # scale is not tried; forced to run both ways, the arbiter keeps the same map
    from torchheat.matching import partial_scale

    holed, whole, truth = spot_holed
    corr = match(holed, whole, partial=True)
    info = corr.info["partial"]
    assert set(info["quality"]) == {"filled"} and info["scale"] == "filled"
    assert "piece's own scale not tried" in info["chosen_by"]
    assert info["closed_margin"] >= 0.75 and info["closed_orientation"] >= 0.6
    assert info["quality"]["filled"] >= partial_scale._FILLED_SURE
    assert corr.info["timings"]["other_scale"] == 0
    W, _ = whole.numpy()
    err = np.linalg.norm(W[corr.map.numpy()] - W[truth], axis=1) / whole.bbox_diagonal()
    assert np.mean(err < 0.02) > 0.9, np.mean(err < 0.02)

    monkeypatch.setattr(partial_scale, "_FILLED_SURE", 1.01)  # never sure: both ways
    both = match(holed, whole, partial=True)
    info = both.info["partial"]
    assert set(info["quality"]) == {"piece", "filled"} and info["scale"] == "filled"
    assert info["chosen_by"].startswith("agreement")
    assert torch.equal(both.map, corr.map)


def test_deep_share_of_a_flat_rectangle():
    # the share of a piece's area at least 0.1 sqrt(area(whole)) from its boundary: on a 1 x
    # 0.75 rectangle the inner rectangle (1 - 2d) x (0.75 - 2d), up to half a cell of lumped
    # mass along its edge
    from types import SimpleNamespace

    from torchheat.matching.partial_scale import _deep_share

    V, F = flat_grid(41, 31, 1.0, 0.75)  # spacing 0.025
    ps = prepare(Mesh(V, F), k=10)
    for whole_area, d in ((1.0, 0.1), (4.0, 0.2)):
        whole = SimpleNamespace(mesh=SimpleNamespace(area=lambda a=whole_area: a))
        exact = (1 - 2 * d) * (0.75 - 2 * d) / 0.75
        assert abs(_deep_share(ps, whole) - exact) < 0.05, (whole_area, exact)


def test_partial_auto_keeps_the_filled_map_of_a_piece_without_interior(spot_holed, monkeypatch):
    # where both ways run, a piece with little area far from its boundary keeps the filled
    # map: the arbiter's evidence is read at the piece's scale. Forced both ways here (never
    # sure), then the rule on and off
    from torchheat.matching import partial_scale

    holed, whole, _ = spot_holed
    monkeypatch.setattr(partial_scale, "_FILLED_SURE", 1.01)
    monkeypatch.setattr(partial_scale, "_DEEP_LEAST", 1.01)  # every piece lacks interior
    corr = match(holed, whole, partial=True)
    info = corr.info["partial"]
    assert set(info["quality"]) == {"piece", "filled"} and info["scale"] == "filled"
    assert "the filled map kept" in info["chosen_by"] and "agreement" not in info["chosen_by"]
    monkeypatch.setattr(partial_scale, "_DEEP_LEAST", 0.0)  # never: the arbiter chooses
    info = match(holed, whole, partial=True).info["partial"]
    assert info["chosen_by"].startswith("agreement")


def test_a_piece_whose_holes_cannot_be_closed(spot_holed, monkeypatch):
    # a patch with a zero-area face: "filled" names the piece and what to do instead; "auto"
    # keeps the piece way and says why the other was not used
    from torchheat.matching import partial_scale

    def bad_fill(V, F):
        a, b = int(F[0, 0]), int(F[0, 1])
        return np.vstack([V, V[a][None]]), np.vstack([F, [[a, b, len(V)]]])

    monkeypatch.setattr(partial_scale, "fill_holes", bad_fill)
    holed, whole, truth = spot_holed
    with pytest.raises(MeshError, match="spot-holed: closing its holes .*partial_scale='piece'"):
        match(holed, whole, partial=True, partial_scale="filled")
    corr = match(holed, whole, partial=True)
    info = corr.info["partial"]
    assert info["scale"] == "piece" and "filled" not in info["quality"]
    assert "the filled piece failed" in info["chosen_by"]


def test_partial_scale_unit_stays_one_option_away(spot_holed):
    # the second way before "filled": the holed piece at unit area, holes open
    holed, whole, truth = spot_holed
    corr = match(holed, whole, partial=True, partial_scale="unit")
    info = corr.info["partial"]
    assert info["scale"] == "unit" and info["ratio"] == pytest.approx(
        holed.area() / whole.area(), rel=1e-9)
    assert corr.info["search"] == "full"  # no staged search on a piece
    W, _ = whole.numpy()
    err = np.linalg.norm(W[corr.map.numpy()] - W[truth], axis=1) / whole.bbox_diagonal()
    assert corr.map.shape == (holed.n_vertices,) and np.mean(err < 0.05) > 0.5


def test_partial_refuses_a_piece_without_interior_and_swapped_shapes(spot_piece):
    piece, whole, _ = spot_piece
    V, F = whole.numpy()
    strip = Mesh(V, F, name="whole-as-piece")
    with pytest.raises(MeshError, match="too little interior") as info:
        match(piece, strip, partial=True, partial_margin=5.0)
    assert "units" not in str(info.value)  # a piece of a sensible size
    # the piece in millimetres against a whole in metres: too small to have an interior,
    # and the error names the likely cause
    Vp, Fp = piece.numpy()
    with pytest.raises(MeshError, match="too little interior.*other units than the whole"):
        match(Mesh(Vp * 1e-3, Fp, name="piece-mm"), whole, partial=True)
    with pytest.raises(MeshError, match="swap the shapes"):
        match(Mesh(V * 1.5, F, name="bigger"), piece, partial=True)
    for scale in ("auto", "piece", "filled"):  # one shape given twice: no piece and whole
        with pytest.raises(ValueError, match="needs two shapes"):
            match(piece, piece, partial=True, partial_scale=scale)


def test_partial_on_a_closed_shape_is_a_full_match(spot_piece):
    _, whole, _ = spot_piece
    M = load_mesh(DATA / "spot.obj")
    V, F = M.numpy()
    W, G, perm = moved_copy(V, F, seed=9)
    corr = match(M, Mesh(W, G), partial=True)
    Wm = W
    err = np.linalg.norm(Wm[corr.map.numpy()] - Wm[perm], axis=1) / M.bbox_diagonal()
    assert np.mean(err < 0.05) > 0.9


def test_sample_areas_are_the_voronoi_masses_of_the_samples():
    V, F = generic_sphere(3)
    s = prepare(Mesh(V * [1.0, 0.7, 0.5], F), k=20)
    mass = s.hk.vertex_mass.double().numpy()
    everyone = torch.randperm(s.n)
    assert torch.equal(partial.sample_areas(s, everyone), torch.from_numpy(mass)[everyone])
    rows = torch.tensor([0, 5, 17, 40, 99, 150])
    W = V * [1.0, 0.7, 0.5]
    nearest = np.argmin(((W[:, None, :] - W[rows.numpy()][None]) ** 2).sum(-1), axis=1)
    ref = np.array([mass[nearest == i].sum() for i in range(rows.numel())])
    assert np.allclose(partial.sample_areas(s, rows).numpy(), ref, rtol=1e-12)


def test_partial_quality_of_the_identity_on_uneven_vertex_masses():
    # a capsule's vertex masses span ~120x (rings crowd at the caps' poles): its rectangular
    # functional map fitted on unweighted rows read the identity 0.69 off orthogonal, and
    # `--partial` called it suspect; rows weighted by the area they stand for read it exact
    import trimesh

    from torchheat.matching.quality import map_quality

    c = trimesh.creation.capsule(height=2.0, radius=0.5, count=[24, 24])
    a, b = prepare(Mesh(c.vertices, c.faces)), prepare(Mesh(c.vertices, c.faces))
    assert float(a.hk.vertex_mass.max() / a.hk.vertex_mass.min()) > 50
    q = map_quality(a, b, torch.arange(a.n), ratio=1.0)
    assert q.defect < 1e-8 and not q.suspect
    # and a map that folds the capsule onto one half still reads far from orthogonal
    V = c.vertices
    folded = torch.as_tensor(np.where(V[:, 2] < 0, np.arange(len(V)),
                                      np.argmin(((V[:, None] * [1, 1, -1] - V[None]) ** 2)
                                                .sum(-1), axis=1)))
    assert map_quality(a, b, folded, ratio=1.0).defect > 0.3


def test_cli_partial(spot_piece, tmp_path, capsys):
    from test_cli import write_off

    piece, whole, truth = spot_piece
    a, b = tmp_path / "piece.off", tmp_path / "whole.off"
    write_off(a, *piece.numpy())
    write_off(b, *whole.numpy())
    out = tmp_path / "map.txt"
    assert main(["match", str(a), str(b), "-o", str(out), "--partial", "--report",
                 str(tmp_path / "r.json")]) == 0
    import json

    rep = json.loads((tmp_path / "r.json").read_text())
    assert rep["partial"]["scale"] in rep["partial"]["quality"]  # the way kept, and its reading
    assert rep["partial"]["ratio"] == pytest.approx(piece.area() / whole.area(), rel=1e-6)
    from torchheat.matching.partial_scale import filled_piece

    assert rep["partial"]["closed_ratio"] == pytest.approx(
        filled_piece(piece).area() / whole.area(), rel=1e-6)
    f = np.loadtxt(out, dtype=np.int64)
    W, _ = whole.numpy()
    err = np.linalg.norm(W[f] - W[truth], axis=1) / whole.bbox_diagonal()
    assert np.mean(err < 0.05) > 0.9
    assert main(["match", str(a), str(b), "-o", str(out), "--partial-margin", "0.1"]) == 1
    assert "--partial-margin needs --partial" in capsys.readouterr().err
    assert main(["match", str(a), str(b), "-o", str(out), "--partial-scale", "piece"]) == 1
    assert "--partial-scale needs --partial" in capsys.readouterr().err
    assert main(["match", str(a), str(b), "-o", str(out), "--partial", "--partial-scale",
                 "piece"]) == 0
    assert "piece" in capsys.readouterr().out
    assert main(["match", str(b), str(a), "-o", str(out), "--partial"]) == 1
    assert "swap the shapes" in capsys.readouterr().err


def test_cli_partial_solves_the_closed_piece_in_the_background(spot_holed, tmp_path,
                                                               monkeypatch):
    # the command line closes the piece's holes with numpy before torch and solves the closed
    # mesh in its eigensolve workers; the filled way takes those eigenpairs (only when they
    # belong to exactly its closed piece) and the map is the in-process one
    import sys

    from test_cli import write_off

    from torchheat.cli import _closed_source
    from torchheat.matching import partial_scale
    from torchheat.topology import fill_holes

    holed, whole, _ = spot_holed
    a, b = tmp_path / "holed.off", tmp_path / "whole.off"
    write_off(a, *holed.numpy())
    write_off(b, *whole.numpy())
    V2, F2 = _closed_source([holed.numpy(), whole.numpy()])
    want = fill_holes(*holed.numpy())
    assert np.array_equal(V2, want[0]) and np.array_equal(F2, want[1])
    assert _closed_source([whole.numpy(), whole.numpy()]) is None  # no holes
    small = cut(whole, 2, 0.3)  # closed, far less than the whole: the filled way is not tried
    assert _closed_source([small.numpy(), whole.numpy()]) is None

    taken = []
    offer = partial_scale.offer_filled
    monkeypatch.setattr(partial_scale, "offer_filled",
                        lambda *a, **k: taken.append(offer(*a, **k)) or taken[-1])
    # the same piece once more with a patch of its faces written reversed (as in SHREC'16's
    # david and michael): Mesh turns them back, and so must the arrays solved before torch
    V, F = holed.numpy()
    patch = V[F].mean(axis=1)[:, 0] < np.quantile(V[:, 0], 0.2)
    c = tmp_path / "holed_reversed.off"
    write_off(c, V, np.where(patch[:, None], F[:, ::-1], F))
    # and written inside out: Mesh turns every face outward, and so must those arrays
    d = tmp_path / "holed_inside_out.off"
    write_off(d, V, F[:, ::-1])
    maps = []
    for piece, workers in ((a, "0"), (a, "2"), (c, "2"), (d, "2")):
        out = tmp_path / f"map_{piece.stem}_w{workers}.txt"
        assert main(["match", str(piece), str(b), "-o", str(out), "--partial", "--threads", "1",
                     "--workers", workers]) == 0
        maps.append(np.loadtxt(out, dtype=np.int64))
    assert taken == ([True, True, True] if sys.platform.startswith("linux") else [])
    assert np.array_equal(maps[0], maps[1]) and np.array_equal(maps[0], maps[2])
    # (its faces start at another corner: the same operator up to rounding)
    assert np.mean(maps[3] == maps[0]) > 0.95
    # arrays that are not the piece's closed mesh are refused
    ps = prepare(holed)
    assert not partial_scale.offer_filled(ps, V2[:-1], F2, (None, None))
    assert ps.caches.filled_eigenpairs is None


# ------------------------------------------------------------------------------------------
# SHREC'16 loader and barycentric evaluation
# ------------------------------------------------------------------------------------------
def test_read_barycentric_checks_the_file(tmp_path):
    from torchheat.datasets import read_barycentric

    F = np.array([[0, 1, 2], [1, 3, 2]])
    p = tmp_path / "a.baryc_gt"
    p.write_text("1 0.2 0.3 0.5\n2 0 0 1\n")
    b = read_barycentric(p, 2, F)
    assert b.corners.tolist() == [[0, 1, 2], [1, 3, 2]]
    assert b.nearest_corner().tolist() == [2, 2]
    p.write_text("0 0.2 0.3 0.5\n")
    with pytest.raises(ValueError, match="a.baryc_gt: triangle indices"):
        read_barycentric(p, 2, F)
    p.write_text("1 0.9 0.3 0.5\n")
    with pytest.raises(ValueError, match="sum to 1"):
        read_barycentric(p, 2, F)
    with pytest.raises(FileNotFoundError):
        read_barycentric(tmp_path / "missing.baryc_gt", 2, F)


def test_barycentric_errors_interpolate_the_distance_field():
    """The batch evaluation's barycentric error against GeodesicSolver fields directly."""
    from torchheat.batch import _barycentric_errors, _TargetGeodesics
    from torchheat.datasets import Barycentric
    from torchheat.evaluate import GeodesicSolver

    V, F = flat_grid(15, 12)
    mesh = Mesh(V, F)
    rng = np.random.default_rng(0)
    tri = rng.integers(0, len(F), 40)
    w = rng.dirichlet([1, 1, 1], 40)
    pred = rng.integers(0, len(V), 40)

    class _P:
        gt_bary = Barycentric(torch.as_tensor(F[tri]), torch.as_tensor(w))
        gt_sym_bary = None

    got = _barycentric_errors(_TargetGeodesics(mesh), pred, _P(), np.arange(40))[0]
    s = GeodesicSolver(mesh)
    want = np.array([sum(w[i, j] * s.distances([F[tri[i], j]])[0][pred[i]] for j in range(3))
                     for i in range(40)]) / math.sqrt(s.area)
    np.testing.assert_allclose(got, want, rtol=1e-7)  # the batch's fields are float32
    # on a flat grid the interpolated field is close to the true distance to the point
    P = (w[:, :, None] * V[F[tri]]).sum(1)
    euclid = np.linalg.norm(P - V[pred], axis=1) / math.sqrt(s.area)
    assert np.all(got >= euclid - 0.05)  # heat-method distances: up to ~4 % low
    assert np.median(np.abs(got - euclid)) < 0.03


@pytest.mark.skipif(not (SHARED / "shrec16_partial").is_dir(), reason="shared data missing")
def test_shrec16_partial_loader():
    from torchheat.datasets import shrec16_partial

    pc = shrec16_partial(kind="holes", classes=["dog"])
    assert len(pc) == 10 and pc.names[0] == "holes_dog_shape_1-dog"
    p = pc[0]
    assert p.target.name == "dog" and p.gt_bary is not None and p.gt_sym_bary is not None
    n = p.source.n_vertices
    assert p.gt_src.tolist() == list(range(n)) and p.gt_bary.corners.shape == (n, 3)
    # the ground truth maps edges of the piece to about the same length on the whole
    V, F = p.source.mesh.numpy()
    W, _ = p.target.mesh.numpy()
    pts = (p.gt_bary.weights.numpy()[:, :, None] * W[p.gt_bary.corners.numpy()]).sum(1)
    E = p.source.mesh.edges().numpy()
    ratio = np.linalg.norm(pts[E[:, 0]] - pts[E[:, 1]], axis=1) / np.linalg.norm(
        V[E[:, 0]] - V[E[:, 1]], axis=1)
    assert 0.9 < np.median(ratio) < 1.1
    assert len(shrec16_partial(kind="cuts")) == 90
    with pytest.raises(ValueError, match="unknown kind"):
        shrec16_partial(kind="slices")
