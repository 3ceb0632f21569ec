"""Command line interface (torchheat.cli) and colour-transfer pictures (torchheat.viz)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import DATA, flat_grid, generic_sphere, write_off

from torchheat.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def rotation(seed: int = 3) -> np.ndarray:
    q, r = np.linalg.qr(np.random.default_rng(seed).standard_normal((3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


@pytest.fixture(scope="module")
def pair(tmp_path_factory):
    """A 642-vertex generic mesh and a permuted + rotated copy; ``expected[i]`` is the image
    of source vertex ``i``."""
    d = tmp_path_factory.mktemp("pair")
    V, F = generic_sphere(3)
    perm = np.random.default_rng(7).permutation(len(V))  # target vertex j = source perm[j]
    inv = np.argsort(perm)
    V2 = (V @ rotation().T)[perm]
    F2 = inv[F]
    src = write_off(d / "src.off", V, F)
    tgt = write_off(d / "tgt.off", V2, F2)
    return src, tgt, inv, d


def read_map(path: Path) -> np.ndarray:
    lines = path.read_text().splitlines()
    assert all(ln.strip().lstrip("-").isdigit() for ln in lines)
    return np.array([int(ln) for ln in lines], dtype=np.int64)


@pytest.fixture(scope="module")
def matched(pair):
    src, tgt, inv, d = pair
    out, sym, png = d / "map.txt", d / "sym.txt", d / "map.png"
    rc = main(["match", str(src), str(tgt), "-o", str(out), "--symmetric-out", str(sym),
               "--png", str(png), "--threads", "1"])
    return rc, out, sym, png


def test_match_round_trip(pair, matched, capsys):
    _, _, inv, d = pair
    rc, out, sym, png = matched
    assert rc == 0
    f = read_map(out)
    assert f.shape == (len(inv),)
    assert f.min() >= 0 and f.max() < len(inv)
    assert np.mean(f == inv) >= 0.99
    assert png.read_bytes()[:8] == PNG_MAGIC
    if sym.exists():  # a generic shape has a (poor) symmetric alternative, or none
        g = read_map(sym)
        assert g.shape == (len(inv),) and g.min() >= 0 and g.max() < len(inv)
    assert not [p for p in os.listdir(d) if p.startswith(".")]  # no temporary files left


def test_map_named_npy_is_a_numpy_file(pair, matched, tmp_path):
    # '-o map.npy' wrote text under that name, which np.load refuses
    src, tgt, _, _ = pair
    _, out, _, _ = matched
    npy, sym = tmp_path / "map.NPY", tmp_path / "sym.npy"
    assert main(["match", str(src), str(tgt), "-o", str(npy), "--symmetric-out", str(sym),
                 "--threads", "1"]) == 0
    f = np.load(npy)
    assert f.dtype == np.int64 and np.array_equal(f, read_map(out))
    assert np.load(sym).shape == f.shape
    assert sorted(os.listdir(tmp_path)) == ["map.NPY", "sym.npy"]  # nothing else, no .npy.npy


def test_symmetric_out_written(pair):
    # the paper's pipeline always reports its next distinct candidate as the symmetric map
    # (the default pipeline reports one only when an orientation-reversing map exists)
    src, tgt, inv, d = pair
    out, sym = d / "p_map.txt", d / "p_sym.txt"
    rc = main(["match", str(src), str(tgt), "-o", str(out), "--symmetric-out", str(sym),
               "--method", "paper", "--threads", "1"])
    assert rc == 0 and sym.exists()
    g = read_map(sym)
    assert g.shape == (len(inv),) and g.min() >= 0 and g.max() < len(inv)
    assert np.mean(g == inv) < 0.5  # a different map from the direct one


def test_match_fixed_pair_and_paper_method(pair, capsys):
    src, tgt, inv, d = pair
    out = d / "pair.txt"
    p = 17
    rc = main(["match", str(src), str(tgt), "-o", str(out), "--landmark", str(p),
               str(int(inv[p])), "--method", "paper", "--threads", "1"])
    assert rc == 0
    f = read_map(out)
    assert np.mean(f == inv) >= 0.99
    stdout = capsys.readouterr().out
    assert f"({p}, {int(inv[p])})" in stdout and "timings" in stdout
    assert "search:" not in stdout  # the paper's pipeline has no staged search


def test_match_prints_which_search_gave_the_map(pair, capsys):
    src, tgt, inv, d = pair
    out = d / "staged.txt"
    assert main(["match", str(src), str(tgt), "-o", str(out), "--threads", "1"]) == 0
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("search: ")]
    assert len(lines) == 1
    assert lines[0] in ("search: first stage", "search: full (first stage not clear)")
    assert np.mean(read_map(out) == inv) >= 0.99


def test_symmetry_writes_map(pair, capsys):
    src, _, inv, d = pair
    out = d / "self.txt"
    assert main(["symmetry", str(src), "-o", str(out), "--threads", "1"]) == 0
    f = read_map(out)
    assert f.shape == (len(inv),) and f.min() >= 0 and f.max() < len(inv)


def test_console_script_subprocess(tmp_path):
    V, F = generic_sphere(2, seed=1)
    mesh = write_off(tmp_path / "small.off", V, F)
    out = tmp_path / "sym.txt"
    exe = Path(sys.executable).parent / "torchheat"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "torchheat.cli"]
    res = subprocess.run([*cmd, "symmetry", str(mesh), "-o", str(out), "--threads", "1"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "Traceback" not in res.stderr
    assert len(out.read_text().splitlines()) == len(V)
    res = subprocess.run([*cmd, "--version"], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0 and "torchheat" in res.stdout
    # the fast exit (os._exit after match/symmetry/demo) keeps the exit status and the output
    res = subprocess.run([*cmd, "match", str(tmp_path / "missing.off"), str(mesh), "-o",
                          str(tmp_path / "m.txt")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 1 and not (tmp_path / "m.txt").exists()
    assert res.stderr.strip().count("\n") == 0 and "missing.off: no such file" in res.stderr


def test_python_dash_m_torchheat_is_the_command(tmp_path):
    """``python -m torchheat`` (no scripts folder on PATH) runs the same command."""
    res = subprocess.run([sys.executable, "-m", "torchheat", "--version"], capture_output=True,
                         text=True, timeout=60, cwd=tmp_path)
    assert res.returncode == 0 and res.stdout.startswith("torchheat "), res.stderr
    res = subprocess.run([sys.executable, "-m", "torchheat", "check",
                          str(tmp_path / "missing.off")], capture_output=True, text=True,
                         timeout=60, cwd=tmp_path)
    assert res.returncode == 1 and "missing.off: no such file" in res.stdout + res.stderr


def test_background_eigensolves_give_the_same_map(pair, matched):
    # --workers 0 solves in-process; the default (workers, when 2+ CPUs) must not change maps
    src, tgt, inv, d = pair
    _, out, _, _ = matched
    out0 = d / "map_w0.txt"
    rc = main(["match", str(src), str(tgt), "-o", str(out0), "--threads", "1",
               "--workers", "0"])
    assert rc == 0
    assert np.array_equal(read_map(out0), read_map(out))


# ------------------------------------------------------------------------------- bad input
def _bad_files(d: Path) -> dict[str, Path]:
    V, F = generic_sphere(2, seed=2)
    files = {}
    files["missing"] = d / "does_not_exist.off"
    unknown = d / "mesh.xyz"
    unknown.write_text("1 2 3\n")
    files["unknown_ext"] = unknown
    raw = [f"{x:.17g} {y:.17g} {z:.17g}" for x, y, z in V]
    raw[5] = "nan 0.1 0.2"
    files["nan"] = write_off(d / "nan_coord.off", V, F, raw_vertices=raw)
    Fd = F.copy()
    Fd[3] = [Fd[3, 0], Fd[3, 0], Fd[3, 1]]
    files["degenerate"] = write_off(d / "degenerate_face.off", V, Fd)
    Fr = F.copy()
    Fr[4, 1] = len(V) + 10
    files["out_of_range"] = write_off(d / "face_out_of_range.off", V, Fr)
    return files


@pytest.mark.parametrize("case", ["missing", "unknown_ext", "nan", "degenerate", "out_of_range"])
@pytest.mark.parametrize("role", ["source", "target"])
def test_bad_mesh_input(pair, tmp_path, capsys, case, role):
    good = pair[0]
    bad = _bad_files(tmp_path)[case]
    out = tmp_path / "map.txt"
    src, tgt = (bad, good) if role == "source" else (good, bad)
    rc = main(["match", str(src), str(tgt), "-o", str(out)])
    err = capsys.readouterr().err
    assert rc != 0
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith("torchheat: error: ")
    assert bad.name in err
    assert "Traceback" not in err
    assert not out.exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]  # no temporary files


@pytest.mark.parametrize("case", ["missing", "nan", "degenerate"])
def test_bad_mesh_symmetry(tmp_path, capsys, case):
    bad = _bad_files(tmp_path)[case]
    out = tmp_path / "sym.txt"
    assert main(["symmetry", str(bad), "-o", str(out)]) != 0
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and bad.name in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("landmark", [["100000"], ["-1"], ["0", "99999"]])
def test_landmark_out_of_range(pair, tmp_path, capsys, landmark):
    src, tgt, _, _ = pair
    out = tmp_path / "map.txt"
    rc = main(["match", str(src), str(tgt), "-o", str(out), "--landmark", *landmark])
    err = capsys.readouterr().err
    assert rc != 0
    assert len(err.strip().splitlines()) == 1, err
    named = tgt.name if len(landmark) == 2 else src.name
    assert named in err and "out of range" in err and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize("flag", [["--threads", "0"], ["--workers", "-1"], ["--fine", "0"]])
def test_counts_below_their_least_refused_by_name(pair, tmp_path, capsys, flag):
    # --workers -1 ran in-process without a word; --threads 0 failed inside torch
    src, tgt, _, _ = pair
    out = tmp_path / "map.txt"
    with pytest.raises(SystemExit) as exc:
        main(["match", str(src), str(tgt), "-o", str(out), *flag])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and f"argument {flag[0]}: must be at least" in err
    assert not out.exists()


def test_unwritable_output_dir(pair, tmp_path, capsys):
    src, tgt, _, _ = pair
    out = tmp_path / "no_such_dir" / "map.txt"
    rc = main(["match", str(src), str(tgt), "-o", str(out)])
    err = capsys.readouterr().err
    assert rc != 0 and len(err.strip().splitlines()) == 1
    assert "map.txt" in err and "does not exist" in err and "Traceback" not in err
    assert not out.exists()


def test_usage_errors_exit_2(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["match", "a.off"])
    assert exc.value.code == 2
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert "torchheat" in capsys.readouterr().out


def test_evaluate_delegates_to_batch(monkeypatch):
    import types

    seen = {}
    fake = types.ModuleType("torchheat.batch")
    fake.main = lambda argv: seen.setdefault("argv", argv) and 0
    monkeypatch.setitem(sys.modules, "torchheat.batch", fake)
    import torchheat

    monkeypatch.setattr(torchheat, "batch", fake, raising=False)
    assert main(["evaluate", "cfg.yaml", "--workers", "2", "--extra"]) == 0
    assert seen["argv"] == ["cfg.yaml", "--workers", "2", "--extra"]


# ------------------------------------------------------------------------------------- viz
def test_color_transfer_png(tmp_path):
    from torchheat import Mesh
    from torchheat.viz import color_transfer

    V, F = generic_sphere(3)
    mesh = Mesh(V, F, name="generic")
    f = np.arange(len(V))
    f[:50] = f[50:100]
    path = color_transfer(mesh, mesh, f, tmp_path / "ct.png", title="identity-ish")
    data = path.read_bytes()
    assert data[:8] == PNG_MAGIC and len(data) > 10_000
    err = np.linalg.norm(V[f] - V, axis=1)
    path3 = color_transfer(mesh, mesh, f, tmp_path / "ct3.png", errors=err)
    assert path3.read_bytes()[:8] == PNG_MAGIC
    assert path3.stat().st_size > 10_000
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]  # no temporary files
    # the format follows the extension (a .pdf or .svg was written as PNG bytes)
    assert color_transfer(mesh, mesh, f, tmp_path / "ct.PDF").read_bytes()[:5] == b"%PDF-"
    assert b"<svg" in color_transfer(mesh, mesh, f, tmp_path / "ct.svg").read_bytes()[:500]
    assert color_transfer(mesh, mesh, f, tmp_path / "ct.jpg").read_bytes()[:2] == b"\xff\xd8"
    with pytest.raises(ValueError, match="unknown picture format '.gif'"):
        color_transfer(mesh, mesh, f, tmp_path / "ct.gif")


def test_picture_format_refused_before_work(pair, tmp_path, capsys):
    src, tgt, _, _ = pair
    out = tmp_path / "map.txt"
    assert main(["match", str(src), str(tgt), "-o", str(out), "--png",
                 str(tmp_path / "ct.gif")]) != 0
    err = capsys.readouterr().err
    assert "unknown picture format '.gif'" in err and not out.exists()


def test_color_transfer_rejects_bad_map(tmp_path):
    from torchheat import Mesh
    from torchheat.viz import color_transfer

    V, F = generic_sphere(2)
    mesh = Mesh(V, F)
    with pytest.raises(ValueError):
        color_transfer(mesh, mesh, np.full(len(V), len(V)), tmp_path / "bad.png")
    with pytest.raises(ValueError):
        color_transfer(mesh, mesh, np.arange(3), tmp_path / "bad.png")
    assert not (tmp_path / "bad.png").exists()


# ---------------------------------------------------------------------- --largest-component
def _with_pieces(V: np.ndarray, F: np.ndarray, shift: float):
    """``V, F`` behind a stray triangle (file vertices 0..2) and before an unreferenced vertex:
    mesh vertex i is file vertex i + 3; the file has len(V) + 4 vertices."""
    stray = V[:3] + [shift, 0.0, 0.0]
    V2 = np.vstack([stray, V, [[shift, shift, shift]]])
    F2 = np.vstack([[[0, 1, 2]], F + 3])
    return V2, F2


@pytest.fixture(scope="module")
def pieces_pair(tmp_path_factory):
    """A 162-vertex generic mesh and a permuted + rotated copy, both with a stray triangle and
    an unreferenced vertex: file source vertex 3 + i maps to file target vertex 3 + inv[i]."""
    d = tmp_path_factory.mktemp("pieces")
    V, F = generic_sphere(2, seed=4)
    perm = np.random.default_rng(5).permutation(len(V))
    inv = np.argsort(perm)
    src = write_off(d / "src_pieces.off", *_with_pieces(V, F, 5.0))
    tgt = write_off(d / "tgt_pieces.off", *_with_pieces((V @ rotation().T)[perm], inv[F], -5.0))
    expected = np.full(len(V) + 4, -1)
    expected[3:-1] = 3 + inv
    return src, tgt, expected, d


def test_several_components_refused_with_the_flag_named(pieces_pair, capsys):
    src, tgt, _, d = pieces_pair
    rc = main(["match", str(src), str(tgt), "-o", str(d / "no.txt")])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1
    assert src.name in err and "--largest-component" in err and "Traceback" not in err
    assert not (d / "no.txt").exists()


def test_largest_component_map_in_file_numbering(pieces_pair, capsys):
    src, tgt, expected, d = pieces_pair
    out, sym, png = d / "map.txt", d / "sym.txt", d / "map.png"
    p = 3 + 17
    rc = main(["match", str(src), str(tgt), "-o", str(out), "--largest-component",
               "--symmetric-out", str(sym), "--png", str(png), "--method", "paper",
               "--landmark", str(p), "--threads", "1"])
    assert rc == 0
    f = read_map(out)
    assert f.shape == (166,)  # one line per vertex of the source file
    assert f[[0, 1, 2, 165]].tolist() == [-1, -1, -1, -1]  # the dropped ones
    assert np.mean(f == expected) >= 0.99  # target indices are the target file's
    stdout = capsys.readouterr().out
    assert f"({p}, {expected[p]})" in stdout  # the landmark in file indices, both sides
    assert "166 vertices (162 in the largest connected component, 4 dropped)" in stdout
    g = read_map(sym)  # method paper always has a symmetric map
    assert g.shape == (166,) and g[[0, 1, 2, 165]].tolist() == [-1, -1, -1, -1]
    assert g[3:-1].min() >= 3 and g[3:-1].max() <= 164  # kept target vertices only
    assert png.read_bytes()[:8] == PNG_MAGIC


def test_largest_component_given_pair_and_workers(pieces_pair, monkeypatch):
    # Q in target file indices; in-process eigensolves give the same map as the workers
    # (which solve the largest piece found before torch is imported), and the workers'
    # eigenpairs are used, not dropped as another mesh's
    import torchheat.matching

    src, tgt, expected, d = pieces_pair
    given = []
    prepare = torchheat.matching.prepare

    def spy(mesh, *args, eigenpairs=None, **kw):
        given.append(None if eigenpairs is None else eigenpairs[1].shape)
        return prepare(mesh, *args, eigenpairs=eigenpairs, **kw)

    monkeypatch.setattr(torchheat.matching, "prepare", spy)
    p = 3 + 40
    maps = []
    for workers in ("0", "2"):
        out = d / f"pair_w{workers}.txt"
        rc = main(["match", str(src), str(tgt), "-o", str(out), "--largest-component",
                   "--landmark", str(p), str(expected[p]), "--method", "paper",
                   "--threads", "1", "--workers", workers])
        assert rc == 0
        maps.append(read_map(out))
    solved = (162, 100) if sys.platform.startswith("linux") else None  # forked workers
    assert given == [None, None, solved, solved]
    assert np.mean(maps[0] == expected) >= 0.99
    assert np.array_equal(maps[0], maps[1])


@pytest.mark.parametrize("landmark, phrase", [
    (["1"], "P=1 is on a piece dropped by --largest-component"),
    (["165"], "P=165 is on a piece dropped by --largest-component"),
    (["166"], "P=166 is out of range; the source has 166 vertices"),
    (["20", "2"], "Q=2 is on a piece dropped by --largest-component"),
])
def test_largest_component_landmark_on_dropped_piece(pieces_pair, capsys, landmark, phrase):
    src, tgt, _, d = pieces_pair
    out = d / "refused.txt"
    rc = main(["match", str(src), str(tgt), "-o", str(out), "--largest-component",
               "--landmark", *landmark])
    err = capsys.readouterr().err
    assert rc == 1 and len(err.strip().splitlines()) == 1, err
    assert phrase in err
    assert (tgt.name if len(landmark) == 2 else src.name) in err
    assert not out.exists()


def test_largest_component_symmetry(pieces_pair):
    src, _, _, d = pieces_pair
    out = d / "self_pieces.txt"
    assert main(["symmetry", str(src), "-o", str(out), "--largest-component",
                 "--threads", "1"]) == 0
    f = read_map(out)
    assert f.shape == (166,) and f[[0, 1, 2, 165]].tolist() == [-1, -1, -1, -1]
    assert f[3:-1].min() >= 3 and f[3:-1].max() <= 164


def test_help_documents_largest_component_and_minimum(capsys):
    from torchheat.eigen import DEFAULT_EIGENPAIRS

    for cmd in ("match", "symmetry"):
        with pytest.raises(SystemExit):
            main([cmd, "--help"])
        text = " ".join(capsys.readouterr().out.split())
        assert "--largest-component" in text and "-1 for the dropped vertices" in text
        if cmd == "match":  # the help's literal minimum is the pipeline's
            assert f"at least {DEFAULT_EIGENPAIRS} vertices" in text


# ------------------------------------------------------------------------ too small to match
def test_too_small_to_match(tmp_path, capsys):
    spot = str(DATA / "spot.obj")
    tri = tmp_path / "triangle.obj"
    tri.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    few = write_off(tmp_path / "grid99.off", *flat_grid(11, 9))  # 99 vertices
    ok = write_off(tmp_path / "grid100.off", *flat_grid(10, 10))  # 100: the minimum
    xs = np.linspace(0, 2 * np.pi, 61)[:-1]  # a band of two rings: every vertex on a boundary
    ring = np.stack([np.cos(xs), np.sin(xs), np.zeros(60)], 1)
    i, j = np.arange(60), (np.arange(60) + 1) % 60
    band = write_off(tmp_path / "band.off", np.vstack([ring, ring + [0, 0, 0.2]]),
                     np.vstack([np.stack([i, j, i + 60], 1), np.stack([j, j + 60, i + 60], 1)]))
    for args, bad, phrase in [
        ([tri, spot], tri, "3 vertices, too few to match"),
        ([spot, tri], tri, "3 vertices, too few to match"),
        ([few, spot], few, "99 vertices, too few to match"),
        ([band, spot], band, "no interior vertex (all 120 vertices lie on the boundary"),
    ]:
        out = tmp_path / "small.txt"
        rc = main(["match", *map(str, args), "-o", str(out), "--threads", "1"])
        err = capsys.readouterr().err
        assert rc == 1 and len(err.strip().splitlines()) == 1, err
        assert err.startswith(f"torchheat: error: {bad}: {phrase}"), err
        if "few" in phrase:
            assert "at least 100 vertices" in err
        assert not out.exists()
    out = tmp_path / "grid100.txt"
    assert main(["match", str(ok), spot, "-o", str(out), "--threads", "1"]) == 0
    f = read_map(out)
    assert f.shape == (100,) and f.min() >= 0 and f.max() < 2930
    assert main(["symmetry", str(tri), "-o", str(out)]) == 1
    assert "at least 100 vertices" in capsys.readouterr().err


# -------------------------------------------------------------------------------- warnings
def test_point_cloud_stderr_is_the_error_alone(tmp_path):
    # a point cloud used to print scipy's FutureWarning about int64 (from the eigensolve
    # worker, forked with the CLI's warning printer) before the error
    cloud = tmp_path / "cloud.obj"
    cloud.write_text("".join(f"v {x} {y} {z}\n" for x, y, z in np.random.default_rng(0)
                             .standard_normal((50, 3))))
    exe = Path(sys.executable).parent / "torchheat"
    cmd = [str(exe)] if exe.exists() else [sys.executable, "-m", "torchheat.cli"]
    res = subprocess.run([*cmd, "match", str(cloud), str(DATA / "spot.obj"), "-o",
                          str(tmp_path / "m.txt")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 1
    assert res.stderr.splitlines() == [
        f"torchheat: error: {cloud}: file has no faces (a point cloud?); a triangle mesh is "
        "required, reconstruct a surface first (e.g. Poisson / ball pivoting in MeshLab or "
        "Open3D)"
    ]
    assert "arning" not in res.stderr and "int64" not in res.stderr


def test_cli_prints_each_warning_once(tmp_path, monkeypatch, capsys):
    # a warning repeated by later loads (a batch reads one target file for each of its pairs)
    # is printed once per command, and again by the next command
    import warnings

    import torchheat.meshio
    from torchheat.mesh import MeshWarning

    read = torchheat.meshio.read_arrays

    def noisy(path):
        for _ in range(3):  # as three loads of one file would
            warnings.warn("shared.off: 12 non-manifold edges", MeshWarning, stacklevel=1)
        return read(path)

    monkeypatch.setattr(torchheat.meshio, "read_arrays", noisy)
    cloud = tmp_path / "cloud.obj"
    cloud.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    for _ in range(2):
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            rc = main(["match", str(cloud), str(cloud), "-o", str(tmp_path / "m.txt")])
        assert rc == 1
        lines = capsys.readouterr().err.splitlines()
        assert lines[0] == "torchheat: warning: shared.off: 12 non-manifold edges"
        assert len(lines) == 2 and lines[1].startswith(f"torchheat: error: {cloud}: file has no")


def test_cli_prints_own_warnings_only(tmp_path, monkeypatch, capsys):
    # main() prints torchheat's warnings (one line each) and drops the libraries' ones
    import warnings

    import torchheat.meshio
    from torchheat.mesh import MeshWarning

    read = torchheat.meshio.read_arrays

    def noisy(path):
        warnings.warn("Input has data type int64, but the output ...", FutureWarning,
                      stacklevel=1)
        warnings.warn("Sparse CSR tensor support is in beta state", UserWarning, stacklevel=1)
        warnings.warn(f"{path}: 1 non-manifold edge\n (shared by more than two faces)",
                      MeshWarning, stacklevel=1)
        return read(path)

    monkeypatch.setattr(torchheat.meshio, "read_arrays", noisy)
    cloud = tmp_path / "cloud.obj"
    cloud.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        rc = main(["match", str(cloud), str(cloud), "-o", str(tmp_path / "m.txt")])
    assert rc == 1
    lines = capsys.readouterr().err.splitlines()
    # the reader refuses the first file (no faces) right after its warning
    assert lines[0] == (f"torchheat: warning: {cloud}: 1 non-manifold edge (shared by more "
                        "than two faces)")
    assert len(lines) == 2 and lines[1].startswith(f"torchheat: error: {cloud}: file has no")


def test_cli_turns_an_inside_out_target_and_reports_it(tmp_path, capsys):
    import json

    from test_matching import mirror_mesh, mirror_permutation, moved_copy

    V, F = mirror_mesh(3)
    mp = mirror_permutation(V)
    W, G, perm = moved_copy(V, F, seed=4)
    a = write_off(tmp_path / "a.off", V, F)
    b = write_off(tmp_path / "b_inside_out.off", W, G[:, [0, 2, 1]])
    out, rep = tmp_path / "m.txt", tmp_path / "r.json"
    assert main(["match", str(a), str(b), "-o", str(out), "--report", str(rep),
                 "--threads", "1"]) == 0
    assert "wound inside out" in capsys.readouterr().out
    f = np.loadtxt(out, dtype=np.int64)
    assert np.mean(f == perm) > 0.95 and np.mean(f == perm[mp]) < 0.2  # not the mirror map
    r = json.loads(rep.read_text())
    assert r["repairs"]["target"] == {"flipped_faces": len(G), "turned_outward": True,
                                      "dropped_vertices": 0}
    assert r["repairs"]["source"]["turned_outward"] is False
    import torchheat  # the report says where it was computed

    assert r["provenance"]["torchheat"] == torchheat.__version__ == r["version"]
    assert r["provenance"]["numpy"] == np.__version__ and r["provenance"]["cpus"] >= 1


def test_check_reports_what_loading_finds(pair, tmp_path, capsys):
    import json

    from torchheat import Mesh

    # torchheat check: matchable or why not, topology, repairs, warnings; status 1 if refused
    src, _, _, _ = pair
    V, F = generic_sphere(3)
    holed = write_off(tmp_path / "holed.off", V, F[1:])  # one face removed: a hole
    flipped = F.copy()
    flipped[:7] = flipped[:7, ::-1]
    turned = write_off(tmp_path / "turned.off", V, flipped)
    two = write_off(tmp_path / "two.off", np.vstack([V, V + 5.0]),
                    np.vstack([F, F + len(V)]))
    assert main(["check", str(src), str(holed), str(turned)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == (f"{src}: ok: 642 vertices, 1280 faces, closed, genus 0; area "
                      f"{Mesh(V, F).area():.4g}, diagonal {Mesh(V, F).bbox_diagonal():.4g}; "
                      "repairs: none")
    assert "1279 faces, 1 boundary loop (3 vertices), genus 0" in out[1]
    assert "7 faces reversed" in out[2]
    assert out[3] == "3 files: 3 can be matched, 0 refused, 0 with warnings"
    assert main(["check", str(two), "--json"]) == 1
    rep = json.loads(capsys.readouterr().out)
    assert rep[0]["ok"] is False and "2 connected components" in rep[0]["error"]
    assert main(["check", str(two), "--largest-component", "--json"]) == 0
    rep = json.loads(capsys.readouterr().out)[0]
    assert rep["ok"] and rep["repairs"]["dropped_vertices"] == 642 and rep["genus"] == 0
    # a torus: genus 1, from the Euler characteristic
    import trimesh

    tor = trimesh.creation.torus(1.0, 0.4)
    p = write_off(tmp_path / "torus.off", np.asarray(tor.vertices), np.asarray(tor.faces))
    assert main(["check", str(p), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)[0]["genus"] == 1
    # two holes touching at a vertex: pinched, no genus (the Euler count read genus -1 or 1
    # on SHREC'16 pieces with such vertices)
    a = 0
    at = np.flatnonzero((F == F[a, 0]).any(axis=1))  # the faces around vertex F[a, 0]
    b = next(int(f) for f in at if len(set(F[f]) & set(F[a])) == 1)
    pinch = write_off(tmp_path / "pinch.off", V, np.delete(F, [a, b], axis=0))
    assert main(["check", str(pinch)]) == 0
    line = capsys.readouterr().out
    assert "2 boundary loops" in line or "1 boundary loop" in line
    assert "1 pinched vertex (holes touching: no genus)" in line
