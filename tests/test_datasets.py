"""Datasets: loaders on the real shared data, the on-disk preprocessing cache, DataLoader use."""

from __future__ import annotations

import os
import pickle
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from torchheat import HeatKernel, load_mesh
from torchheat.datasets import (
    Preprocess,
    ShapeCollection,
    collate_list,
    data_root,
    folder,
    kids,
    landmarks,
    pairs_from_list,
    scape,
    tosca_hires,
    tosca_remeshed_5k,
    tosca_remeshed_5k_symmetry,
)
from torchheat.mesh import MeshWarning

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
SPOT = Path(__file__).resolve().parents[1] / "torchheat" / "data" / "spot.obj"

needs_data = pytest.mark.skipif(not SHARED.is_dir(), reason=f"shared data not found at {SHARED}")


@pytest.fixture(scope="module")
def tosca():
    if not SHARED.is_dir():
        pytest.skip(f"shared data not found at {SHARED}")
    return tosca_remeshed_5k(SHARED)


def _perturbed_obj(src: Path, dst: Path, scale: float = 0.01, seed: int = 0, only_first=False):
    """Copy an OBJ with its vertex coordinates moved (all of them, or the first one only)."""
    rng = np.random.default_rng(seed)
    out = []
    done = False
    for ln in src.read_text().splitlines():
        if ln.startswith("v ") and not (only_first and done):
            xyz = np.array(ln.split()[1:4], dtype=float)
            xyz += scale * rng.standard_normal(3)
            ln = "v " + " ".join(f"{c:.6f}" for c in xyz)
            done = True
        out.append(ln)
    dst.write_text("\n".join(out) + "\n")
    return dst


@pytest.fixture
def spot_files(tmp_path):
    a = tmp_path / "meshes" / "spot.obj"
    a.parent.mkdir()
    shutil.copyfile(SPOT, a)
    b = _perturbed_obj(SPOT, tmp_path / "meshes" / "spot_b.obj", scale=0.005)
    return a, b


class CallCounter:
    """Spy on Preprocess.__call__ (patched on the class, so it counts in this process)."""

    def __init__(self, monkeypatch):
        self.n = 0
        orig = Preprocess.__call__

        def spy(pp, mesh):
            self.n += 1
            return orig(pp, mesh)

        monkeypatch.setattr(Preprocess, "__call__", spy)


# ------------------------------------------------------------------------------------------
# loaders on real data
# ------------------------------------------------------------------------------------------
@needs_data
def test_tosca_5k_test_pairs_and_vts_ground_truth(tosca):
    assert len(tosca) == 284
    assert len(tosca.shapes) == 76
    p = tosca[0]
    a, b = tosca.names[0].split("-")
    assert p.name == f"{a}-{b}" and p.cls == "cat"
    assert p.source.name == a and p.target.name == b
    for g, shape in ((p.gt_src, p.source), (p.gt_tgt, p.target), (p.gt_sym_tgt, p.target)):
        assert g.dtype == torch.int64 and g.shape == (5000,)
        assert int(g.min()) >= 0 and int(g.max()) < shape.n_vertices
    corres = SHARED / "tosca_remeshed_5k" / "vtx_5k" / "corres"
    first = lambda name: int((corres / name).read_text().split()[0]) - 1  # noqa: E731
    assert int(p.gt_src[0]) == first(f"{a}.vts")
    assert int(p.gt_tgt[0]) == first(f"{b}.vts")
    assert int(p.gt_sym_tgt[0]) == first(f"{b}.sym.vts")
    # every pair is within a class
    assert all(tosca.shapes.classes[i] == tosca.shapes.classes[j] for i, j in tosca.pairs)
    # picklable (DataLoader workers receive the dataset), same items after the round trip
    again = pickle.loads(pickle.dumps(tosca))
    assert again.names == tosca.names and torch.equal(again[0].gt_tgt, p.gt_tgt)


