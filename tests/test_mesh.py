"""Tests of torchheat.mesh: loading, validation errors, topology helpers."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp
import torch
import trimesh

from torchheat.mesh import Mesh, MeshError, MeshWarning, load_mesh

DATA = Path(__file__).resolve().parents[1] / "torchheat" / "data"
SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"

TRI_V = "0 0 0\n1 0 0\n0 1 0\n"
TETRA_V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TETRA_F = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


def write(tmp_path: Path, name: str, text: str | bytes) -> Path:
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text)
    return path


def off_text(V, F, header_same_line: bool = False) -> str:
    V, F = np.asarray(V), np.asarray(F)
    head = f"OFF {len(V)} {len(F)} 0\n" if header_same_line else f"OFF\n{len(V)} {len(F)} 0\n"
    rows = [" ".join(repr(float(x)) for x in v) for v in V]
    rows += [f"{len(f)} " + " ".join(str(int(i)) for i in f) for f in F]
    return head + "\n".join(rows) + "\n"


def obj_text(V, F) -> str:
    rows = ["v " + " ".join(repr(float(x)) for x in v) for v in np.asarray(V)]
    rows += ["f " + " ".join(str(int(i) + 1) for i in f) for f in np.asarray(F)]
    return "\n".join(rows) + "\n"


def ply_text(V, F) -> str:
    V, F = np.asarray(V), np.asarray(F)
    head = (
        "ply\nformat ascii 1.0\n"
        f"element vertex {len(V)}\nproperty double x\nproperty double y\nproperty double z\n"
        f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    rows = [" ".join(repr(float(x)) for x in v) for v in V]
    rows += [f"{len(f)} " + " ".join(str(int(i)) for i in f) for f in F]
    return head + "\n".join(rows) + "\n"


def write_mesh(tmp_path: Path, name: str, V, F) -> Path:
    fmt = Path(name).suffix.lower()
    text = {".off": off_text, ".obj": obj_text, ".ply": ply_text}[fmt](V, F)
    return write(tmp_path, name, text)


def assert_mesh_error(path: Path, *phrases: str, **kwargs) -> str:
    with pytest.raises(MeshError) as info:
        load_mesh(path, **kwargs)
    msg = str(info.value)
    assert isinstance(info.value, ValueError)
    assert msg.startswith(str(path)), msg
    for phrase in phrases:
        assert phrase in msg, msg
    return msg


def two_triangles_apart():
    V = np.array(
        [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]],
    )
    F = np.array([[0, 1, 2], [1, 3, 2], [4, 5, 6]])
    return V, F


# ------------------------------------------------------------------ file errors
def test_missing_file(tmp_path):
    path = tmp_path / "nope.off"
    assert_mesh_error(path, "no such file")


def test_directory(tmp_path):
    path = tmp_path / "dir.obj"
    path.mkdir()
    assert_mesh_error(path, "directory")


def test_unknown_extension(tmp_path):
    path = write(tmp_path, "tri.xyz", "0 0 0\n1 0 0\n")
    msg = assert_mesh_error(path, "unsupported mesh format", ".obj", ".off", ".ply", ".stl")
    assert "'.xyz'" in msg


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("garbled.off", "OFF\n3 1 0\n0 0 zz\n1 0\n"),
        ("truncated.off", "OFF\n4 2 0\n0 0 0\n1 0 0\n0 1 0\n"),
        ("binary.off", b"\x00\x01\x02garbage\xff\xfe\n"),
        ("empty.off", ""),
        (
            "garbled.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\nfoo\n",
        ),
    ],
)
def test_unreadable_off_ply(tmp_path, name, text):
    path = write(tmp_path, name, text)
    assert_mesh_error(path, "could not read the file")


def test_unreadable_obj(tmp_path):
    path = write(tmp_path, "binary.obj", b"\x00\x01\x02garbage\xff\xfe\n")
    assert_mesh_error(path, "no vertex ('v') or face ('f') lines")
    path = write(tmp_path, "badvertex.obj", "v 0 0 0\nv 1 zz 0\nv 0 1 0\nf 1 2 3\n")
    assert_mesh_error(path, "cannot parse vertex 1 on line 2")
    path = write(tmp_path, "shortvertex.obj", "v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n")
    assert_mesh_error(path, "cannot parse vertex 1")
    path = write(tmp_path, "badface.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 x 3\n")
    assert_mesh_error(path, "cannot parse the face indices")


@pytest.mark.parametrize(
    ("name", "text"),
    [
        ("points.off", "OFF\n3 0 0\n" + TRI_V),
        ("points.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\n"),
        (
            "points.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nend_header\n" + TRI_V,
        ),
    ],
)
def test_no_faces(tmp_path, name, text):
    path = write(tmp_path, name, text)
    assert_mesh_error(path, "no faces", "point cloud")


@pytest.mark.parametrize(
    ("name", "text", "n_faces"),
    [
        ("quad.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n", 2),
        (
            "mixed.off",
            "OFF\n5 2 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n2 2 0\n3 1 4 2\n4 0 1 2 3\n",
            3,
        ),
        ("quad.obj", "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n", 2),
        (
            "quad.ply",
            "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            "end_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n",
            2,
        ),
    ],
)
def test_polygon_faces_are_triangulated(tmp_path, name, text, n_faces):
    # polygons are cut into triangles (tests/test_meshio.py has the details); vertices kept
    mesh = load_mesh(write(tmp_path, name, text))
    assert mesh.n_faces == n_faces
    assert mesh.vertices[:4].tolist() == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    assert mesh.area() == pytest.approx(1.5 if name == "mixed.off" else 1.0)


def test_face_with_two_corners_reports_line(tmp_path):
    text = "# edge\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3\nf 1 3\n"
    path = write(tmp_path, "edge.obj", text)
    assert_mesh_error(path, "face 1 (line 7) has 2 corners", "at least three")


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
def test_nan_coordinates(tmp_path, ext):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    V[2, 1] = np.nan
    V[3, 0] = np.inf
    path = write_mesh(tmp_path, "nan" + ext, V, [[0, 1, 2], [1, 3, 2]])
    assert_mesh_error(path, "2 vertices with NaN/inf", "first: vertex 2")


@pytest.mark.parametrize(
    ("name", "text", "phrase"),
    [
        ("oob.off", "OFF\n3 1 0\n" + TRI_V + "3 0 1 5\n", "out of range"),
        ("neg.off", "OFF\n3 1 0\n" + TRI_V + "3 0 1 -1\n", "out of range"),
        ("oob.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", "out of range"),
        ("zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", "out of range"),
        ("negobj.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n", "out of range"),
        (
            "oob.ply",
            "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            "property float z\nelement face 1\nproperty list uchar int vertex_indices\n"
            "end_header\n" + TRI_V + "3 0 1 7\n",
            "out of range",
        ),
    ],
)
def test_face_index_out_of_range(tmp_path, name, text, phrase):
    path = write(tmp_path, name, text)
    assert_mesh_error(path, phrase)


def test_out_of_range_in_memory():
    with pytest.raises(MeshError, match=r"^tri: 1 face with vertex indices out of range") as e:
        Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], name="tri")
    assert "one-based" not in str(e.value)
    # MATLAB's one-based faces (a .mat file's TRIV, say): named as such
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    with pytest.raises(MeshError, match="from 1 to 4: they are one-based.*subtract 1"):
        Mesh(V, (F + 1).astype(float), name="mat")
    with pytest.raises(MeshError, match="out of range"):
        Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, -1, 2]], name="tri")


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
def test_degenerate_faces(tmp_path, ext):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]])
    # face 1 is collinear (zero area), face 2 repeats a vertex
    F = np.array([[0, 1, 2], [0, 1, 3], [1, 1, 2]])
    path = write_mesh(tmp_path, "degenerate" + ext, V, F)
    assert_mesh_error(path, "2 degenerate faces", "1 with a repeated vertex", "first faces 1, 2")


def test_degenerate_faces_from_duplicated_vertices(tmp_path):
    # a UV sphere whose pole is stored once per meridian (as many exporters write it): the
    # pole rows' faces have two distinct corners at one position; only merging repairs that
    n, m = 12, 6
    th, ph = np.meshgrid(np.pi * np.arange(m + 1) / m, 2 * np.pi * np.arange(n) / n,
                         indexing="ij")
    V = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    V = V.reshape(-1, 3)
    idx = np.arange((m + 1) * n).reshape(m + 1, n)
    a, b = idx[:-1], idx[1:]
    a1, b1 = np.roll(a, -1, axis=1), np.roll(b, -1, axis=1)
    F = np.concatenate([np.stack([a, b, b1], -1).reshape(-1, 3),
                        np.stack([a, b1, a1], -1).reshape(-1, 3)])
    path = write_mesh(tmp_path, "uv_sphere.off", V, F)
    msg = assert_mesh_error(path, f"{2 * n} degenerate faces",
                            f"{2 * n} of them have two corners at one position",
                            "merge coincident vertices")
    assert "keeping the vertex order" not in msg  # removing them alone would open holes
    # the advice works: merged and cleaned as it says, the sphere loads
    import trimesh

    fixed = trimesh.load(path, process=True, validate=True)
    assert Mesh(fixed.vertices, fixed.faces).n_vertices == (m - 1) * n + 2
    # a genuinely flat face (distinct positions) keeps the usual advice
    V2 = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [2, 0, 0]])
    with pytest.raises(MeshError) as info:
        Mesh(V2, [[0, 1, 2], [0, 1, 3]], name="flat")
    assert "merge" not in str(info.value) and "keeping the vertex order" in str(info.value)


def test_degenerate_threshold_is_relative():
    # a tiny but valid triangle on a mesh of any scale is accepted ...
    scale = 1e-4
    V = scale * np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    assert Mesh(V, [[0, 1, 2]]).area() == pytest.approx(0.5 * scale**2)
    # ... a sliver with area 1e-14 on a unit-size mesh is not
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0.5, 1e-14, 0]])
    F = [[0, 1, 2], [0, 3, 1]]
    with pytest.raises(MeshError, match="1 degenerate face"):
        Mesh(V, F, name="sliver")


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
def test_unreferenced_vertices(tmp_path, ext):
    V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [9, 9, 9], [1, 1, 0], [8, 8, 8]])
    F = np.array([[0, 1, 2], [1, 4, 2]])
    path = write_mesh(tmp_path, "unref" + ext, V, F)
    assert_mesh_error(path, "2 unreferenced vertices", "vertices 3, 5", "ground-truth", "clean",
                      "--largest-component on the command line", "largest_component=True")


@pytest.mark.parametrize("ext", [".off", ".obj", ".ply"])
def test_several_components(tmp_path, ext):
    V, F = two_triangles_apart()
    path = write_mesh(tmp_path, "parts" + ext, V, F)
    assert_mesh_error(
        path, "2 connected components", "vertex counts 4, 3", "largest_component=True",
        "--largest-component on the command line",
    )


def test_largest_component(tmp_path):
    V, F = two_triangles_apart()
    # put the small component first so that reindexing is visible
    perm = np.array([4, 5, 6, 0, 1, 2, 3])
    inv = np.argsort(perm)
    V2, F2 = V[perm], inv[F][[2, 0, 1]]
    path = write_mesh(tmp_path, "parts.off", V2, F2)
    mesh = load_mesh(path, largest_component=True)
    assert (mesh.n_vertices, mesh.n_faces, mesh.n_input_vertices) == (4, 2, 7)
    assert mesh.vertex_map.dtype == torch.int64
    assert mesh.vertex_map.tolist() == [3, 4, 5, 6]
    assert mesh.with_vertices(2 * mesh.vertices).n_input_vertices == 7
    np.testing.assert_array_equal(mesh.vertices.numpy(), V2[mesh.vertex_map.numpy()])
    # faces refer to the same points as before
    np.testing.assert_array_equal(mesh.vertices.numpy()[mesh.faces.numpy()], V2[F2[1:]])
    # unreferenced vertices are dropped as well
    V3 = np.vstack([V[:4], [[7.0, 7, 7]]])
    m3 = Mesh(V3, F[:2], largest_component=True)
    assert m3.vertex_map.tolist() == [0, 1, 2, 3] and m3.n_input_vertices == 5
    # a single component keeps everything
    m4 = Mesh(V[:4], F[:2], largest_component=True)
    assert m4.vertex_map.tolist() == [0, 1, 2, 3] and m4.n_input_vertices == 4
    assert Mesh(V[:4], F[:2]).vertex_map.tolist() == [0, 1, 2, 3]
    # a tie between equal pieces goes to the one holding the lowest vertex index
    tie = Mesh(V[[4, 5, 6, 0, 1, 2]], [[0, 1, 2], [3, 4, 5]], largest_component=True)
    assert tie.vertex_map.tolist() == [0, 1, 2]


def test_largest_component_without_torch():
    # the command line finds the piece before it imports torch (for its eigensolve workers)
    import subprocess
    import sys

    code = ("import sys, numpy as np; from torchheat.topology import largest_component, "
            "restrict_faces; F = np.array([[4, 5, 6], [0, 1, 2], [1, 3, 2]]); "
            "k = largest_component(F, 8); print(k.tolist(), restrict_faces(F, k, 8).tolist(), "
            "'torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=60, check=True).stdout
    assert out.strip() == "[0, 1, 2, 3] [[0, 1, 2], [1, 3, 2]] False"
    V, F = two_triangles_apart()
    mesh = Mesh(V[[4, 5, 6, 0, 1, 2, 3]], [[4, 5, 6], [0, 1, 2], [4, 3, 5]],
                largest_component=True)
    assert mesh.vertex_map.tolist() == [3, 4, 5, 6]  # the same piece
    assert mesh.faces.tolist() == [[1, 2, 3], [1, 0, 2]]


def test_non_manifold_edge_warns(tmp_path):
    V = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]]
    F = [[0, 1, 2], [0, 1, 3], [0, 1, 4]]
    path = write_mesh(tmp_path, "fan.off", V, F)
    with pytest.warns(MeshWarning, match=r"1 non-manifold edge .*first \(0, 1\)") as rec:
        mesh = load_mesh(path)
    assert str(path) in str(rec[0].message)
    assert "repair the mesh if you can" in str(rec[0].message)  # no repeated face to name
    assert mesh.n_faces == 3
    assert mesh.boundary_edges().shape[0] == 6


@pytest.mark.parametrize("flap", [False, True])
def test_repeated_faces_named(tmp_path, flap):
    # an exported copy of a face, or a two-sided flap (SHREC'16's null cat has 12 flaps):
    # the non-manifold-edge warning says which faces repeat which, and how to remove them
    m = trimesh.creation.icosphere(1)
    F = np.asarray(m.faces)
    extra = F[[7, 3]][:, ::-1] if flap else np.roll(F[[7, 3]], 1, axis=1)
    path = write_mesh(tmp_path, "rep.off", np.asarray(m.vertices), np.vstack([F, extra]))
    with pytest.warns(MeshWarning) as rec:
        mesh = load_mesh(path)
    msg = str(rec[0].message)
    n = F.shape[0]
    how = "wound the other way: a two-sided flap" if flap else "a copy"
    assert f"2 faces repeat the three vertices of an earlier face (first: face {n} repeats " \
           f"face 7, {how})" in msg
    assert "6 non-manifold edges" in msg and "unique_faces" in msg
    assert mesh.n_faces == n + 2  # warned, not changed: face indices stay the file's


def test_non_manifold_vertex_boundary_orientation_accepted():
    # two tetrahedra sharing only vertex 0 (pinched), one with flipped faces, plus no warning
    V = np.vstack([TETRA_V, -TETRA_V[1:]])
    F2 = np.where(TETRA_F == 0, 0, TETRA_F + 3)[:, ::-1]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        mesh = Mesh(V, np.vstack([TETRA_F, F2]), name="pinched")
    assert mesh.boundary_edges().shape == (0, 2)
    # a single triangle with boundary is fine, and so is inconsistent orientation
    V = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]
    mesh = Mesh(V, [[0, 1, 2], [1, 2, 3]])
    assert mesh.area() == pytest.approx(1.0)


# ----------------------------------------------------------------- in-memory errors
def test_shape_errors():
    with pytest.raises(MeshError, match="^mesh: mesh has no vertices"):
        Mesh(np.zeros((0, 3)), [[0, 1, 2]])
    with pytest.raises(MeshError, match=r"^x: vertices must have shape \[n, 3\]"):
        Mesh(np.zeros((4, 2)), [[0, 1, 2]], name="x")
    with pytest.raises(MeshError, match="no faces"):
        Mesh(np.zeros((3, 3)), np.zeros((0, 3), dtype=int))
    with pytest.raises(MeshError, match="no faces"):
        Mesh(np.zeros((3, 3)), [])
    with pytest.raises(MeshError, match="triangulate it first"):
        Mesh(np.eye(4, 3), [[0, 1, 2, 3]])
    with pytest.raises(MeshError, match=r"faces must have shape \[m, 3\]"):
        Mesh(np.eye(3), [0, 1, 2])
    with pytest.raises(MeshError, match="must be integers"):
        Mesh(np.eye(3), [[0, 1, 1.5]])
    with pytest.raises(MeshError, match="non-numeric"):
        Mesh([["a", "b", "c"]], [[0, 0, 0]])


def test_check_false_skips_validation():
    V = np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [np.nan, 0, 0]])
    mesh = Mesh(V, np.array([[0, 1, 2]], dtype=np.int32), check=False)
    assert mesh.vertices.dtype == torch.float64
    assert mesh.faces.dtype == torch.int64
    assert mesh.n_vertices == 4


# ------------------------------------------------------------------- round trips
@pytest.mark.parametrize("ext", [".off", ".OFF", ".ply", ".obj", ".Obj"])
def test_round_trip_exact(tmp_path, ext):
    m = trimesh.creation.icosphere(2)
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(m.vertices))
    V = (m.vertices * rng.uniform(0.5, 2.0, size=(1, 3)))[perm] + rng.normal(size=3)
    F = np.argsort(perm)[m.faces][rng.permutation(len(m.faces))]
    path = write_mesh(tmp_path, "rand" + ext, V, F)
    mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.vertices.numpy(), V)
    np.testing.assert_array_equal(mesh.faces.numpy(), F)
    assert mesh.name == str(path)


@pytest.mark.parametrize("ext", ["off", "ply", "obj"])
def test_round_trip_trimesh_export(tmp_path, ext):
    V, F = TETRA_V * 1.5 + 0.25, TETRA_F
    path = tmp_path / f"tetra.{ext}"
    trimesh.Trimesh(V, F, process=False).export(path)
    mesh = load_mesh(path)
    np.testing.assert_allclose(mesh.vertices.numpy(), V, rtol=1e-7)
    np.testing.assert_array_equal(mesh.faces.numpy(), F)


def test_off_header_on_same_line(tmp_path):
    path = write(tmp_path, "same.off", off_text(TETRA_V, TETRA_F, header_same_line=True))
    mesh = load_mesh(path)
    np.testing.assert_array_equal(mesh.faces.numpy(), TETRA_F)


def test_obj_corner_formats_and_negative_indices(tmp_path):
    text = (
        "# comment\nmtllib x.mtl\no thing\n"
        "v 0 0 0\nv 1 0 0 1.0\nv 0 1 0 0.5 0.5 0.5\nvt 0 0\nvt 1 0\nvn 0 0 1\n"
        "  v 0 0 1\n"
        "f 1/1/1 3/2/1 2/1/1\n"
        "f 1//1 2//1 4//1  # trailing comment\n"
        "f\t-3/1 -2/2 -1/1\n"
        "v 5 5 5\n"
        "f -5 -2 -3\n"
    )
    path = write(tmp_path, "corners.obj", text)
    with pytest.raises(MeshError, match="1 unreferenced vertex"):
        load_mesh(path)
    mesh = load_mesh(path, largest_component=True)
    assert mesh.faces.tolist() == TETRA_F.tolist()
    assert mesh.vertex_map.tolist() == [0, 1, 2, 3]
    assert mesh.vertices[1].tolist() == [1.0, 0.0, 0.0]
    assert mesh.vertices[2].tolist() == [0.0, 1.0, 0.0]


# ------------------------------------------------------------------ bundled data
def test_spot():
    mesh = load_mesh(DATA / "spot.obj")
    assert (mesh.n_vertices, mesh.n_faces) == (2930, 5856)
    assert mesh.boundary_edges().shape == (0, 2)
    assert mesh.vertices.is_contiguous()
    assert repr(mesh) == f"Mesh(name={str(DATA / 'spot.obj')!r}, n_vertices=2930, n_faces=5856)"


def test_bs_rest_is_a_disk():
    mesh = load_mesh(DATA / "bs_rest.obj")
    assert (mesh.n_vertices, mesh.n_faces) == (19985, 39856)
    assert mesh.boundary_edges().shape == (112, 2)
    bv = mesh.boundary_vertices()
    assert bv.dtype == torch.bool and bv.shape == (19985,)
    assert int(bv.sum()) == 112  # a single boundary loop
    n, e, f = mesh.n_vertices, mesh.edges().shape[0], mesh.n_faces
    assert n - e + f == 1  # Euler characteristic of a disk


@pytest.mark.slow
def test_scape_mesh():
    path = SHARED / "scape" / "mesh000.off"
    if not path.exists():
        pytest.skip(f"{path} not available")
    mesh = load_mesh(path)
    assert (mesh.n_vertices, mesh.n_faces) == (12500, 24998)
    # vertex order is exactly the file's
    tm = trimesh.load(path, process=False, force="mesh")
    np.testing.assert_array_equal(mesh.vertices.numpy(), tm.vertices)


# ------------------------------------------------------------------ Mesh basics
def test_accepts_numpy_torch_lists():
    V = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]
    F = [[0, 1, 2]]
    meshes = [
        Mesh(V, F),
        Mesh(np.array(V, dtype=np.float32), np.array(F, dtype=np.int32)),
        Mesh(torch.tensor(V, dtype=torch.float32), torch.tensor(F)),
        Mesh(torch.tensor(V).T.contiguous().T, torch.tensor(F, dtype=torch.int32)),
    ]
    for mesh in meshes:
        assert mesh.vertices.dtype == torch.float64 and mesh.vertices.shape == (3, 3)
        assert mesh.vertices.is_contiguous()
        assert mesh.faces.dtype == torch.int64 and mesh.faces.shape == (1, 3)
        assert mesh.vertex_map.tolist() == [0, 1, 2]
        assert mesh.name is None
    V2, F2 = meshes[1].numpy()
    assert V2.dtype == np.float64 and F2.dtype == np.int64
    V2[0, 0] = 5.0  # a copy: the mesh is unchanged
    assert meshes[1].vertices[0, 0] == 0.0


def test_areas_by_hand():
    tri = Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    assert tri.face_areas().tolist() == [0.5]
    assert tri.area() == 0.5
    V = [[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]]
    square = Mesh(V, [[0, 1, 2], [0, 3, 2]])  # second face flipped: areas are unsigned
    np.testing.assert_allclose(square.face_areas().numpy(), [0.5, 0.5])
    assert square.area() == pytest.approx(1.0)
    assert square.bbox_diagonal() == pytest.approx(np.sqrt(2.0))
    tetra = Mesh(TETRA_V, TETRA_F)
    assert tetra.area() == pytest.approx(1.5 + np.sqrt(3) / 2)


def test_boundary_single_triangle_and_tetrahedron():
    tri = Mesh([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], [[2, 0, 1]])
    assert tri.boundary_edges().tolist() == [[0, 1], [0, 2], [1, 2]]
    assert tri.boundary_vertices().tolist() == [True, True, True]
    tetra = Mesh(TETRA_V, TETRA_F)
    assert tetra.boundary_edges().shape == (0, 2)
    assert not tetra.boundary_vertices().any()
    assert tetra.edges().shape == (6, 2)


def test_edges_and_adjacency_icosahedron():
    ico = trimesh.creation.icosahedron()
    mesh = Mesh(ico.vertices, ico.faces, name="ico")
    E = mesh.edges()
    assert E.shape == (30, 2) and E.dtype == torch.int64
    assert bool((E[:, 0] < E[:, 1]).all())
    keys = (E[:, 0] * mesh.n_vertices + E[:, 1]).numpy()
    assert np.all(np.diff(keys) > 0)  # lexicographic, unique
    expected = {tuple(sorted(e)) for e in np.asarray(ico.edges_unique)}
    assert {tuple(e) for e in E.tolist()} == expected
    A = mesh.adjacency()
    assert isinstance(A, sp.csr_matrix) and A.shape == (12, 12)
    assert (A != A.T).nnz == 0 and A.diagonal().sum() == 0
    np.testing.assert_array_equal(np.asarray(A.sum(axis=1)).ravel(), np.full(12, 5.0))
    assert mesh.boundary_edges().shape == (0, 2)


def test_with_vertices():
    ico = trimesh.creation.icosahedron()
    mesh = Mesh(ico.vertices, ico.faces, name="ico")
    bigger = mesh.with_vertices(torch.as_tensor(ico.vertices) * 2.0)
    assert bigger.name == "ico" and bigger.faces is mesh.faces
    assert bigger.area() == pytest.approx(4.0 * mesh.area())
    assert bigger.edges().shape == (30, 2)
    with pytest.raises(MeshError, match=r"^ico: new vertices have shape \(11, 3\)"):
        mesh.with_vertices(ico.vertices[:11])
    flat = np.array(ico.vertices)
    flat[:, 2] = 0.0
    flat[:, 1] = 0.0  # every face collapses onto a line
    with pytest.raises(MeshError, match="degenerate"):
        mesh.with_vertices(flat)
    bad = np.array(ico.vertices)
    bad[4] = np.nan
    with pytest.raises(MeshError, match="first: vertex 4"):
        mesh.with_vertices(bad)
    # a mirror image is wound outward as Mesh(vertices, faces) winds it (its faces kept as
    # they were, it read inside out and matched by the mirror map)
    mirrored = np.array(ico.vertices) * [-1.0, 1.0, 1.0]
    fresh = Mesh(mirrored, ico.faces)
    m2 = mesh.with_vertices(mirrored)
    assert fresh.turned_outward and m2.turned_outward and not mesh.turned_outward
    assert torch.equal(m2.faces, fresh.faces) and m2.flipped_faces == fresh.flipped_faces == 20
    back = m2.with_vertices(ico.vertices)  # and back again
    assert torch.equal(back.faces, mesh.faces) and not back.turned_outward
    assert back.flipped_faces == 0


def test_torch_input_is_copied_and_keeps_grad():
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64, requires_grad=True)
    mesh = Mesh(V, torch.tensor([[0, 1, 2]]))
    assert mesh.vertices.data_ptr() != V.data_ptr()
    mesh.area()
    mesh.face_areas().sum().backward()
    assert V.grad is not None and V.grad.shape == (3, 3)


def test_fast_off_reader_matches_trimesh_or_defers(tmp_path):
    from torchheat.meshio import _load_trimesh, _parse_off

    rng = np.random.default_rng(5)
    V = rng.standard_normal((40, 3))
    F = rng.integers(0, 40, (30, 3))
    body = "".join(f"{x:.17g} {y:.17g} {z:.17g}\n" for x, y, z in V)
    body += "".join(f"3 {a} {b} {c}\n" for a, b, c in F)
    plain = tmp_path / "plain.off"
    plain.write_text("# made by a test\nOFF\n\n40 30 0  # counts\n" + body)
    fast = _parse_off(plain)
    assert fast is not None
    ref = _load_trimesh(plain, "OFF")
    assert np.array_equal(fast[0], ref[0]) and np.array_equal(fast[1], ref[1])
    # anything unusual goes to trimesh (and its error messages): colours, quads, a short file
    for name, text in (
        ("colour.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2 255 0 0\n"),
        ("quad.off", "OFF\n4 1 0\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n"),
        ("short.off", "OFF\n3 1 0\n0 0 0\n1 0 0\n"),
        ("coff.off", "COFF\n3 1 0\n0 0 0 1 1 1 1\n1 0 0 1 1 1 1\n0 1 0 1 1 1 1\n3 0 1 2\n"),
    ):
        (tmp_path / name).write_text(text)
        assert _parse_off(tmp_path / name) is None, name


def _holed_sphere(seed: int = 0):
    """An icosphere with three disjoint holes punched out (the faces around three vertices)."""
    m = trimesh.creation.icosphere(3)
    V, F = np.asarray(m.vertices), np.asarray(m.faces, dtype=np.int64)
    centres = [0, 40, 200]
    drop = np.zeros(len(F), dtype=bool)
    for c in centres:  # the one-ring, and for the last one the two-ring too
        ring = np.isin(F, [c]).any(axis=1)
        if c == 200:
            ring = np.isin(F, np.unique(F[ring])).any(axis=1)
        drop |= ring
    F = F[~drop]
    used = np.unique(F)  # renumber: the removed centres leave no unreferenced vertex
    new = np.full(len(V), -1)
    new[used] = np.arange(used.size)
    return V[used], new[F]


def test_boundary_loops_follow_the_face_orientation():
    from torchheat.topology import boundary_loops

    V, F = _holed_sphere()
    loops = boundary_loops(F, len(V))
    assert len(loops) == 3
    assert sum(len(lp) for lp in loops) == len(Mesh(V, F).boundary_edges())
    assert all(np.unique(lp).size == lp.size for lp in loops)
    face_edges = {(int(a), int(b)) for f in F for a, b in ((f[0], f[1]), (f[1], f[2]),
                                                           (f[2], f[0]))}
    for lp in loops:  # every step is a face edge whose reverse no face has
        for a, b in zip(lp, np.roll(lp, -1), strict=True):
            assert (a, b) in face_edges and (b, a) not in face_edges
    assert boundary_loops(np.asarray(trimesh.creation.icosphere(1).faces), 42) == []


@pytest.mark.parametrize("rings", [False, True])
def test_fill_holes_closes_every_loop_consistently(rings):
    from torchheat.topology import boundary_loops, fill_holes

    V, F = _holed_sphere()
    V2, F2 = fill_holes(V, F, rings=rings)
    n = len(V)
    assert np.array_equal(V2[:n], V) and np.array_equal(F2[:len(F)], F)
    assert boundary_loops(F2, len(V2)) == []
    # a closed, consistently oriented surface: every directed edge once, its reverse once
    he = np.concatenate([F2[:, [0, 1]], F2[:, [1, 2]], F2[:, [2, 0]]])
    keys = he[:, 0] * len(V2) + he[:, 1]
    assert np.unique(keys).size == keys.size
    assert np.isin(he[:, 1] * len(V2) + he[:, 0], keys).all()
    E = np.unique(np.sort(he, axis=1), axis=0)
    assert len(V2) - len(E) + len(F2) == 2  # a sphere again
    Mesh(V2, F2, name="filled")  # valid: no degenerate or non-manifold faces
    loops = boundary_loops(F, n)
    if not rings:
        assert len(V2) == n + 3
        for c in range(n, len(V2)):  # each new vertex is the centroid of its loop
            ring = np.unique(F2[(F2 == c).any(axis=1)])
            np.testing.assert_allclose(V2[c], V[ring[ring < n]].mean(0), atol=1e-12)
    else:  # the two-ring hole (12 edges, radius ~2 edges) gets a ring, the one-rings do not
        assert len(V2) == n + 3 + max(len(lp) for lp in loops)
        # the patches' edges stay about as long as the loops' (a single fan's spokes reach
        # across the two-ring hole: about twice that)
        lens = np.linalg.norm(V2[E[:, 0]] - V2[E[:, 1]], axis=1)
        loop_edges = max(np.linalg.norm(V[lp] - V[np.roll(lp, -1)], axis=1).max()
                         for lp in loops)
        assert lens[(E >= n).any(axis=1)].max() <= 1.5 * loop_edges


def test_fill_holes_cuts_a_pinched_loop_into_simple_ones():
    from torchheat.topology import boundary_loops, fill_holes

    # two squares of two triangles each, touching at vertex 2; leaving 2 the walk takes the
    # lower-numbered edge 2 -> 1 into the second square, so one walk visits 2 twice
    V = np.array([[0.0, 0, 0], [2, 1, 0], [1, 1, 0], [2, 2, 0], [1, 2, 0], [1, 0, 0],
                  [0, 1, 0]])
    F = np.array([[0, 5, 2], [0, 2, 6], [2, 1, 3], [2, 3, 4]])
    (loop,) = boundary_loops(F, len(V))
    assert len(loop) == 8 and np.count_nonzero(loop == 2) == 2
    V2, F2 = fill_holes(V, F)
    assert len(V2) == len(V) + 2  # one fan per simple loop
    he = np.concatenate([F2[:, [0, 1]], F2[:, [1, 2]], F2[:, [2, 0]]])
    edges, counts = np.unique(np.sort(he, axis=1), axis=0, return_counts=True)
    assert (counts == 2).all()  # closed, every edge manifold


def _flip_some(F: np.ndarray, seed: int = 0, share: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """``F`` with a random minority of faces reversed, and the mask of those faces."""
    rng = np.random.default_rng(seed)
    turned = rng.random(len(F)) < share
    G = F.copy()
    G[turned] = G[turned][:, [0, 2, 1]]
    return G, turned


def test_orient_faces_undoes_reversed_faces():
    from torchheat.topology import orient_faces

    for V, F in (_holed_sphere(), (np.asarray(trimesh.creation.icosphere(3).vertices),
                                   np.asarray(trimesh.creation.icosphere(3).faces))):
        G, turned = _flip_some(F)
        F2, flipped, ok = orient_faces(G, len(V))
        assert ok and flipped == turned.sum() > 0
        assert np.array_equal(F2, F)  # the same rows, in order, turned back
        assert orient_faces(F, len(V))[1:] == (0, True)  # consistent: untouched
        # the majority keeps its sense: all faces reversed but a few -> the few turn
        H, few = _flip_some(F[:, [0, 2, 1]], seed=1, share=0.1)
        F3, k, _ = orient_faces(H, len(V))
        assert k == few.sum() and np.array_equal(F3, F[:, [0, 2, 1]])


def test_orient_faces_patches_and_moebius():
    from torchheat.topology import orient_faces

    # two triangles joined only at a vertex: separate patches, each keeps its own sense
    F = np.array([[0, 1, 2], [2, 4, 3]])
    assert orient_faces(F, 5)[1:] == (0, True)
    # two spheres, one facing in and one out, a few faces reversed in each: each patch's
    # majority wins on its own
    S = np.asarray(trimesh.creation.icosphere(2).faces)
    F = np.vstack([S, S[:, [0, 2, 1]] + 162])
    G, turned = _flip_some(F, seed=3, share=0.1)
    F2, flipped, ok = orient_faces(G, 324)
    assert ok and flipped == turned.sum() and np.array_equal(F2, F)
    # a Moebius strip (a band of 2 * 6 triangles glued with a half twist) cannot be oriented
    k = 6
    top, bot = np.arange(k), np.arange(k) + k
    F = []
    for i in range(k):
        j = (i + 1) % k
        a, b, c, d = top[i], bot[i], top[j], bot[j]
        if j == 0:
            c, d = d, c  # the twist: top meets bottom
        F += [[a, b, c], [b, d, c]]
    F2, flipped, ok = orient_faces(np.array(F), 2 * k)
    assert not ok and flipped == 0 and np.array_equal(F2, F)


def test_mesh_turns_reversed_faces_so_boundaries_and_patches_stay_manifold():
    from torchheat.topology import boundary_loops, fill_holes

    V, F = _holed_sphere()
    G, turned = _flip_some(F, share=0.05)
    mesh = Mesh(V, G, name="flipped")
    assert mesh.flipped_faces == turned.sum()
    assert np.array_equal(mesh.faces.numpy(), F)
    # as given, the reversed faces' edges read as boundary: more loops, and the patches over
    # them would glue a third face to interior edges
    assert len(boundary_loops(G, len(V))) > 3
    assert len(boundary_loops(mesh.faces.numpy(), len(V))) == 3
    V2, F2 = fill_holes(*mesh.numpy())
    Mesh(V2, F2, name="filled")
    _, counts = np.unique(np.sort(np.concatenate([F2[:, [0, 1]], F2[:, [1, 2]], F2[:, [2, 0]]]),
                                  axis=1), axis=0, return_counts=True)
    assert (counts == 2).all()


def _signed_volume(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum()) / 6.0


def test_a_surface_wound_inside_out_is_turned_outward():
    from torchheat.topology import orient_outward

    m = trimesh.creation.icosphere(3)
    V, F = np.asarray(m.vertices) * [1.0, 0.8, 0.6] + [3.0, -2.0, 1.0], np.asarray(m.faces)
    assert _signed_volume(V, F) > 0  # trimesh winds outward
    inv = F[:, [0, 2, 1]]
    # closed: the enclosed volume's sign (the same from any origin)
    assert orient_outward(V, F)[1] is False
    G, turned = orient_outward(V, inv)
    assert turned and np.array_equal(G, F)
    mesh = Mesh(V, inv, name="inside-out")
    assert mesh.turned_outward and mesh.flipped_faces == len(F)
    assert np.array_equal(mesh.faces.numpy(), F)
    assert not Mesh(V, F).turned_outward and Mesh(V, F).flipped_faces == 0
    # and some faces also reversed against their neighbours: all face outward after load
    G, turned_some = _flip_some(inv, share=0.05)
    mesh = Mesh(V, G)
    assert mesh.turned_outward and np.array_equal(mesh.faces.numpy(), F)
    assert mesh.flipped_faces == len(F) - turned_some.sum()
    # with holes: read once they are closed
    V, F = _holed_sphere()
    assert orient_outward(V, F)[1] is False
    assert Mesh(V, F[:, [0, 2, 1]]).turned_outward
    # a closed thin plate (volume 4e-4 area^1.5) is read too: a closed surface's sign is exact
    plate = trimesh.creation.box(extents=[1.0, 1.0, 0.001])
    Vp, Fp = np.asarray(plate.vertices), np.asarray(plate.faces)
    assert not Mesh(Vp, Fp).turned_outward and Mesh(Vp, Fp[:, [0, 2, 1]]).turned_outward
    # a flat patch encloses nothing: the file's winding is kept either way
    grid = np.asarray(trimesh.creation.box().vertices)[:4]  # the corners of the side x = -0.5
    Fg = np.array([[0, 1, 3], [0, 3, 2]])
    for faces in (Fg, Fg[:, [0, 2, 1]]):
        assert not Mesh(grid, faces).turned_outward


def _seamed_ellipsoid():
    """An ellipsoid whose faces with x > 0 use copies of their vertices: two components that
    meet along a seam of duplicated vertices (as UV-mapped exports store a surface)."""
    m = trimesh.creation.icosphere(3)
    V, F = np.asarray(m.vertices) * [1.0, 0.8, 0.6], np.asarray(m.faces, dtype=np.int64)
    right = V[F].mean(axis=1)[:, 0] > 0
    left_used = np.unique(F[~right])
    right_used = np.unique(F[right])
    shared = np.intersect1d(left_used, right_used)
    copy = {int(v): len(V) + i for i, v in enumerate(shared)}
    G = F.copy()
    G[right] = np.vectorize(lambda v: copy.get(int(v), int(v)))(F[right])
    return np.vstack([V, V[shared]]), G, shared.size


def test_components_meeting_at_a_seam_of_duplicated_vertices_are_named():
    V, F, seam = _seamed_ellipsoid()
    with pytest.raises(MeshError, match=f"meet at {seam} coincident vertices") as err:
        Mesh(V, F, name="seamed")
    assert "merge the duplicate vertices" in str(err.value)
    with pytest.warns(MeshWarning, match=f"meet the kept one at {seam} coincident vertices"):
        kept = Mesh(V, F, name="seamed", largest_component=True)
    assert kept.n_vertices < len(V)
    # copies a few ulps apart (an exporter computing them separately) are a seam too: the
    # exact comparison called them plain "several components"
    Vj = V.copy()
    Vj[-seam:] += 1e-12 * np.random.default_rng(0).standard_normal((seam, 3))
    assert not (Vj[-seam:] == V[-seam:]).all(axis=1).any()
    with pytest.raises(MeshError, match=f"meet at {seam} coincident vertices"):
        Mesh(Vj, F, name="seamed")
    # components apart: the plain advice, and no warning when the largest is kept
    a = trimesh.creation.icosphere(2)
    W = np.vstack([a.vertices, a.vertices + [3.0, 0, 0]])
    G = np.vstack([a.faces, a.faces + len(a.vertices)])
    with pytest.raises(MeshError, match="connected components") as err:
        Mesh(W, G)
    assert "coincident" not in str(err.value)
    with warnings.catch_warnings():
        warnings.simplefilter("error", MeshWarning)
        Mesh(W, G, largest_component=True)


def test_as_mesh_takes_what_users_hold(tmp_path):
    from torchheat import as_mesh

    s = trimesh.creation.icosphere(2)
    V, F = np.asarray(s.vertices), np.asarray(s.faces)
    path = tmp_path / "ico.off"
    s.export(path)
    base = Mesh(V, F)
    assert as_mesh(base) is base
    from types import SimpleNamespace

    pyg = SimpleNamespace(pos=torch.from_numpy(V).float(), face=torch.from_numpy(F.T.copy()))
    for x in (s, (V, F), [V, F], str(path), path, pyg):
        m = as_mesh(x)
        assert np.allclose(m.vertices.numpy(), V, atol=1e-6)
        assert np.array_equal(m.faces.numpy(), F)
    assert as_mesh(str(path)).name == str(path)
    with pytest.raises(TypeError, match="a .vertices, faces. pair; got int"):
        as_mesh(3)
    with pytest.raises(MeshError, match="no such file"):
        as_mesh(tmp_path / "missing.off")
    with pytest.raises(MeshError, match="connected components"):  # validated as a Mesh
        as_mesh((np.vstack([V, V + 3]), np.vstack([F, F + len(V)])))
