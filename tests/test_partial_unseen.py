"""scripts/partial_unseen.py: its random pieces are repeatable, keep what they say, and make
meshes the matcher takes (the held-out partial check must not test broken pieces)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from conftest import SHARED, load_script


def _script():
    return load_script("partial_unseen")


def _capsule():
    m = trimesh.creation.capsule(height=2.0, radius=0.5, count=[32, 32])
    return np.asarray(m.vertices, float), np.asarray(m.faces)


def test_random_cut_keeps_one_side_of_its_planes_and_repeats_with_its_seed():
    pu = _script()
    V, F = _capsule()
    a = pu.random_cut(V, F, np.random.default_rng(3))
    b = pu.random_cut(V, F, np.random.default_rng(3))
    assert a.dtype == bool and a.shape == (len(F),) and (a == b).all()
    kept = [pu.random_cut(V, F, np.random.default_rng(s)).mean() for s in range(40)]
    assert 0.0 < min(kept) and max(kept) < 1.0 and np.std(kept) > 0.1
    # a one-plane draw: the kept faces lie on one side of the plane, every dropped face has a
    # vertex on the other (the plane redrawn from the same seed, as random_cut draws it)
    one = [s for s in range(40) if np.random.default_rng(s).integers(1, 3) == 1]
    assert one
    for s in one[:5]:
        keep = pu.random_cut(V, F, np.random.default_rng(s))
        rng = np.random.default_rng(s)
        rng.integers(1, 3)  # the plane count and the kept share, drawn first
        rng.uniform(0.14, 0.88)
        d = rng.normal(size=3)
        h = V @ (d / np.linalg.norm(d))
        assert keep.any() and (h[F[~keep]].min(axis=1) < h[F[keep]].min()).all()


def test_random_holes_drop_the_faces_inside_balls_and_make_a_matchable_piece():
    pu = _script()
    V, F = _capsule()
    keep = pu.random_holes(V, F, np.random.default_rng(5))
    assert 0.2 < keep.mean() < 0.99
    piece = pu._piece(V, F, keep, "holed")
    assert piece.n_vertices < len(V) and piece.n_vertices > 300
    # the piece's vertices are vertices of the mesh, found back through vertex_map
    Vp, _ = piece.numpy()
    assert np.allclose(Vp, V[piece.vertex_map.numpy()])


def test_fixed_pieces_cut_below_the_height_quantile():
    pu = _script()
    V, F = _capsule()
    pieces = pu.fixed_pieces(V, F)
    c = np.quantile(V[:, 1], 0.6)
    assert (V[F[pieces["cut"]], 1] <= c).all() and (V[F[~pieces["cut"]], 1] > c).any(axis=1).all()
    assert 0.5 < pieces["holes"].mean() < 1.0


def test_match_options_read_each_value_as_yaml_and_refuse_an_item_without_a_key():
    pu = _script()
    got = pu.match_options(["refine_samples=49", "zoomout=false", " partial_scale = piece",
                            "orientation_weight=2.5"])
    assert got == {"refine_samples": 49, "zoomout": False, "partial_scale": "piece",
                   "orientation_weight": 2.5}
    assert pu.match_options([]) == {}
    for bad in ("refine_samples", "=3"):
        with pytest.raises(ValueError, match="expected KEY=VALUE"):
            pu.match_options([bad])
    with pytest.raises(TypeError, match="'refine_sample' .did you mean 'refine_samples'"):
        pu.match_options(["refine_sample=49"])
    with pytest.raises(ValueError, match="refine_samples"):  # below its least value
        pu.match_options(["refine_samples=0"])
    with pytest.raises(ValueError, match="always matched with partial=True"):
        pu.match_options(["partial=false"])


@pytest.mark.skipif(not (SHARED / "tosca_remeshed_5k").exists(), reason="shared TOSCA data absent")
def test_a_file_of_other_options_is_not_resumed(tmp_path):
    # resuming would mix pieces matched with different options in one file
    out = tmp_path / "u.jsonl"
    out.write_text('{"piece": "wolf0-wolf1:cut0", "kind": "cut", "acc": 1.0}\n')
    with pytest.raises(SystemExit, match="matched with options {}, not {'refine_samples': 49}"):
        _script().main([str(out), "wolf", "--random", "1", "--match", "refine_samples=49"])
