"""Fuzzed mesh files: every input ends in a clean MeshError or in a mesh that validates.

Property-based tests (hypothesis) over the OFF, OBJ and PLY (ASCII) readers of
:mod:`torchheat.meshio`: truncations, random bytes, wrong header counts, odd numbers (``nan``,
``inf``, ``1e400``, ``-1``, words), duplicated / deleted / swapped / shifted lines, repeated
corners and indices out of range, on small meshes of triangles, quads and a non-convex
hexagon; also binary PLY (header and byte mutations), binary STL and GLB (random bytes) and
:func:`~torchheat.meshio.triangulate_polygons` on arbitrary corner lists. Each case must give
either a :class:`~torchheat.meshio.MeshError` or arrays ``(V, F)`` that
:class:`~torchheat.mesh.Mesh` accepts or refuses with a ``MeshError``: never another exception
type, never a hang (hypothesis' ``deadline`` bounds each case). A last test feeds mutated OFF
files to ``torchheat match`` in-process.
"""

from __future__ import annotations

import os
import re
import struct
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchheat.mesh import Mesh
from torchheat.meshio import MeshError, read_arrays, triangulate_polygons

#: TORCHHEAT_FUZZ_SCALE=20 runs 20x more (random, not derandomized) cases: a bug hunt
_SCALE = int(os.environ.get("TORCHHEAT_FUZZ_SCALE", "1"))


def fuzz(max_examples: int, deadline: int | None = 2000) -> settings:
    """Settings of a fuzz test: few, reproducible cases (a few seconds in all)."""
    return settings(
        max_examples=max_examples * _SCALE,
        deadline=deadline,  # ms per case: a reader that hangs fails here
        derandomize=_SCALE == 1,  # the same cases on every run (CI stays reproducible)
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
        database=None,
    )


# ------------------------------------------------------------------ small meshes
def cube_quads() -> tuple[np.ndarray, list[list[int]]]:
    """A unit cube of 6 quads (8 vertices)."""
    V = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    F = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    return V, F


def mixed_polygons() -> tuple[np.ndarray, list[list[int]]]:
    """A pyramid over an L-shaped hexagon: six triangles and a non-convex hexagon."""
    base = [[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]]
    V = np.array(base + [[0.8, 0.8, 1.5]], dtype=float)
    F = [[5, 4, 3, 2, 1, 0]] + [[i, (i + 1) % 6, 6] for i in range(6)]
    return V, F


def tetrahedron() -> tuple[np.ndarray, list[list[int]]]:
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    return V, [[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]]


MESHES = {"tetra": tetrahedron(), "cube": cube_quads(), "mixed": mixed_polygons()}


def _num(x: float) -> str:
    return repr(float(x))


def off_text(V, F) -> str:
    rows = ["OFF", f"{len(V)} {len(F)} 0"]
    rows += [" ".join(map(_num, v)) for v in V]
    rows += [f"{len(f)} " + " ".join(map(str, f)) for f in F]
    return "\n".join(rows) + "\n"


def obj_text(V, F) -> str:
    rows = ["# fuzz", "o thing"] + ["v " + " ".join(map(_num, v)) for v in V]
    rows += ["vt 0 0", "vn 0 0 1"]
    rows += ["f " + " ".join(f"{i + 1}/1/1" for i in f) for f in F]
    return "\n".join(rows) + "\n"


def ply_text(V, F) -> str:
    head = [
        "ply", "format ascii 1.0", "comment fuzz", f"element vertex {len(V)}",
        "property float x", "property float y", "property float z",
        f"element face {len(F)}", "property list uchar int vertex_indices", "end_header",
    ]
    rows = [" ".join(map(_num, v)) for v in V] + [f"{len(f)} " + " ".join(map(str, f)) for f in F]
    return "\n".join(head + rows) + "\n"


def ply_binary(V, F) -> bytes:
    head = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode()
    body = b"".join(struct.pack("<3f", *v) for v in V)
    body += b"".join(struct.pack(f"<B{len(f)}i", len(f), *f) for f in F)
    return head + body


WRITERS = {".off": off_text, ".obj": obj_text, ".ply": ply_text}

ODD_TOKENS = [
    "nan", "inf", "-inf", "1e400", "-1e400", "1e-400", "1e39", "-3.5e38", "-1", "0", "-0",
    "1.5", "foo", "",
    "99999999999999999999", "-99999999999999999999", "3", "4", "1e3", "0x10", "+2", "1/2/3",
    "//", "#", "\x00", "é", "١",
]


