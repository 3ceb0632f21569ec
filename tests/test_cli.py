"""Command line interface (torchheat.cli) and colour-transfer pictures (torchheat.viz)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import generic_sphere

from torchheat.cli import main

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def write_off(path: Path, V: np.ndarray, F: np.ndarray, *, raw_vertices: list[str] | None = None):
    lines = ["OFF", f"{len(V)} {len(F)} 0"]
    lines += raw_vertices if raw_vertices is not None else [
        f"{x:.17g} {y:.17g} {z:.17g}" for x, y, z in V
    ]
    lines += [f"3 {a} {b} {c}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")
    return path


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
    assert not [p for p in os.listdir(d) if p.endswith(".tmp")]  # no temp files left


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
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


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
    assert not [p for p in os.listdir(tmp_path) if p.endswith(".tmp")]


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