@needs_data
def test_tosca_5k_gt_maps_neighbours_to_neighbours(tosca):
    p = tosca[0]
    src, dst = p.gt_src.numpy(), p.gt_tgt.numpy()
    n = p.source.n_vertices
    m = np.full(n, -1)
    m[src[::-1]] = dst[::-1]  # first listed image of every source vertex
    E = p.source.mesh.edges().numpy()
    E = E[(m[E[:, 0]] >= 0) & (m[E[:, 1]] >= 0)]
    assert len(E) > 1000
    VB = p.target.mesh.vertices.numpy()
    d_gt = np.linalg.norm(VB[m[E[:, 0]]] - VB[m[E[:, 1]]], axis=1).mean()
    perm = np.random.default_rng(0).permutation(p.target.n_vertices)
    d_rand = np.linalg.norm(VB[perm[m[E[:, 0]]]] - VB[perm[m[E[:, 1]]]], axis=1).mean()
    EB = p.target.mesh.edges().numpy()
    edge = np.linalg.norm(VB[EB[:, 0]] - VB[EB[:, 1]], axis=1).mean()
    # neighbours land about one target edge apart (1.3 on cat0-cat1), random ones ~20 edges
    assert d_gt < 0.1 * d_rand and d_gt < 2 * edge, (d_gt, d_rand, edge)
    # the symmetric map too
    ms = np.full(n, -1)
    ms[src[::-1]] = p.gt_sym_tgt.numpy()[::-1]
    d_sym = np.linalg.norm(VB[ms[E[:, 0]]] - VB[ms[E[:, 1]]], axis=1).mean()
    assert d_sym < 0.1 * d_rand and d_sym < 2 * edge


@needs_data
def test_tosca_5k_all_pairs_classes_and_symmetry():
    allp = tosca_remeshed_5k(SHARED, pairs="all")
    assert len(allp) == 414
    assert all(i < j for i, j in allp.pairs)
    wolf = tosca_remeshed_5k(SHARED, classes=["wolf"])
    assert len(wolf.shapes) == 3 and len(wolf) == 3  # test_pairs.txt has 3 wolf pairs
    sym = tosca_remeshed_5k_symmetry(SHARED, classes=["wolf"])
    assert len(sym) == 3 and len(tosca_remeshed_5k_symmetry(SHARED)) == 76
    q = sym[0]
    assert q.source is q.target and q.gt_sym_tgt is None
    assert q.gt_src.shape == q.gt_tgt.shape == (5000,)
    # a left/right symmetry moves most points
    assert (q.gt_src != q.gt_tgt).float().mean() > 0.5


@needs_data
def test_scape_pairs_are_identity():
    pc = scape(SHARED)
    assert len(pc) >= 30 and len(pc) == 40
    assert pc.names[0] == "mesh000-mesh001"
    assert all(i != j for i, j in pc.pairs)
    p = pc[0]
    assert p.gt_sym_tgt is None and p.cls == "scape"
    n = p.source.n_vertices
    assert n == p.target.n_vertices == 12500
    assert torch.equal(p.gt_src, torch.arange(n)) and torch.equal(p.gt_tgt, torch.arange(n))


@needs_data
def test_kids_and_tosca_hires_pairs():
    pc = kids(SHARED)
    assert len(pc) == 3
    assert pc.names == [
        "0001.null.0-0001.isometry.1",
        "0001.null.0-0001.isometry.2",
        "0001.isometry.1-0001.isometry.2",
    ]
    th = tosca_hires(SHARED)
    assert len(th) == 34
    wolf = tosca_hires(SHARED, classes=["wolf"])
    assert wolf.names == ["wolf0-wolf1", "wolf0-wolf2"]
    p = wolf[1]
    assert p.gt_src.shape == (4344,) and torch.equal(p.gt_src, p.gt_tgt)
    with pytest.raises(ValueError, match="unknown TOSCA classes"):
        tosca_hires(SHARED, classes=["unicorn"])


@needs_data
def test_landmarks_are_zero_based_with_symmetric_pairs():
    idx, names, sym = landmarks(SHARED, "tosca_hires", "cat")
    assert len(idx) == len(names) == 21
    assert names[0] == "tip of head/mouth"
    assert sym.shape == (8, 2) and sym.tolist()[0] == [2, 3]
    first = int((SHARED / "tosca_hires" / "landmarks" / "cat.pid").read_text().split()[0])
    assert idx[0] == first  # 0-based: read as is
    idx, names, sym = landmarks(SHARED, "scape")
    assert len(idx) == 36 and len(names) == 36 and sym.shape[1] == 2
    assert idx.max() < 12500 and sym.max() < 36