# ------------------------------------------------------------------ mutations
@st.composite
def mutated(draw, text: str) -> str:
    """``text`` after a few random line- and token-level mutations."""
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        op = draw(st.sampled_from(
            ["token", "token", "dup", "del", "swap", "truncate", "corner", "count", "insert",
             "shift"]
        ))
        if not lines:
            break
        i = draw(st.integers(0, len(lines) - 1))
        toks = lines[i].split(" ")
        if op == "token":  # any token of the file, uniformly (faces are most of them)
            where = [(a, b) for a, ln in enumerate(lines) for b in range(len(ln.split(" ")))]
            i, j = draw(st.sampled_from(where))
            toks = lines[i].split(" ")
            toks[j] = draw(st.sampled_from(ODD_TOKENS) | st.integers(-3, 12).map(str))
            lines[i] = " ".join(toks)
        elif op == "dup":
            lines.insert(i, lines[i])
        elif op == "del":
            del lines[i]
        elif op == "swap":
            k = draw(st.integers(0, len(lines) - 1))
            lines[i], lines[k] = lines[k], lines[i]
        elif op == "truncate":
            cut = draw(st.integers(0, len(lines[i])))
            lines = lines[:i] + [lines[i][:cut]]
        elif op == "corner" and len(toks) > 2:  # repeat one corner of a face in another slot
            a, b = draw(st.integers(1, len(toks) - 1)), draw(st.integers(1, len(toks) - 1))
            toks[b] = toks[a]
            lines[i] = " ".join(toks)
        elif op == "count":  # a wrong count: header numbers, per-face counts
            nums = [j for j, t in enumerate(toks) if re.fullmatch(r"-?\d+", t)]
            if nums:
                j = draw(st.sampled_from(nums))
                toks[j] = str(draw(st.integers(-2, 40) | st.sampled_from([10**9, 2**31, 2**64])))
                lines[i] = " ".join(toks)
        elif op == "shift" and i + 1 < len(lines) and len(toks) > 1:  # a number moves down
            lines[i] = " ".join(toks[:-1])
            lines[i + 1] = lines[i + 1] + " " + toks[-1]
        elif op == "insert":
            lines.insert(i, draw(st.text(alphabet="0123456789 .-efnaiv/#\t", max_size=12)))
    return "\n".join(lines) + draw(st.sampled_from(["\n", "", "\r\n", "\n\n"]))


