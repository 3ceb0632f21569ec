"""torchheat.meshio: file formats (STL, GLB/glTF, PLY, OFF, OBJ) and polygon triangulation.

Checked against independent references: meshes written by trimesh, areas by the shoelace
formula, triangle sets compared by coordinates, and a quad version of a bundled mesh.
"""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import numpy as np
import pytest
import trimesh
from conftest import DATA, generic_sphere, write_off
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from torchheat.mesh import Mesh, load_mesh
from torchheat.meshio import (
    FORMATS_HELP,
    MERGED_FORMATS,
    ORDER_KEEPING_FORMATS,
    SUPPORTED_FORMATS,
    MeshError,
    read_arrays,
    triangulate_polygons,
)


# ------------------------------------------------------------------ helpers
def write(path: Path, content: str | bytes) -> Path:
    if isinstance(content, bytes):
        path.write_bytes(content)
    else:
        path.write_text(content)
    return path


def canonical_triangles(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Triangles as rows of 9 coordinates, each rotated to start at its smallest corner
    (orientation kept), rows sorted: equal for equal triangle sets whatever the numbering."""
    T = np.asarray(V)[np.asarray(F)]  # [m, 3, 3]
    first = np.array([min(range(3), key=lambda i: tuple(t[i])) for t in T])
    T = np.stack([np.roll(t, -f, axis=0) for t, f in zip(T, first, strict=True)])
    rows = T.reshape(len(T), 9)
    return rows[np.lexsort(rows.T[::-1])]


def first_appearance(points: np.ndarray) -> np.ndarray:
    """Distinct rows of ``points`` in order of first appearance (a plain dict, no numpy)."""
    seen: dict[tuple[float, ...], None] = {}
    for p in points:
        seen.setdefault(tuple(float(x) + 0.0 for x in p), None)
    return np.array(list(seen))


def signed_areas(V: np.ndarray, F: np.ndarray, normal: np.ndarray) -> np.ndarray:
    V = np.asarray(V, dtype=float)
    T = V[np.asarray(F)]
    return 0.5 * np.cross(T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]) @ normal


def shoelace(P2: np.ndarray) -> float:
    x, y = P2[:, 0], P2[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def assert_valid_triangulation(V, poly, tris, normal, area):
    """``tris`` triangulate the simple polygon ``poly``: k - 2 triangles of its corners, all
    of positive area relative to ``normal``, summing to ``area``, every polygon side used once
    in its direction and every diagonal twice in opposite directions."""
    k = len(poly)
    tris = np.asarray(tris)
    assert tris.shape == (k - 2, 3)
    assert set(tris.ravel()) <= set(poly)
    s = signed_areas(V, tris, normal)
    assert (s > 1e-9 * area).all(), s
    assert s.sum() == pytest.approx(area, rel=1e-9)
    half = [(int(t[i]), int(t[(i + 1) % 3])) for t in tris for i in range(3)]
    sides = {(poly[i], poly[(i + 1) % k]) for i in range(k)}
    for e in half:
        assert half.count(e) == 1, e
        assert e in sides or (e[1], e[0]) in half, e
    assert sides <= set(half)


def obj_text(V, polys, corner="{i}") -> str:
    rows = ["v " + " ".join(repr(float(x)) for x in v) for v in np.asarray(V)]
    rows += ["vt 0 0", "vn 0 0 1"]
    rows += ["f " + " ".join(corner.format(i=i + 1) for i in p) for p in polys]
    return "\n".join(rows) + "\n"


def off_text(V, polys, colour: str = "") -> str:
    rows = ["OFF", f"{len(V)} {len(polys)} 0"] + [" ".join(map(repr, map(float, v))) for v in V]
    rows += [f"{len(p)} " + " ".join(map(str, p)) + colour for p in polys]
    return "\n".join(rows) + "\n"


def ply_text(V, polys, name: str = "vertex_indices") -> str:
    head = [
        "ply", "format ascii 1.0", "comment polygons", "obj_info test",
        f"element vertex {len(V)}", "property double x", "property double y",
        "property double z", f"element face {len(polys)}",
        f"property list uchar int {name}", "end_header",
    ]
    rows = [" ".join(map(repr, map(float, v))) for v in V]
    rows += [f"{len(p)} " + " ".join(map(str, p)) for p in polys]
    return "\n".join(head + rows) + "\n"


def quad_grid(nx: int = 5, ny: int = 4):
    """A planar grid with uneven spacing: vertices and quads (counter-clockwise about +z)."""
    xs = np.cumsum(np.r_[0.0, np.linspace(0.5, 1.5, nx - 1)])
    ys = np.cumsum(np.r_[0.0, np.linspace(1.2, 0.4, ny - 1)])
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    quads = np.stack(
        [idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()],
        axis=1,
    )
    return V, quads, float(xs[-1] * ys[-1])


def merge_into_quads(F: np.ndarray) -> list[list[int]]:
    """Merge pairs of adjacent triangles into quads (greedy, in face order); leftovers stay
    triangles. Triangles (u, v, a) and (v, u, b) become the quad (u, b, v, a)."""
    owner: dict[tuple[int, int], int] = {}
    for f, (a, b, c) in enumerate(F):
        for e in ((a, b), (b, c), (c, a)):
            owner[(int(e[0]), int(e[1]))] = f
    used = np.zeros(len(F), dtype=bool)
    polys: list[list[int]] = []
    for f, tri in enumerate(F):
        if used[f]:
            continue
        used[f] = True
        for i in range(3):
            u, v, a = int(tri[i]), int(tri[(i + 1) % 3]), int(tri[(i + 2) % 3])
            g = owner.get((v, u))
            if g is not None and not used[g]:
                b = next(int(x) for x in F[g] if x != u and x != v)
                used[g] = True
                polys.append([u, b, v, a])
                break
        else:
            polys.append([int(x) for x in tri])
    return polys


# ------------------------------------------------------------------ constants
def test_format_lists():
    assert set(SUPPORTED_FORMATS) == set(ORDER_KEEPING_FORMATS) | set(MERGED_FORMATS)
    assert not set(ORDER_KEEPING_FORMATS) & set(MERGED_FORMATS)
    assert {".off", ".obj", ".ply"} == set(ORDER_KEEPING_FORMATS)
    assert {".stl", ".glb", ".gltf"} == set(MERGED_FORMATS)
    assert "\n" not in FORMATS_HELP and "STL" in FORMATS_HELP and "merged" in FORMATS_HELP
    assert len(FORMATS_HELP) < 200


# ------------------------------------------------------------------ STL
@pytest.mark.parametrize("encoding", ["binary", "ascii"])
def test_stl_round_trip_merges_the_soup(tmp_path, encoding):
    V, F = generic_sphere(2, seed=2)
    m = trimesh.Trimesh(V, F, process=False)
    path = tmp_path / f"sphere_{encoding}.STL"  # the extension is case-insensitive
    if encoding == "binary":
        write(path, trimesh.exchange.stl.export_stl(m))
        ref = V.astype(np.float32).astype(np.float64)  # binary STL stores float32
    else:
        write(path, trimesh.exchange.stl.export_stl_ascii(m))
        ref = V  # trimesh writes repr() digits: exact
    V2, F2 = read_arrays(path)
    assert V2.shape == V.shape  # every duplicate merged, nothing else
    np.testing.assert_array_equal(canonical_triangles(V2, F2), canonical_triangles(ref, F))
    # vertex order: first appearance in the triangle soup (first triangle's corners first)
    np.testing.assert_array_equal(V2, first_appearance(ref[F].reshape(-1, 3)))
    np.testing.assert_array_equal(V2[F2], ref[F])  # faces kept in file order
    mesh = load_mesh(path)  # a closed, valid mesh again
    assert mesh.boundary_edges().shape[0] == 0


def test_stl_merges_signed_zero_and_concatenates_solids(tmp_path):
    def facet(*corners):
        rows = "\n".join(f"      vertex {c}" for c in corners)
        return f"  facet normal 0 0 0\n    outer loop\n{rows}\n    endloop\n  endfacet\n"

    text = (
        "solid a\n" + facet("0 0 0", "1 0 0", "0 1 0") + facet("-0.0 0 0", "0 1 0", "0 0 1")
        + "endsolid a\nsolid b\n" + facet("5 5 5", "6 5 5", "5 6 5") + "endsolid b\n"
    )
    V, F = read_arrays(write(tmp_path / "two.stl", text))
    assert V.tolist() == [
        [0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [5, 5, 5], [6, 5, 5], [5, 6, 5]
    ]
    assert F.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6]]
    with pytest.raises(MeshError, match="2 connected components"):
        load_mesh(tmp_path / "two.stl")


@pytest.mark.parametrize("content", [b"", b"solid empty\nendsolid empty\n", b"\0" * 84])
def test_stl_without_triangles(tmp_path, content):
    path = write(tmp_path / "empty.stl", content)
    with pytest.raises(MeshError, match=r"^.*empty\.stl: "):
        read_arrays(path)


# ------------------------------------------------------------------ GLB / glTF
def test_glb_single_mesh_keeps_its_order(tmp_path):
    V, F = generic_sphere(2, seed=3)
    path = tmp_path / "sphere.glb"
    trimesh.Trimesh(V, F, process=False).export(path)
    V2, F2 = read_arrays(path)
    np.testing.assert_array_equal(V2, V.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(F2, F)


@pytest.mark.parametrize("ext", [".glb", ".gltf"])
def test_gltf_scene_parts_are_placed_concatenated_and_merged(tmp_path, ext):
    # a sphere cut in two meshes, each with its own copy of the seam vertices, the second
    # stored moved by -t and placed back by its node transform
    V, F = generic_sphere(2, seed=5)
    V = np.round(V * 1024) / 1024 + 0.25  # V and V - t exact in float32: seams match exactly
    t = np.array([1.0, 2.0, -0.5])
    top = V[F].mean(axis=1)[:, 2] > 0
    scene = trimesh.Scene()
    for name, sel, shift in (("top", top, np.zeros(3)), ("bottom", ~top, t)):
        used, Fp = np.unique(F[sel], return_inverse=True)
        part = trimesh.Trimesh(V[used] - shift, Fp.reshape(-1, 3), process=False)
        scene.add_geometry(part, node_name=name, geom_name=name,
                           transform=trimesh.transformations.translation_matrix(shift))
    if ext == ".glb":
        write(tmp_path / "parts.glb", trimesh.exchange.gltf.export_glb(scene))
    else:  # .gltf with its buffers in separate files next to it
        for name, data in trimesh.exchange.gltf.export_gltf(scene).items():
            write(tmp_path / ("parts.gltf" if name.endswith(".gltf") else name), data)
    V2, F2 = read_arrays(tmp_path / f"parts{ext}")
    assert V2.shape == V.shape  # the seam copies merged back
    np.testing.assert_allclose(
        canonical_triangles(V2, F2), canonical_triangles(V, F), rtol=0, atol=1e-6
    )
    mesh = Mesh(V2, F2, name="parts")  # one closed component
    assert mesh.boundary_edges().shape[0] == 0


def test_glb_without_triangles(tmp_path):
    path = tmp_path / "points.glb"
    trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(path)
    with pytest.raises(MeshError, match="no faces"):
        read_arrays(path)
    with pytest.raises(MeshError, match="could not read the file as GLB"):
        read_arrays(write(tmp_path / "junk.glb", b"glTF\x02\x00\x00\x00garbage"))


# ------------------------------------------------------------------ PLY
def test_binary_ply_by_trimesh_keeps_order(tmp_path):
    V, F = generic_sphere(2, seed=6)
    perm = np.random.default_rng(1).permutation(len(V))
    V, F = V[perm], np.argsort(perm)[F]
    path = tmp_path / "sphere.ply"
    trimesh.Trimesh(V, F, process=False).export(path)  # binary little endian, float32
    V2, F2 = read_arrays(path)
    np.testing.assert_array_equal(V2, V.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(F2, F)
    # the same as ASCII, up to trimesh's 8 printed digits
    path = tmp_path / "sphere_ascii.ply"
    trimesh.Trimesh(V, F, process=False).export(path, encoding="ascii")
    V3, F3 = read_arrays(path)
    np.testing.assert_allclose(V3, V2, rtol=2e-7, atol=1e-8)
    np.testing.assert_array_equal(F3, F2)


def _big_endian_ply(V, polys, uniform: bool) -> bytes:
    """Big-endian PLY with extra vertex properties, an 'edge' element, uint list counts and a
    scalar after the face list."""
    head = (
        "ply\nformat binary_big_endian 1.0\ncomment made by hand\n"
        f"element vertex {len(V)}\nproperty double x\nproperty float nx\nproperty double y\n"
        "property double z\nproperty uchar red\n"
        "element edge 2\nproperty int vertex1\nproperty int vertex2\n"
        f"element face {len(polys)}\nproperty list uint int vertex_index\n"
        "property float quality\nend_header\n"
    )
    body = b"".join(struct.pack(">dfddB", v[0], 0.5, v[1], v[2], 7) for v in V)
    body += struct.pack(">ii", 0, 1) + struct.pack(">ii", 1, 2)
    body += b"".join(struct.pack(f">I{len(p)}if", len(p), *p, 1.0) for p in polys)
    assert uniform == (len({len(p) for p in polys}) == 1)
    return head.encode() + body


@pytest.mark.parametrize("uniform", [True, False])
def test_binary_big_endian_ply_with_extra_properties(tmp_path, uniform):
    V, quads, area = quad_grid(4, 3)
    polys = [list(q) for q in quads]
    if not uniform:
        polys[0:1] = [[polys[0][0], polys[0][1], polys[0][2]], [polys[0][0], polys[0][2],
                                                                 polys[0][3]]]
    V2, F2 = read_arrays(write(tmp_path / "be.ply", _big_endian_ply(V, polys, uniform)))
    np.testing.assert_array_equal(V2, V)
    assert F2.shape == (2 * len(quads), 3)
    assert signed_areas(V, F2, np.array([0, 0, 1.0])).sum() == pytest.approx(area)


def _tri_ply(count_type: str, count: int) -> bytes:
    head = (
        "ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
        "property float y\nproperty float z\nelement face 1\n"
        f"property list {count_type} int vertex_indices\nend_header\n"
    ).encode()
    code = {"uint": "I", "char": "b", "uchar": "B"}[count_type]
    body = struct.pack("<9f", 0, 0, 0, 1, 0, 0, 0, 1, 0)
    return head + body + struct.pack(f"<{code}3i", count, 0, 1, 2)


@pytest.mark.parametrize(
    ("raw", "phrase"),
    [
        (_tri_ply("uint", 2**32 - 1), "past the end of the file"),  # numpy refused the dtype
        (_tri_ply("char", -3), "negative length"),  # numpy refused the dtype
        (_tri_ply("uchar", 3)[:-5], "past the end of the file"),
        (_tri_ply("uchar", 3).replace(b"face 1", b"face 99999999999999"), "past the end"),
    ],
)
def test_binary_ply_bad_list_counts(tmp_path, raw, phrase):
    path = write(tmp_path / "counts.ply", raw)
    with pytest.raises(MeshError, match=phrase):
        read_arrays(path)
    assert read_arrays(write(tmp_path / "ok.ply", _tri_ply("uchar", 3)))[1].tolist() == [[0, 1, 2]]


@pytest.mark.parametrize(
    ("text", "phrase"),
    [
        ("ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n",
         "no x, y, z"),
        ("ply\nformat ascii 2.0x\nend_header\n", "could not read the file as PLY"),
        ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         "end_header\n0 0 0\n1 0 0\n0 1 0\n", "truncated"),
        ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         "end_header\n0 0 0\n1 0 0\n0 1 0\n3 0 1\n", "cannot parse face 0"),
        ("ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
         "property float y\nproperty float z\nelement face 1\n"
         "property list uchar int vertex_indices\nend_header\n" + "\0" * 30, "truncated"),
        ("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
         "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
         "end_header\n0 0 0\n1 0 0\n0 1 0\n4 0 1 2 1\n", "repeats vertices"),
    ],
)
def test_ply_errors(tmp_path, text, phrase):
    path = write(tmp_path / "bad.ply", text.encode("latin-1"))
    with pytest.raises(MeshError, match=phrase) as info:
        read_arrays(path)
    assert str(info.value).startswith(str(path))


# ------------------------------------------------------------------ OFF
def test_off_variants(tmp_path):
    V, quads, area = quad_grid(3, 3)
    polys = [list(q) for q in quads]
    ref = read_arrays(write(tmp_path / "plain.off", off_text(V, polys)))[1]
    # colours on faces, comments, counts on the header line
    text = off_text(V, polys, colour=" 255 0 0 0.5").replace("OFF\n", "# made by hand\nOFF ")
    V2, F2 = read_arrays(write(tmp_path / "colour.off", text))
    np.testing.assert_array_equal(V2, V)
    np.testing.assert_array_equal(F2, ref)
    # COFF: a colour per vertex; NOFF: normals
    lines = text.splitlines()
    lines[1] = "COFF " + lines[1][4:]
    for i in range(2, 2 + len(V)):
        lines[i] += " 0.1 0.2 0.3 1.0"
    V3, F3 = read_arrays(write(tmp_path / "coff.off", "\n".join(lines)))
    np.testing.assert_array_equal(V3, V)
    np.testing.assert_array_equal(F3, ref)
    assert signed_areas(V, ref, np.array([0, 0, 1.0])).sum() == pytest.approx(area)


@pytest.mark.parametrize(
    ("text", "phrase"),
    [
        ("OFF BINARY\n3 1 0\n", "binary OFF is not supported"),
        ("4OFF\n3 1 0\n0 0 0 0\n1 0 0 0\n0 1 0 0\n3 0 1 2\n", "4D or nD"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 2\n", "1 lines after the 3 vertices"),
        ("OFF\n3 2 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "declares 3 vertices and 2 faces"),
        ("OFF\n3 -1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n", "negative counts"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1\n3 0 1 2\n", "cannot parse vertex 2 on line 5"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n4 0 1 2\n", "cannot parse face 0 on line 6"),
        ("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 99999999999999999999999\n", "out of range"),
        ("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 7 3\n",
         "face 0 (line 7) has vertex indices out of range"),
        ("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 0 2\n", "face 0 (line 7) repeats"),
        ("OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 0 1\n", "face 0 (line 7) has 2 corners"),
        ("NOT AN OFF\n", "does not start with 'OFF'"),
        # a short and a long vertex line: the old fast reader shifted coordinates silently
        ("OFF\n3 1 0\n0 0 0 1\n1 0\n0 1 0\n3 0 1 2\n", "cannot parse vertex 1 on line 4"),
    ],
)
def test_off_errors(tmp_path, text, phrase):
    path = write(tmp_path / "bad.off", text)
    with pytest.raises(MeshError) as info:
        load_mesh(path)
    assert str(info.value).startswith(str(path))
    assert phrase in str(info.value)


# ------------------------------------------------------------------ polygons
def test_quad_grid_obj_gives_two_triangles_per_quad(tmp_path):
    V, quads, area = quad_grid()
    path = write(tmp_path / "grid.obj", obj_text(V, quads, corner="{i}/1/1"))
    V2, F2 = read_arrays(path)
    np.testing.assert_array_equal(V2, V)
    assert F2.shape == (2 * len(quads), 3)
    s = signed_areas(V2, F2, np.array([0.0, 0, 1]))
    assert (s > 0).all()
    assert s.sum() == pytest.approx(area, rel=1e-12)
    for q, pair in zip(quads, F2.reshape(-1, 2, 3), strict=True):  # each quad's own corners
        assert set(pair.ravel()) == set(q)
    mesh = load_mesh(path)
    assert mesh.n_vertices == len(V) and mesh.area() == pytest.approx(area)


def test_l_shape_and_comb_are_ear_cut(tmp_path):
    # L-shape (star-shaped from its inner corner only) and a comb (not star-shaped from any
    # corner, so only ear clipping can cut it), in a tilted plane, written clockwise in OBJ
    L = [[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]]
    comb = [[0, 0], [5, 0], [5, 3], [4, 3], [4, 1], [3, 1], [3, 3], [2, 3], [2, 1], [1, 1],
            [1, 3], [0, 3]]
    rot, _ = np.linalg.qr(np.random.default_rng(2).standard_normal((3, 3)))
    for name, P2 in (("L", np.array(L, float)), ("comb", np.array(comb, float))):
        V = np.c_[P2, np.zeros(len(P2))] @ rot.T + [3.0, -1.0, 2.0]
        poly = list(range(len(P2)))[::-1]  # clockwise seen from +n: normal is -n
        normal = -rot[:, 2]
        path = write(tmp_path / f"{name}.obj", obj_text(V, [poly]))
        V2, F2 = read_arrays(path)
        np.testing.assert_array_equal(V2, V)
        assert_valid_triangulation(V, poly, F2, normal, shoelace(P2))
    # a fan from the first corner would not do: it has a flipped triangle
    fan = [[1, 2, 3], [1, 3, 4], [1, 4, 5], [1, 5, 0]]
    assert (signed_areas(np.c_[L, np.zeros(6)], fan, np.array([0, 0, 1.0])) < 0).any()


def test_collinear_corners_and_saddle_quads():
    # a square with its side midpoints: a fan from corner 0 has zero-area triangles
    P = [[0, 0], [1, 0], [2, 0], [2, 1], [2, 2], [1, 2], [0, 2], [0, 1]]
    V = np.c_[np.array(P, float), np.zeros(8)]
    F = triangulate_polygons(V, [list(range(8))])
    assert_valid_triangulation(V, list(range(8)), F, np.array([0, 0, 1.0]), 4.0)
    # a non-planar (saddle) quad: both triangles face the side of its Newell normal
    V = np.array([[0, 0, 0], [1, 0, 1], [1, 1, 0], [0, 1, 1]], dtype=float)
    F = triangulate_polygons(V, [[0, 1, 2, 3]])
    assert (signed_areas(V, F, np.array([0, 0, 1.0])) > 0).all()
    # degenerate polygons are fanned: validation reports them
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]], dtype=float)
    assert triangulate_polygons(V, [[0, 1, 2, 3]]).tolist() == [[0, 1, 2], [0, 2, 3]]
    with pytest.raises(MeshError, match="degenerate"):
        Mesh(V, triangulate_polygons(V, [[0, 1, 2, 3]]))


@settings(max_examples=60, deadline=2000, derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow])
@given(
    k=st.integers(4, 24),
    seed=st.integers(0, 2**32 - 1),
    planar=st.booleans(),
)
def test_random_star_polygons_triangulate_validly(k, seed, planar):
    # star-shaped about their centre (not about a corner, in general): ear clipping's domain
    rng = np.random.default_rng(seed)
    gaps = rng.uniform(0.3, 1.0, k)
    angles = np.cumsum(gaps) / gaps.sum() * 2 * np.pi
    radii = rng.uniform(0.2, 1.0, k)
    P2 = np.c_[radii * np.cos(angles), radii * np.sin(angles)]
    rot, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    height = np.zeros(k) if planar else 1e-3 * rng.standard_normal(k)
    V = np.c_[P2, height] @ rot.T + rng.standard_normal(3)
    F = triangulate_polygons(V, [list(range(k))])
    if planar:
        assert_valid_triangulation(V, list(range(k)), F, rot[:, 2], shoelace(P2))
    else:  # slightly bent: positive areas about the Newell normal, one triangle per corner - 2
        N = 0.5 * np.cross(V, np.roll(V, -1, axis=0)).sum(axis=0)
        assert F.shape == (k - 2, 3)
        assert (signed_areas(V, F, N / np.linalg.norm(N)) > 0).all()


def test_mixed_polygons_same_in_obj_off_ply(tmp_path):
    # triangles, quads and a pentagon; OBJ with v/vt/vn corners and negative indices
    V = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0],
                  [0.5, 2, 0], [1.5, 2.5, 0], [2.5, 2, 0], [3, 1.5, 0]], dtype=float)
    polys = [[0, 1, 4, 3], [1, 2, 5], [1, 5, 4], [3, 4, 7, 6], [4, 5, 9, 8, 7]]
    rows = ["v " + " ".join(map(str, v)) for v in V] + ["vt 0 0", "vn 0 0 1"]
    rows += ["f 1/1/1 2/1/1 5/1/1 4/1/1", "f 2//1 3//1 6//1", "f -9/1 -5/1 -6/1",
             "f 4 5 8 7", "f -6/1/1 -5/1/1 -1/1/1 -2/1/1 -3/1/1"]
    F_obj = read_arrays(write(tmp_path / "mixed.obj", "\n".join(rows) + "\n"))[1]
    F_off = read_arrays(write(tmp_path / "mixed.off", off_text(V, polys)))[1]
    F_ply = read_arrays(write(tmp_path / "mixed.ply", ply_text(V, polys, "vertex_index")))[1]
    np.testing.assert_array_equal(F_obj, F_off)
    np.testing.assert_array_equal(F_ply, F_off)
    assert F_off.shape == (2 + 1 + 1 + 2 + 3, 3)
    assert F_off[2:4].tolist() == [[1, 2, 5], [1, 5, 4]]  # triangles untouched, in order
    s = signed_areas(V, F_off, np.array([0, 0, 1.0]))
    assert (s > 0).all()
    assert s.sum() == pytest.approx(sum(shoelace(V[p, :2]) for p in polys))


@pytest.mark.parametrize("fmt", ["obj", "off", "coff", "ply"])
def test_byte_order_mark_is_skipped(tmp_path, fmt):
    # Windows editors and some exporters start a text file with a UTF-8 BOM; it was read as
    # part of the first token: an OBJ lost its first vertex (every index shifted: "out of
    # range", or a wrong mesh with relative indices), OFF and PLY were refused
    V, F = generic_sphere(1)
    polys = F.tolist()
    if fmt == "obj":
        text = "".join(f"v {a!r} {b!r} {c!r}\n" for a, b, c in V.tolist())
        text += "".join(f"f {a - len(V)} {b - len(V)} {c - len(V)}\n" for a, b, c in F)
    elif fmt == "ply":
        text = ply_text(V, polys, "vertex_indices")
    else:
        text = off_text(V, polys)
        if fmt == "coff":
            rows = text.splitlines()
            rows[0] = "COFF"
            rows[2:2 + len(V)] = [r + " 200 100 50 255" for r in rows[2:2 + len(V)]]
            text = "\n".join(rows) + "\n"
    ext = "off" if fmt == "coff" else fmt
    plain = read_arrays(write(tmp_path / f"plain.{ext}", text))
    path = tmp_path / f"bom.{ext}"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    V2, F2 = read_arrays(path)
    np.testing.assert_array_equal(V2, plain[0])
    np.testing.assert_array_equal(F2, plain[1])
    np.testing.assert_allclose(V2, V, atol=1e-6)
    assert len(F2) == len(F)


def test_obj_line_continuation(tmp_path):
    # the OBJ spec lets a backslash at the end of a line continue it (long polygons)
    V, F = generic_sphere(1)
    plain = "".join(f"v {a!r} {b!r} {c!r}\n" for a, b, c in V.tolist())
    split = plain.replace(" ", " \\\n ", 1)  # the first 'v' line split after 'v'
    plain += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in F.tolist())
    split += "".join(f"f {a + 1} \\\r\n{b + 1} \\ \n {c + 1}\n" for a, b, c in F.tolist())
    Vp, Fp = read_arrays(write(tmp_path / "plain.obj", plain))
    Vs, Fs = read_arrays(write(tmp_path / "split.obj", split))
    np.testing.assert_array_equal(Vs, Vp)
    np.testing.assert_array_equal(Fs, Fp)
    np.testing.assert_array_equal(Fp, F)
    # a comment is not continued (it may end in a Windows path), and errors keep line numbers
    commented = "# exported from C:\\models\\\n" + plain
    np.testing.assert_array_equal(read_arrays(write(tmp_path / "c.obj", commented))[1], F)
    bad = "v 0 0 \\\n 0\nv 1 0 0\nv 0 1 0\nv 1 x 0\nf 1 2 3\n"
    with pytest.raises(MeshError, match="line 5"):
        read_arrays(write(tmp_path / "bad.obj", bad))


def test_repeated_last_corner_is_dropped(tmp_path):
    # '4 a b c c' (triangles written as degenerate quads by some exporters) is a triangle
    text = "OFF\n4 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 2\n4 0 2 3 0\n"
    V, F = read_arrays(write(tmp_path / "tri_as_quad.off", text))
    assert F.tolist() == [[0, 1, 2], [0, 2, 3]]


# ------------------------------------------------------------------ a real quad mesh
@pytest.fixture(scope="module")
def spot_quads(tmp_path_factory):
    V, F = read_arrays(DATA / "spot.obj")
    polys = merge_into_quads(F)
    n_quads = sum(len(p) == 4 for p in polys)
    assert n_quads > 0.9 * len(F) / 2
    path = tmp_path_factory.mktemp("quads") / "spot_quads.obj"
    rows = ["v " + " ".join(f"{x:.17g}" for x in v) for v in V]
    rows += ["f " + " ".join(f"{i + 1}//{i + 1}" for i in p) for p in polys]
    path.write_text("\n".join(rows) + "\n")
    return path, V, F, n_quads


def test_quad_dominant_spot_reads_back(spot_quads):
    path, V, F, n_quads = spot_quads
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no non-manifold edge, nothing
        mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.vertices.numpy(), V)
    assert mesh.n_faces == len(F)
    ref = Mesh(V, F)
    assert mesh.area() == pytest.approx(ref.area(), rel=1e-3)


def test_quad_dominant_spot_matches_one_line_per_vertex(spot_quads, tmp_path, capsys):
    from torchheat.cli import main

    path, V, _, _ = spot_quads
    out = tmp_path / "map.txt"
    rc = main(["match", str(path), str(DATA / "spot.obj"), "-o", str(out), "--threads", "1"])
    assert rc == 0, capsys.readouterr().err
    m = np.array(out.read_text().split(), dtype=np.int64)
    assert m.shape == (len(V),)
    assert m.min() >= 0 and m.max() < len(V)


def test_cli_matches_stl_to_glb(tmp_path, capsys):
    from torchheat.cli import main

    V, F = generic_sphere(2, seed=8)
    m = trimesh.Trimesh(V, F, process=False)
    write(tmp_path / "a.stl", trimesh.exchange.stl.export_stl(m))
    m.export(tmp_path / "b.glb")
    out = tmp_path / "map.txt"
    rc = main(["match", str(tmp_path / "a.stl"), str(tmp_path / "b.glb"), "-o", str(out),
               "--threads", "1"])
    assert rc == 0, capsys.readouterr().err
    Vs = read_arrays(tmp_path / "a.stl")[0]
    m = np.array(out.read_text().split(), dtype=np.int64)
    assert m.shape == (len(Vs),) == (len(V),)
    # same shape, STL numbering (first appearance) vs GLB numbering (file order): compare points
    Vb = read_arrays(tmp_path / "b.glb")[0]
    assert np.median(np.linalg.norm(Vb[m] - Vs, axis=1)) < 1e-6


@pytest.mark.parametrize("kind", ["gz", "bz2", "xz"])
def test_compressed_order_keeping_files(tmp_path, kind):
    # datasets ship meshes compressed (cat0.off.gz): read as the file inside, vertex order kept;
    # they were refused as an unsupported format '.gz'
    import bz2
    import gzip
    import lzma

    V, F = generic_sphere(2)
    plain = tmp_path / "ball.ply"
    trimesh.Trimesh(V, F, process=False).export(plain)  # binary PLY
    off = write_off(tmp_path / "ball.off", V, F)
    module = {"gz": gzip, "bz2": bz2, "xz": lzma}[kind]
    for src in (plain, off):
        packed = tmp_path / f"{src.name}.{kind.upper() if kind == 'gz' else kind}"
        packed.write_bytes(module.compress(src.read_bytes()))
        Vc, Fc = read_arrays(packed)
        Vp, Fp = read_arrays(src)
        assert np.array_equal(Vc, Vp) and np.array_equal(Fc, Fp) and np.allclose(Vc, V)
    bad = tmp_path / f"cut.off.{kind}"
    bad.write_bytes(module.compress(off.read_bytes())[:40])  # a truncated download
    with pytest.raises(MeshError, match=f"cut.off.{kind}: not a valid {kind} file"):
        read_arrays(bad)
    stl = tmp_path / f"ball.stl.{kind}"
    stl.write_bytes(module.compress(b"solid x\nendsolid x\n"))
    with pytest.raises(MeshError, match=r"a compressed \.stl is not read"):
        read_arrays(stl)