def test_missing_data_root_error_says_how_to_fix(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCHHEAT_DATA", str(tmp_path / "nowhere"))
    with pytest.raises(FileNotFoundError, match="TORCHHEAT_DATA"):
        data_root()
    with pytest.raises(FileNotFoundError, match="TORCHHEAT_DATA"):
        scape()
    monkeypatch.setenv("TORCHHEAT_DATA", str(tmp_path))
    with pytest.raises(FileNotFoundError, match="scape"):
        scape()


# ------------------------------------------------------------------------------------------
# cache
# ------------------------------------------------------------------------------------------
def test_preprocess_key_is_stable_and_parameter_sensitive():
    a = Preprocess(times=[0.1, 1.0], k=12)
    assert a.times == (0.1, 1.0)
    assert a.key() == Preprocess(times=(0.1, 1.0), k=12).key()
    t64 = torch.tensor([0.1, 1.0], dtype=torch.float64)
    assert a.key() == Preprocess(times=t64, k=12).key() == Preprocess(times=t64.numpy(), k=12).key()
    assert a.key() != Preprocess(times=torch.tensor([0.1, 1.0]), k=12).key()  # float32 values
    keys = {
        a.key(),
        Preprocess(times=[0.1, 1.0], k=13).key(),
        Preprocess(times=[0.1, 1.5], k=12).key(),
        Preprocess(times=[0.1, 1.0], k=12, kind="fem").key(),
        Preprocess(times=[0.1, 1.0], k=12, boundary="dirichlet").key(),
        Preprocess(k=12).key(),
    }
    assert len(keys) == 6
    # (k=5.5 solved 5 eigenpairs; a NaN time passed the positivity test)
    for bad in ({"k": 0}, {"kind": "x"}, {"boundary": "x"}, {"times": [0.0]},
                {"times": [float("nan")]}, {"times": [1.0, float("inf")]}):
        with pytest.raises(ValueError):
            Preprocess(**bad)
    # the number of eigenpairs follows prepare's rule: an integer, not a float, not a bool
    import trimesh

    import torchheat

    ico = trimesh.creation.icosphere(1)
    sphere = torchheat.Mesh(ico.vertices, ico.faces)
    for bad_k in (5.5, 3.0, True, "8"):
        with pytest.raises(TypeError, match="k must be an integer"):
            Preprocess(k=bad_k)
        with pytest.raises(TypeError, match="k must be an integer"):
            torchheat.prepare(sphere, k=bad_k)
    assert Preprocess(k=np.int64(7)).k == 7 and type(Preprocess(k=np.int64(7)).k) is int


def test_membership_by_name_reads_no_file(spot_files, tmp_path, monkeypatch):
    calls = CallCounter(monkeypatch)
    a, b = spot_files
    ds = ShapeCollection([a, b], names=["one", "two"], preprocess=Preprocess(k=8),
                         cache_dir=tmp_path / "cache")
    monkeypatch.setattr(ShapeCollection, "__getitem__",
                        lambda self, i: pytest.fail("membership loaded a shape"))
    assert "two" in ds and "one" in ds
    assert "three" not in ds and 0 not in ds and a.stem not in ds
    assert calls.n == 0 and not (tmp_path / "cache").exists()


def test_cache_hit_parameter_change_and_file_change(spot_files, tmp_path, monkeypatch):
    calls = CallCounter(monkeypatch)
    a, _ = spot_files
    cache = tmp_path / "cache"
    pp = Preprocess(k=8)
    ds = ShapeCollection([a], preprocess=pp, cache_dir=cache)
    s1 = ds[0]
    assert calls.n == 1
    d = s1.data
    assert d["eigenvectors"].shape == (2930, 8) and d["hks"].shape == (2930, 10)
    assert abs(float(d["mass"].sum()) - 1.0) < 1e-12 and d["area"] > 0 and d["lambda_max"] > 0
    s2 = ds[0]  # from disk
    assert calls.n == 1
    for k in ("eigenvalues", "eigenvectors", "hks", "mass", "times"):
        assert torch.equal(s1.data[k], s2.data[k])
    assert s2.data["lambda_max"] == d["lambda_max"] and s2.data["area"] == d["area"]
    # a new collection (another process, say) with the same parameters reuses the entry
    ShapeCollection([a], preprocess=Preprocess(k=8), cache_dir=cache)[0]
    assert calls.n == 1
    # changing a parameter recomputes
    s3 = ShapeCollection([a], preprocess=Preprocess(k=9), cache_dir=cache)[0]
    assert calls.n == 2 and s3.data["eigenvalues"].numel() == 9
    # changing the file bytes recomputes, and the result differs
    _perturbed_obj(SPOT, a, scale=0.02, only_first=True)
    s4 = ds[0]
    assert calls.n == 3
    assert not torch.allclose(s4.data["eigenvalues"], d["eigenvalues"], rtol=0, atol=1e-12)
    ds[0]
    assert calls.n == 3
    files = sorted(p.name for p in cache.iterdir())
    assert len(files) == 3 and all(f.endswith(".npz") for f in files)  # no temp files left


def test_cache_entries_are_readable_by_the_team(spot_files, tmp_path):
    # a cache shared by several users (torchheat preprocess --cache /shared/cache) needs the
    # umask's permissions, not mkstemp's owner-only 0o600 (what entries got before)
    import stat

    a, _ = spot_files
    old = os.umask(0o022)
    try:
        ds = ShapeCollection([a], preprocess=Preprocess(k=6), cache_dir=tmp_path / "c")
        ds[0]
    finally:
        os.umask(old)
    assert stat.S_IMODE(ds.cache_path(0).stat().st_mode) == 0o644


def test_corrupt_cache_entry_is_recomputed(spot_files, tmp_path, monkeypatch):
    calls = CallCounter(monkeypatch)
    a, _ = spot_files
    ds = ShapeCollection([a], preprocess=Preprocess(k=6), cache_dir=tmp_path / "c")
    ds[0]
    path = ds.cache_path(0)
    path.write_bytes(b"not a zip file")
    with pytest.warns(UserWarning, match="unusable cache entry"):
        s = ds[0]
    assert calls.n == 2 and s.data["eigenvalues"].numel() == 6
    ds[0]
    assert calls.n == 2


def test_cached_shape_heat_kernel_equals_fresh_solver(spot_files, tmp_path):
    a, _ = spot_files
    ds = ShapeCollection([a], preprocess=Preprocess(k=8), cache_dir=tmp_path / "c")
    ds[0]
    shape = ds[0]  # read back from disk
    hk = shape.heat_kernel()
    ref = HeatKernel(load_mesh(a), k=8)
    assert hk.lambda_max == ref.lambda_max
    torch.testing.assert_close(hk.eigenvalues, ref.eigenvalues, rtol=0, atol=1e-12)
    c, r = hk.columns([0]), ref.columns([0])
    assert c.shape == r.shape == (1, 2930, 10)
    assert float((c - r).abs().max()) <= 1e-10 * float(r.abs().max())
    assert torch.allclose(c, r, rtol=0, atol=1e-10)
    # fewer eigenpairs: a slice of the cache; other overrides pass through
    assert shape.heat_kernel(k=4, rtol=1e-8).eigenvalues.numel() == 4


def test_dataloader_with_two_workers(spot_files, tmp_path):
    a, b = spot_files
    ds = ShapeCollection([a, b], preprocess=Preprocess(k=6), cache_dir=tmp_path / "c")
    loader = DataLoader(ds, batch_size=1, num_workers=2, collate_fn=collate_list)
    got = [s for batch in loader for s in batch]
    assert sorted(s.name for s in got) == ["spot", "spot_b"]
    assert all(s.data is not None and s.data["eigenvalues"].numel() == 6 for s in got)
    assert not np.allclose(got[0].data["eigenvalues"], got[1].data["eigenvalues"])
    assert len(list((tmp_path / "c").glob("*.npz"))) == 2
    assert not any(p.name.startswith(".") for p in (tmp_path / "c").iterdir())  # temporaries


def test_folder_and_pairs_from_list(spot_files, tmp_path):
    a, b = spot_files
    (a.parent / "notes.txt").write_text("not a mesh")
    shapes = folder(a.parent)
    assert shapes.names == ["spot", "spot_b"] and shapes.classes == ["spot", "spot_b"]
    assert shapes.preprocess is None and shapes[0].data is None
    pc = pairs_from_list(shapes, [("spot", "spot_b"), (1, 0)])
    assert pc.names == ["spot-spot_b", "spot_b-spot"]
    p = pc[0]
    assert p.cls == "spot-spot_b" and torch.equal(p.gt_src, torch.arange(2930))
    assert pairs_from_list(shapes, [(0, 1)], gt=None)[0].gt_src is None
    with pytest.raises(KeyError):
        pairs_from_list(shapes, [("spot", "cow")])
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no files matching"):
        folder(tmp_path / "empty")


def test_folder_matches_extensions_in_any_case(spot_files, tmp_path):
    # exports from Windows and macOS tools: SPOT.OBJ, Spot.Obj; a case-sensitive glob left
    # them out of the collection without a word
    a, _ = spot_files
    d = tmp_path / "mixed"
    d.mkdir()
    shutil.copy(a, d / "spot1.obj")
    shutil.copy(a, d / "SPOT2.OBJ")
    shutil.copy(a, d / "spot3.Obj")
    (d / "sub").mkdir()
    shutil.copy(a, d / "sub" / "spot4.obj")
    (d / "readme.TXT").write_text("not a mesh")
    shapes = folder(d)
    assert sorted(shapes.names) == ["SPOT2", "spot1", "spot3"]
    assert shapes[shapes.names.index("SPOT2")].mesh.n_vertices == 2930
    assert folder(d, pattern="*.OBJ").names == shapes.names  # patterns ignore case too
    assert folder(d, pattern="sub/*.obj").names == ["spot4"]  # a subfolder pattern is globbed


def test_default_cache_dir_from_environment(spot_files, tmp_path, monkeypatch):
    a, _ = spot_files
    monkeypatch.setenv("TORCHHEAT_CACHE", str(tmp_path / "envcache"))
    ds = ShapeCollection([a], preprocess=Preprocess(k=4))
    assert ds.cache_dir == tmp_path / "envcache"
    assert ds.cache_path(0).parent == tmp_path / "envcache"
    assert os.fspath(ds.cache_path(0)).endswith(".npz")


class _Threads(torch.utils.data.Dataset):
    def __len__(self):
        return 2

    def __getitem__(self, i):
        from threadpoolctl import threadpool_info

        blas = [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]
        return torch.get_num_threads(), max(blas)


def test_worker_init_limits_torch_and_blas_threads():
    from torchheat.datasets import worker_init

    loader = DataLoader(_Threads(), batch_size=1, num_workers=2, collate_fn=collate_list,
                        worker_init_fn=worker_init)
    assert [b[0] for b in loader] == [(1, 1), (1, 1)]


def test_match_and_symmetry_take_dataset_shapes_and_pairs(tmp_path, monkeypatch):
    """A dataset shape's cached eigenpairs serve match/prepare/symmetry: no eigensolve, and
    the same maps as from the meshes prepared with the same eigenpair count."""
    from conftest import deformed_spheres

    from torchheat import heat, match, prepare, symmetry

    files = deformed_spheres(tmp_path / "m", n=2)
    shapes = ShapeCollection(files, preprocess=Preprocess(k=30), cache_dir=tmp_path / "c")
    shapes.fill_cache()
    pc = pairs_from_list(shapes, [(0, 1)])
    calls = []
    orig = heat.HeatKernel._eigensolve
    monkeypatch.setattr(heat.HeatKernel, "_eigensolve",
                        lambda self, k, **kw: calls.append(k) or orig(self, k, **kw))
    loader = DataLoader(pc, batch_size=1, collate_fn=collate_list)
    (pair,) = next(iter(loader))
    corr = match(pair, method="paper")
    prepared = prepare(pair.source)
    sym = symmetry(pair.target, method="paper")
    assert calls == []  # everything from the cache
    assert prepared.hk.k == 30 and prepared.hk.times.numel() == 10
    ref = match(prepare(pair.source.mesh, k=30), prepare(pair.target.mesh, k=30), method="paper")
    assert calls == [30, 30]
    assert torch.equal(corr.map, ref.map) and corr.landmarks == ref.landmarks
    assert torch.equal(prepared.hk.times, prepare(pair.source.mesh, k=30).hk.times)
    assert sym.map.shape == (pair.target.n_vertices,)
    assert prepare(pair.source, k=40).hk.k == 40 and calls[-1] == 40  # more: solved again
    with pytest.raises(TypeError, match="dataset Pair"):
        match(pair.source)


def test_cached_eigenpairs_beyond_k_serve_fine_maps(tmp_path, monkeypatch):
    """Preprocess(k=40) cached, prepared with k=30: the heat kernel is the 30-pair one and
    match(fine_k=40) refines on the cached 40 without an eigensolve."""
    from conftest import deformed_spheres

    from torchheat import heat, match, prepare

    files = deformed_spheres(tmp_path / "m", n=2)
    shapes = ShapeCollection(files, preprocess=Preprocess(k=40), cache_dir=tmp_path / "c")
    shapes.fill_cache()
    calls = []
    orig = heat.HeatKernel._eigensolve
    monkeypatch.setattr(heat.HeatKernel, "_eigensolve",
                        lambda self, k, **kw: calls.append(k) or orig(self, k, **kw))
    S, T = prepare(shapes[0], k=30), prepare(shapes[1], k=30)
    assert S.hk.k == 30 and S.caches.basis.shape == (S.n, 40)
    assert torch.equal(S.caches.basis, shapes[0].data["eigenvectors"].double())
    c = match(S, T, fine_k=40)
    assert c.map.shape == (S.n,) and "fine_map" in c.info["timings"]
    assert calls == []  # the 40 modes came from the cache
    assert prepare(shapes[0]).caches.basis is None  # all 40 in the heat kernel: nothing more


def test_ordered_pairs_and_fill_cache(tmp_path):
    from conftest import deformed_spheres

    files = deformed_spheres(tmp_path / "m", n=3, subdivisions=2)
    shapes = ShapeCollection(files, classes=["blob"] * 3, preprocess=Preprocess(k=8),
                             cache_dir=tmp_path / "c")
    from torchheat.datasets.loaders import _within_class_pairs

    assert _within_class_pairs(shapes, "ordered") == [(0, 1), (0, 2), (1, 0), (1, 2), (2, 0),
                                                      (2, 1)]
    assert not any(shapes.is_cached(i) for i in range(3))
    first = shapes.fill_cache()
    assert [d["computed"] for d in first] == [True] * 3 and all(map(shapes.is_cached, range(3)))
    again = shapes.fill_cache()
    assert [d["computed"] for d in again] == [False] * 3
    assert [d["path"] for d in again] == [str(shapes.cache_path(i)) for i in range(3)]
    (tmp_path / "c" / Path(first[0]["path"]).name).write_bytes(b"broken")
    assert not shapes.is_cached(0)
    with pytest.warns(UserWarning, match="unusable cache entry"):
        assert [d["computed"] for d in shapes.fill_cache()] == [True, False, False]


def test_folder_lists_compressed_meshes_by_their_inner_name(spot_files, tmp_path):
    # spot.obj.gz is read as spot.obj and named spot (its stem was "spot.obj", and the folder
    # left compressed files out)
    import gzip

    a, _ = spot_files
    d = tmp_path / "packed"
    d.mkdir()
    (d / "spot.obj.gz").write_bytes(gzip.compress(a.read_bytes()))
    shutil.copyfile(a, d / "cow2.obj")
    shapes = folder(d)
    assert shapes.names == ["cow2", "spot"] and shapes.classes == ["cow", "spot"]
    V1, _ = shapes[1].mesh.numpy()
    V0, _ = shapes[0].mesh.numpy()
    assert np.array_equal(V0, V1)  # the same mesh, read through gzip


def test_a_files_mesh_warning_is_shown_once_per_collection(tmp_path):
    # a shape is read again on every access (a whole in many pairs): its MeshWarning once
    V = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]]
    F = [[0, 1, 2], [0, 1, 3], [0, 1, 4]]  # edge (0, 1) in three faces
    path = tmp_path / "fan.off"
    path.write_text("OFF\n5 3 0\n" + "".join(f"{x} {y} {z}\n" for x, y, z in V)
                    + "".join(f"3 {a} {b} {c}\n" for a, b, c in F))
    ds = ShapeCollection([path])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        meshes = [ds[0].mesh for _ in range(3)]
        ShapeCollection([path])[0]  # another collection says it again
    mesh_warnings = [w for w in caught if issubclass(w.category, MeshWarning)]
    assert len(mesh_warnings) == 2
    assert "non-manifold edge" in str(mesh_warnings[0].message)
    assert mesh_warnings[0].filename == __file__  # points at the caller, not the package
    assert all(m.n_faces == 3 for m in meshes)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        with pytest.raises(MeshWarning):
            ShapeCollection([path])[0]