def check_outcome(path: Path) -> str:
    """Read ``path`` and validate it: 'error' (clean MeshError) or 'ok'; anything else raises."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # readers warn nothing (the CLI would print it)
            V, F = read_arrays(path)
    except MeshError as err:
        assert str(err).startswith(str(path)), err
        return "error"
    assert isinstance(V, np.ndarray) and V.dtype == np.float64 and V.ndim == 2
    assert V.shape[1] == 3
    assert isinstance(F, np.ndarray) and F.dtype == np.int64 and F.ndim == 2
    assert F.shape[1] == 3
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            Mesh(V, F, name=str(path))
    except MeshError as err:
        assert str(err).startswith(str(path)), err
        return "error"
    return "ok"


# ------------------------------------------------------------------ reader properties
@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
@pytest.mark.parametrize("mesh", sorted(MESHES))
def test_unmutated_meshes_read(tmp_path, ext, mesh):
    V, F = MESHES[mesh]
    path = tmp_path / f"{mesh}{ext}"
    path.write_text(WRITERS[ext](V, F))
    assert check_outcome(path) == "ok"


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
@fuzz(120)
@given(data=st.data())
def test_mutated_text_files(tmp_path, ext, data):
    V, F = MESHES[data.draw(st.sampled_from(sorted(MESHES)))]
    text = data.draw(mutated(WRITERS[ext](V, F)))
    path = tmp_path / f"fuzz{ext}"
    path.write_bytes(text.encode("utf-8", errors="surrogateescape"))
    check_outcome(path)


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
@fuzz(60)
@given(data=st.data())
def test_truncated_files(tmp_path, ext, data):
    V, F = MESHES[data.draw(st.sampled_from(sorted(MESHES)))]
    raw = WRITERS[ext](V, F).encode()
    path = tmp_path / f"cut{ext}"
    path.write_bytes(raw[: data.draw(st.integers(0, len(raw)))])
    check_outcome(path)


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply", ".stl", ".glb"])
@fuzz(40)
@given(blob=st.binary(max_size=300))
def test_random_bytes(tmp_path, ext, blob):
    path = tmp_path / f"bytes{ext}"
    path.write_bytes(blob)
    check_outcome(path)


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
@fuzz(40)
@given(data=st.data())
def test_header_then_random_bytes(tmp_path, ext, data):
    V, F = MESHES["cube"]
    raw = WRITERS[ext](V, F).encode()
    cut = data.draw(st.integers(0, len(raw)))
    path = tmp_path / f"tail{ext}"
    path.write_bytes(raw[:cut] + data.draw(st.binary(max_size=60)))
    check_outcome(path)


PLY_HEADER_TOKENS = ["char", "uchar", "short", "ushort", "int", "uint", "float", "double",
                     "list", "vertex", "face", "edge", "0", "1", "-1", "255", "4294967295",
                     "99999999999999999999", "x", "vertex_indices", "binary_big_endian"]


@fuzz(80)
@given(data=st.data())
def test_binary_ply_header_mutations(tmp_path, data):
    V, F = MESHES[data.draw(st.sampled_from(sorted(MESHES)))]
    raw = ply_binary(V, F)
    cut = raw.index(b"end_header")
    head = raw[:cut].decode().split("\n")
    for _ in range(data.draw(st.integers(1, 3))):
        i = data.draw(st.integers(1, len(head) - 1))
        toks = head[i].split(" ")
        toks[data.draw(st.integers(0, len(toks) - 1))] = data.draw(
            st.sampled_from(PLY_HEADER_TOKENS))
        head[i] = " ".join(toks)
    path = tmp_path / "head.ply"
    path.write_bytes("\n".join(head).encode() + raw[cut:])
    check_outcome(path)


@fuzz(80)
@given(data=st.data())
def test_binary_ply_byte_flips(tmp_path, data):
    V, F = MESHES[data.draw(st.sampled_from(sorted(MESHES)))]
    raw = bytearray(ply_binary(V, F))
    start = raw.index(b"end_header")
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(raw) - 1))
        if data.draw(st.booleans()) or pos < start:
            raw[pos] = data.draw(st.integers(0, 255))
        else:
            raw = raw[:pos]
            break
    path = tmp_path / "flip.ply"
    path.write_bytes(bytes(raw))
    check_outcome(path)


@fuzz(40)
@given(data=st.data())
def test_binary_stl_byte_flips(tmp_path, data):
    m = trimesh.creation.icosahedron()
    raw = bytearray(trimesh.exchange.stl.export_stl(m))
    for _ in range(data.draw(st.integers(1, 4))):
        pos = data.draw(st.integers(0, len(raw) - 1))
        raw[pos] = data.draw(st.integers(0, 255))
    if data.draw(st.booleans()):
        raw = raw[: data.draw(st.integers(0, len(raw)))]
    path = tmp_path / "flip.stl"
    path.write_bytes(bytes(raw))
    check_outcome(path)


@fuzz(150)
@given(
    points=st.lists(
        st.tuples(*[st.sampled_from([0.0, 1.0, -1.0, 0.5, 2.0, 1e-9, 1e9, np.nan, np.inf])
                    | st.floats(-10, 10)] * 3),
        min_size=3, max_size=9,
    ),
    data=st.data(),
)
def test_triangulate_any_polygon(points, data):
    """Any corner list (self-intersecting, repeated points, collinear, NaN): k - 2 triangles
    of its own corners, or a MeshError for repeated corners."""
    V = np.array(points, dtype=float)
    k = data.draw(st.integers(3, 12))
    poly = data.draw(st.lists(st.integers(0, len(V) - 1), min_size=k, max_size=k))
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            F = triangulate_polygons(V, [poly])
    except MeshError as err:
        assert "repeats vertices" in str(err)
        return
    assert F.shape[1] == 3 and set(F.ravel()) <= set(poly)
    assert F.shape[0] in (k - 2, len(set(poly)) - 2) or k == 3


# ------------------------------------------------------------------ the command line
def test_cli_on_mutated_off_files(tmp_path, capsys):
    """~60 mutated OFF files of a 162-vertex mesh through ``torchheat match``, in-process."""
    from conftest import generic_sphere

    from torchheat.cli import main

    V, F = generic_sphere(2, seed=4)
    good = tmp_path / "good.off"
    good.write_text(off_text(V, F))
    text = good.read_text()
    cases = []

    @fuzz(60, deadline=None)
    @given(mutated(text))
    def collect(t):
        cases.append(t)

    collect()
    t0 = time.perf_counter()
    outcomes = {"error": 0, "ok": 0}
    for k, t in enumerate(cases):
        src = tmp_path / f"case{k:03d}.off"
        src.write_bytes(t.encode("utf-8", errors="surrogateescape"))
        out = tmp_path / f"case{k:03d}.txt"
        rc = main(["match", str(src), str(good), "-o", str(out), "--threads", "1"])
        err = capsys.readouterr().err
        assert "Traceback" not in err, err
        if rc != 0:
            lines = [ln for ln in err.splitlines() if not ln.startswith("torchheat: warning")]
            assert len(lines) == 1 and lines[0].startswith("torchheat: error: "), err
            assert src.name in lines[0], err
            assert not out.exists()
            outcomes["error"] += 1
        else:
            n_src = read_arrays(src)[0].shape[0]
            assert len(out.read_text().splitlines()) == n_src
            outcomes["ok"] += 1
    elapsed = time.perf_counter() - t0
    assert len(cases) >= 40
    assert elapsed < 45 * _SCALE, f"{elapsed:.1f} s for {len(cases)} cases {outcomes}"
