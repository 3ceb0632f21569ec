"""Reading mesh files into numpy arrays (no torch): OFF, OBJ, PLY, STL, GLB and glTF.

This is the file layer under :mod:`torchheat.mesh`: :func:`read_arrays` turns a path into
``(V, F)`` and :func:`torchheat.mesh.load_mesh` wraps them in a validated
:class:`~torchheat.mesh.Mesh`. It imports only numpy (and trimesh for STL, GLB and glTF), so
worker processes can read and solve meshes before torch is imported (see
:mod:`torchheat.eigen`). :class:`MeshError` and :class:`MeshWarning` live here and are
re-exported by :mod:`torchheat.mesh`.

Formats and vertex order
------------------------
Ground-truth correspondences are lists of vertex indices, so what a reader does to the vertex
order matters:

==================  =========================================================================
``.off .obj .ply``  **Vertex order kept exactly** (:data:`ORDER_KEEPING_FORMATS`): every
                    vertex of the file, in file order, none merged or dropped. Own parsers:
                    ASCII OFF (``OFF``, ``COFF``, ``NOFF``, ``STOFF``...: extra vertex
                    columns and face colours are ignored), OBJ (``v`` lines and the first
                    index of each ``f`` corner: ``i``, ``i/t``, ``i//n``, ``i/t/n``,
                    negative = relative; texture seams do not split vertices as they do in
                    trimesh), PLY ASCII and binary (either byte order; ``x y z`` of the
                    ``vertex`` element, the ``vertex_indices`` list of the ``face`` element).
``.stl``            **Merged** (:data:`MERGED_FORMATS`): an STL is a triangle soup (three
                    corners written per triangle, ASCII or binary), so vertices with exactly
                    the same coordinates are merged. The vertex order is then the order of
                    first appearance in the file (first triangle's corners first), and so is
                    the line order of a map computed on it.
``.glb .gltf``      **Merged** the same way: every triangle mesh instance of the scene (all
                    primitives, placed by the node transforms, in the order of trimesh's scene
                    graph), concatenated, then exact duplicates merged (glTF splits vertices
                    along UV and normal seams) and vertices no triangle uses dropped. Points and
                    lines are ignored. A glTF file with one seamless mesh keeps its order.
==================  =========================================================================

Polygons (quads, pentagons, ...) in OFF, OBJ and PLY are triangulated, keeping the vertices:
a fan from the corner that gives the best triangles when one is valid, else ear clipping on the
polygon projected to its plane (see :func:`triangulate_polygons`). A polygon's triangles follow
each other in face order, so face numbers in validation messages count triangles.

Examples
--------
>>> from importlib.resources import files
>>> V, F = read_arrays(files("torchheat") / "data" / "spot.obj")
>>> V.shape, F.shape
((2930, 3), (5856, 3))
"""

from __future__ import annotations

import os
import re
import struct
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

__all__ = [
    "FORMATS_HELP",
    "MERGED_FORMATS",
    "MeshError",
    "MeshWarning",
    "ORDER_KEEPING_FORMATS",
    "SUPPORTED_FORMATS",
    "COMPRESSED",
    "read_arrays",
    "triangulate_polygons",
]

#: Extensions whose vertices are read exactly as stored: every vertex, in file order.
ORDER_KEEPING_FORMATS: tuple[str, ...] = (".obj", ".off", ".ply")
#: Extensions whose exact-duplicate vertices are merged (order of first appearance).
MERGED_FORMATS: tuple[str, ...] = (".stl", ".glb", ".gltf")
#: File extensions understood by :func:`read_arrays` (case-insensitive).
SUPPORTED_FORMATS: tuple[str, ...] = ORDER_KEEPING_FORMATS + MERGED_FORMATS
#: Compressions read transparently for the order-keeping formats (``cat0.off.gz``)
COMPRESSED: tuple[str, ...] = (".gz", ".bz2", ".xz")
#: One line for a command's ``--help`` about formats.
FORMATS_HELP = (
    "Meshes: OFF, OBJ, PLY (also .gz, .bz2, .xz) keep their vertex order; STL, GLB, glTF "
    "have duplicate vertices merged: one map line per merged vertex, in order of first "
    "appearance."
)

# a triangle of a triangulated polygon must have a signed area above this fraction of the
# polygon's area (relative to the polygon's normal): no zero-area or flipped triangles
_POLY_REL_AREA = 1e-9
# polygons with more corners are ear-clipped directly (the fan search costs k^2 per polygon)
_FAN_SEARCH_MAX = 16


class MeshError(ValueError):
    """Invalid mesh input.

    The message starts with the file path (or the mesh name, or ``"mesh"``), then says what is
    wrong and what to do about it.

    Examples
    --------
    >>> from torchheat.mesh import Mesh, MeshError
    >>> try:
    ...     Mesh([[0.0, 0.0, 0.0]], [[0, 1, 2]], name="tiny")
    ... except MeshError as err:
    ...     print(str(err).split(":")[0])
    tiny
    """


class MeshWarning(UserWarning):
    """Suspicious but usable mesh input (e.g. non-manifold edges).

    Examples
    --------
    >>> import warnings
    >>> from torchheat.mesh import Mesh, MeshWarning
    >>> V = [[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1]]
    >>> F = [[0, 1, 2], [0, 1, 3], [0, 1, 4]]  # edge (0, 1) in three faces
    >>> with warnings.catch_warnings(record=True) as caught:
    ...     warnings.simplefilter("always")
    ...     _ = Mesh(V, F, name="fan")
    >>> caught[0].category.__name__
    'MeshWarning'
    """


def _plural(k: int, word: str) -> str:
    if k == 1:
        return f"{k} {word}"
    return f"{k} {word[:-2]}ices" if word.endswith("vertex") else f"{k} {word}s"


def _parse_numbers(text: str, dtype: type, count: int) -> np.ndarray | None:
    """Parse ``count`` whitespace-separated numbers, or return None when that fails.

    Integers too large for int64 are clamped by numpy (then reported as out of range).
    """
    if count == 0:
        return np.zeros(0, dtype=dtype) if not text.strip() else None
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns (and stops) on unparsable text
        try:
            out: np.ndarray = np.fromstring(text, dtype=dtype, sep=" ")
        except (ValueError, OverflowError, DeprecationWarning):
            return None
    return out if out.size == count else None


def _no_faces(path: Path) -> MeshError:
    return MeshError(
        f"{path}: file has no faces (a point cloud?); a triangle mesh is required, "
        "reconstruct a surface first (e.g. Poisson / ball pivoting in MeshLab or Open3D)"
    )


# ------------------------------------------------------------------ triangulation
def _fan_table(k: int) -> np.ndarray:
    """Local corners of the fan from every apex: ``[a, j] = (a, a+j+1, a+j+2) mod k``."""
    a = np.arange(k)[:, None]
    j = np.arange(k - 2)[None, :]
    return np.stack([np.broadcast_to(a, (k, k - 2)), (a + j + 1) % k, (a + j + 2) % k], axis=-1)


def _newell(X: np.ndarray) -> np.ndarray:
    """Vector area (Newell's normal times the area) of polygons ``X [..., k, 3]``."""
    return 0.5 * np.cross(X, np.roll(X, -1, axis=-2)).sum(axis=-2)


def _ear_clip(X: np.ndarray) -> list[tuple[int, int, int]]:
    """Triangulate one polygon ``X [k, 3]`` (local corner indices), ``k - 2`` triangles.

    The polygon is projected to the plane of its Newell normal (its best-fit plane, oriented by
    the corner order). The ear whose triangle is best shaped (twice its area over the sum of
    its squared sides) among those that hold no other corner, closed, is cut first; collinear
    corners are never ear tips, so no triangle has zero or negative area in that plane when the
    projected polygon is simple. Otherwise (self-intersecting projection, no ear left) the best
    convex corner is cut anyway, and a remainder without convex corners is fanned. Only the two
    neighbours of a cut corner are updated: O(k) numpy work per cut (~1 s for k = 10000).
    """
    k = X.shape[0]
    Xc = X - X.mean(axis=0)
    N = _newell(Xc)
    norm = float(np.linalg.norm(N))
    if not np.isfinite(norm) or norm == 0.0:
        return [(0, i, i + 1) for i in range(1, k - 1)]
    n = N / norm
    u = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    P = np.stack([Xc @ u, Xc @ w], axis=1)  # counter-clockwise: positive area
    tol = 2.0 * _POLY_REL_AREA * norm  # on twice the areas
    eps = 1e-12 * float(np.abs(P).max()) ** 2  # closed point-in-triangle test
    nxt = np.roll(np.arange(k), -1)
    prv = np.roll(np.arange(k), 1)

    def corner(i: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """Twice the signed area of (prev, i, next), and its shape quality."""
        a, b, c = P[prv[i]], P[i], P[nxt[i]]
        e1, e2 = b - a, c - b
        cross = e1[..., 0] * e2[..., 1] - e1[..., 1] * e2[..., 0]
        sides = (e1**2).sum(-1) + (e2**2).sum(-1) + ((c - a) ** 2).sum(-1)
        return cross, cross / np.maximum(sides, np.finfo(float).tiny)

    cross, quality = corner(np.arange(k))
    convex = cross > tol
    alive = np.ones(k, dtype=bool)
    q = np.where(convex, quality, -np.inf)
    tris: list[tuple[int, int, int]] = []
    for m in range(k, 3, -1):
        refused: list[tuple[int, float]] = []
        chosen = -1
        while True:
            c = int(np.argmax(q))
            if q[c] == -np.inf:
                break
            a, d = int(prv[c]), int(nxt[c])
            others = np.flatnonzero(alive & ~convex)
            others = others[(others != a) & (others != d)]
            if others.size:
                pa, pb, pd, t = P[a], P[c], P[d], P[others]
                s1 = (pb[0] - pa[0]) * (t[:, 1] - pa[1]) - (pb[1] - pa[1]) * (t[:, 0] - pa[0])
                s2 = (pd[0] - pb[0]) * (t[:, 1] - pb[1]) - (pd[1] - pb[1]) * (t[:, 0] - pb[0])
                s3 = (pa[0] - pd[0]) * (t[:, 1] - pd[1]) - (pa[1] - pd[1]) * (t[:, 0] - pd[0])
                if ((s1 >= -eps) & (s2 >= -eps) & (s3 >= -eps)).any():
                    refused.append((c, float(q[c])))
                    q[c] = -np.inf
                    continue
            chosen = c
            break
        for c, qc in refused:
            q[c] = qc
        if chosen < 0:
            if not refused:  # no convex corner left: fan the rest
                start = int(np.flatnonzero(alive)[0])
                ring = [start]
                for _ in range(m - 1):
                    ring.append(int(nxt[ring[-1]]))
                tris += [(ring[0], ring[i], ring[i + 1]) for i in range(1, m - 1)]
                return tris
            chosen = refused[0][0]  # the best convex corner, although not an ear
        a, d = int(prv[chosen]), int(nxt[chosen])
        tris.append((a, chosen, d))
        alive[chosen] = False
        q[chosen] = -np.inf
        nxt[a], prv[d] = d, a
        for v in (a, d):
            cv, qv = corner(v)
            convex[v] = cv > tol
            q[v] = qv if convex[v] else -np.inf
    start = int(np.flatnonzero(alive)[0])
    tris.append((start, int(nxt[start]), int(nxt[nxt[start]])))
    return tris


def _triangulate_group(V: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Triangles ``[n, k - 2, 3]`` of ``n`` polygons with ``k >= 4`` corners ``P [n, k]``.

    Indices must be in range. A fan from the corner whose worst triangle is best shaped, when
    all its triangles have positive area relative to the polygon's normal (always the case for
    convex polygons); else ear clipping. Polygons with non-finite or zero area are fanned from
    their first corner (validation then reports them).
    """
    with np.errstate(all="ignore"):  # inf / nan coordinates: such polygons are fanned
        return _fan_or_ear_clip(V, P)


def _fan_or_ear_clip(V: np.ndarray, P: np.ndarray) -> np.ndarray:
    """:func:`_triangulate_group` without the floating-point error guard."""
    n, k = P.shape
    out = np.empty((n, k - 2, 3), dtype=np.int64)
    if n == 0:
        return out
    X = V[P]
    X = X - X.mean(axis=1, keepdims=True)
    N = _newell(X)
    area = np.linalg.norm(N, axis=1)
    j = np.arange(k - 2)
    fan0 = P[:, np.stack([np.zeros_like(j), j + 1, j + 2], axis=1)]  # from the first corner
    bad = ~np.isfinite(area) | (area == 0.0)
    todo = np.flatnonzero(~bad)
    out[bad] = fan0[bad]
    if k <= _FAN_SEARCH_MAX and todo.size:
        table = _fan_table(k)
        if k == 4:
            table = table[:2]  # apex 2 and 3 give the same two splits as apex 0 and 1
        chunk = max(256, 2_000_000 // table.size)  # bounded memory (~50 MB)
        for lo in range(0, todo.size, chunk):
            rows = todo[lo : lo + chunk]
            T = X[rows][:, table]  # [r, apexes, k-2, 3 corners, 3]
            e1, e2 = T[..., 1, :] - T[..., 0, :], T[..., 2, :] - T[..., 0, :]
            nrm = N[rows] / area[rows, None]
            signed = 0.5 * np.einsum("rajc,rc->raj", np.cross(e1, e2), nrm)
            sides = (e1**2).sum(-1) + (e2**2).sum(-1) + ((e2 - e1) ** 2).sum(-1)
            quality = (signed / np.maximum(sides, np.finfo(float).tiny)).min(axis=2)
            ok = signed.min(axis=2) > _POLY_REL_AREA * area[rows, None]
            quality = np.where(ok, quality, -np.inf)
            best = np.argmax(quality, axis=1)
            good = ok[np.arange(rows.size), best]
            sel = rows[good]
            out[sel] = np.take_along_axis(P[sel], table[best[good]].reshape(-1, (k - 2) * 3),
                                          axis=1).reshape(-1, k - 2, 3)
            for r in rows[~good]:
                out[r] = P[r][np.array(_ear_clip(X[r]))]
    else:
        for r in todo:
            out[r] = P[r][np.array(_ear_clip(X[r]))]
    return out


def _collapse_repeats(
    path: Path, counts: np.ndarray, corners: np.ndarray, locate: Callable[[int], str]
) -> tuple[np.ndarray, np.ndarray]:
    """Drop a polygon corner equal to the next one (``4 a b c c`` is the triangle ``a b c``).

    Polygons with other repeated corners are refused; triangles are left to validation.
    """
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    fix: list[int] = []
    for k in np.unique(counts[counts > 3]):
        rows = np.flatnonzero(counts == k)
        S = np.sort(corners[starts[rows][:, None] + np.arange(k)], axis=1)
        fix += rows[(S[:, 1:] == S[:, :-1]).any(axis=1)].tolist()
    if not fix:
        return counts, corners
    counts = counts.copy()
    pieces = np.split(corners, starts[1:])
    for j in sorted(fix):
        c = pieces[j]
        keep = c != np.roll(c, -1)  # one corner of each (cyclic) run of equal corners
        c2 = c[keep] if keep.any() else c[:1]
        if c2.size < 3 or np.unique(c2).size != c2.size:
            raise MeshError(
                f"{path}: {locate(j)} repeats vertices ({' '.join(map(str, c.tolist()))}, "
                "0-based); a polygon must go round distinct vertices, fix or remove that face"
            )
        pieces[j] = c2
        counts[j] = c2.size
    return counts, np.concatenate(pieces)


def _polygons_to_triangles(
    path: Path,
    V: np.ndarray,
    counts: np.ndarray,
    corners: np.ndarray,
    locate: Callable[[int], str],
) -> np.ndarray:
    """Triangles ``[m, 3]`` of polygon faces (``counts`` corners each, ``corners`` flat).

    Triangles pass through unchanged (indices not range-checked: validation does it); a
    polygon's triangles follow each other in face order.
    """
    counts = np.asarray(counts, dtype=np.int64)
    corners = np.asarray(corners, dtype=np.int64)
    if counts.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    small = np.flatnonzero(counts < 3)
    if small.size:
        j = int(small[0])
        raise MeshError(
            f"{path}: {locate(j)} has {int(counts[j])} corners ({_plural(small.size, 'face')} "
            "with fewer than 3); a face needs at least three vertices, fix or remove it"
        )
    if (counts == 3).all():
        return corners.reshape(-1, 3)
    counts, corners = _collapse_repeats(path, counts, corners, locate)
    n = V.shape[0]
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    first_tri = np.concatenate([[0], np.cumsum(counts - 2)[:-1]])
    F = np.empty((int((counts - 2).sum()), 3), dtype=np.int64)
    for k in np.unique(counts):
        rows = np.flatnonzero(counts == k)
        P = corners[starts[rows][:, None] + np.arange(k)]
        dest = first_tri[rows][:, None] + np.arange(k - 2)
        if k == 3:
            F[dest[:, 0]] = P
            continue
        bad = np.flatnonzero(((P < 0) | (P >= n)).any(axis=1))
        if bad.size:
            j = int(rows[bad[0]])
            raise MeshError(
                f"{path}: {locate(j)} has vertex indices out of range (valid: 0..{n - 1}, "
                f"0-based; corners {' '.join(map(str, P[bad[0]].tolist()))}); the file is "
                "corrupt or the vertex count is wrong, fix the face list"
            )
        F[dest.ravel()] = _triangulate_group(V, P).reshape(-1, 3)
    return F


def triangulate_polygons(vertices: Any, polygons: Sequence[Sequence[int]]) -> np.ndarray:
    """Triangulate polygon faces without touching the vertices.

    Each polygon with ``k`` corners gives ``k - 2`` triangles, in polygon order; triangles are
    kept as they are. A polygon is cut by a fan from the corner whose worst triangle is best
    shaped, among the fans whose triangles all have positive area relative to the polygon's
    Newell normal (any convex polygon has one); otherwise (non-convex, or with collinear
    corners) by ear clipping of the polygon projected to the plane of that normal, which gives
    no zero-area or flipped triangle for a simple projected polygon. A corner repeating the
    previous one is dropped (``[a, b, c, c]`` is the triangle ``[a, b, c]``).

    Parameters
    ----------
    vertices : array_like, shape (n, 3)
    polygons : sequence of sequences of int
        Zero-based corner indices, at least three per polygon, in order around it.

    Returns
    -------
    numpy.ndarray of int64, shape (m, 3)
        ``m = sum(len(p) - 2)``.

    Raises
    ------
    MeshError
        A polygon with fewer than three corners, repeated (non-adjacent) corners, or indices
        out of range.

    Examples
    --------
    An L-shaped hexagon, whose fan from the first corner would leave its outline, is fanned
    from its inner corner 3:

    >>> V = [[0, 0, 0], [2, 0, 0], [2, 1, 0], [1, 1, 0], [1, 2, 0], [0, 2, 0]]
    >>> triangulate_polygons(V, [[1, 2, 3, 4, 5, 0]]).tolist()
    [[3, 4, 5], [3, 5, 0], [3, 0, 1], [3, 1, 2]]
    >>> triangulate_polygons(V, [[0, 1, 2], [0, 2, 3, 3]]).tolist()
    [[0, 1, 2], [0, 2, 3]]
    """
    V = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    polys = [np.asarray(p, dtype=np.int64).ravel() for p in polygons]
    counts = np.array([p.size for p in polys], dtype=np.int64)
    corners = np.concatenate(polys) if polys else np.zeros(0, dtype=np.int64)
    return _polygons_to_triangles(Path("polygons"), V, counts, corners, lambda j: f"polygon {j}")


# ------------------------------------------------------------------ OBJ
_OBJ_V = re.compile(r"^[ \t]*v[ \t]+([^\r\n#]*)", re.MULTILINE)
_OBJ_F = re.compile(r"^[ \t]*f[ \t]+([^\r\n#]*)", re.MULTILINE)
_SLASH_SUFFIX = re.compile(r"/\S*")


def _line_of(text: str, pattern: re.Pattern[str], k: int) -> int:
    """Line number (1-based) of the ``k``-th match of ``pattern`` in ``text``."""
    for i, match in enumerate(pattern.finditer(text)):
        if i == k:
            return text.count("\n", 0, match.start()) + 1
    return 0


#: UTF-8 byte-order mark, which Windows editors and some exporters put before a text file
_BOM = b"\xef\xbb\xbf"


def _file_bytes(path: Path) -> bytes:
    """The file's bytes, decompressed when it ends in one of :data:`COMPRESSED`, without a
    leading UTF-8 byte-order mark (read as part of the first token, it hid an OBJ file's first
    vertex and shifted every index)."""
    raw = path.read_bytes()
    kind = path.suffix.lower()
    if kind in COMPRESSED:
        import bz2
        import gzip
        import lzma

        module = {".gz": gzip, ".bz2": bz2, ".xz": lzma}[kind]
        try:
            raw = module.decompress(raw)
        except (OSError, EOFError, ValueError, lzma.LZMAError) as exc:
            raise MeshError(f"{path}: not a valid {kind[1:]} file ({exc}); the download may be "
                            "truncated, or the file not compressed: rename it") from None
    return raw[len(_BOM):] if raw.startswith(_BOM) else raw


#: A line that ends in a backslash (spaces after it allowed)
_OBJ_CONTINUED = re.compile(r"\\[ \t]*\r?$", re.MULTILINE)


def _join_continued(text: str) -> str:
    """OBJ lines continued by a backslash at their end (the OBJ spec) joined into one, each
    followed by as many empty lines as it absorbed (error messages keep their line numbers).
    A comment line is never continued: it may end in a Windows path's backslash."""
    out: list[str] = []
    head, absorbed = None, 0
    for line in text.splitlines():
        if head is not None:
            line, absorbed = head + " " + line, absorbed + 1
        stripped = line.rstrip()
        if stripped.endswith("\\") and not stripped.lstrip().startswith("#"):
            head = stripped[:-1]
            continue
        out.append(line)
        out.extend([""] * absorbed)
        head, absorbed = None, 0
    if head is not None:
        out.append(head)
    return "\n".join(out) + "\n"


def _parse_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``v`` lines and the first index of every ``f`` corner of an OBJ file, in order."""
    text = _file_bytes(path).decode("utf-8", errors="replace")
    if _OBJ_CONTINUED.search(text):  # not for a mere backslash (a path in a comment)
        text = _join_continued(text)
    vlines = _OBJ_V.findall(text)
    flines = _OBJ_F.findall(text)
    if not vlines and not flines:
        raise MeshError(
            f"{path}: no vertex ('v') or face ('f') lines found; the file is empty or not a "
            "text OBJ file, check it"
        )
    if not vlines:
        raise MeshError(
            f"{path}: no vertex ('v') lines, only faces; the file is truncated or not a "
            "complete OBJ file, check it"
        )
    # vertices: 'v x y z [w]' or 'v x y z r g b'; only x y z are kept
    vrows = [ln.split() for ln in vlines]
    nvtok = np.fromiter(map(len, vrows), dtype=np.int64, count=len(vrows))
    V = None
    if (nvtok == 3).all():
        V = _parse_numbers(" ".join(vlines), np.float64, 3 * len(vlines))
    elif (nvtok >= 3).all():
        V = _parse_numbers(" ".join([" ".join(r[:3]) for r in vrows]), np.float64, 3 * len(vlines))
    if V is None:
        for k, r in enumerate(vrows):
            ok = len(r) >= 3 and _parse_numbers(" ".join(r[:3]), np.float64, 3) is not None
            if not ok:
                raise MeshError(
                    f"{path}: cannot parse vertex {k} on line {_line_of(text, _OBJ_V, k)} "
                    f"({vlines[k].strip()!r}); each 'v' line needs three numbers, the file may "
                    "be corrupt"
                )
        raise MeshError(f"{path}: cannot parse the vertices; the file may be corrupt")
    V = V.reshape(-1, 3)
    if not flines:
        return V, np.zeros((0, 3), dtype=np.int64)
    # faces: 'f a b c ...' with a = 'i', 'i/t', 'i//n' or 'i/t/n'; only i is kept
    ncorners = np.fromiter((len(ln.split()) for ln in flines), dtype=np.int64, count=len(flines))
    idx = _parse_numbers(_SLASH_SUFFIX.sub("", " ".join(flines)), np.int64, int(ncorners.sum()))
    if idx is None:
        raise MeshError(
            f"{path}: cannot parse the face indices; each 'f' line needs three or more "
            "integer vertex references, the file may be corrupt"
        )
    # OBJ is 1-based; 0 is invalid and becomes -1 so that the range check reports it
    F = np.where(idx > 0, idx - 1, -1)
    neg = idx < 0
    if neg.any():
        # negative indices count back from the last vertex defined before the face line
        vpos = np.fromiter((m.start() for m in _OBJ_V.finditer(text)), dtype=np.int64)
        fpos = np.fromiter((m.start() for m in _OBJ_F.finditer(text)), dtype=np.int64)
        nv = np.repeat(np.searchsorted(vpos, fpos), ncorners)
        F = np.where(neg, nv + np.maximum(idx, -(2**62)), F)

    def locate(j: int) -> str:
        return f"face {j} (line {_line_of(text, _OBJ_F, j)})"

    return V, _polygons_to_triangles(path, V, ncorners, F, locate)


# ------------------------------------------------------------------ OFF
def _parse_off(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """Fast reader of plain ASCII triangle OFF files (the common case), or None.

    Handles ``#`` comments, blank lines and counts on the header line or the next; returns
    None for anything else (coloured OFF, extra columns, polygons other than triangles, a
    short or malformed file), which then goes to :func:`_read_off` and its error messages.
    About 10x faster than ``trimesh.load``.
    """
    raw = _file_bytes(path)
    try:
        text = raw.decode("ascii")
    except UnicodeDecodeError:
        return None
    if "#" in text:
        text = "\n".join(line.split("#", 1)[0] for line in text.splitlines())
    lines = [ln for ln in text.splitlines() if ln.strip()]
    if not lines:
        return None
    head = lines[0].split()
    if head[0] != "OFF":
        return None
    counts, start = head[1:], 1
    if not counts:
        if len(lines) < 2:
            return None
        counts, start = lines[1].split(), 2
    try:
        nv, nf = int(counts[0]), int(counts[1])
    except (IndexError, ValueError):
        return None
    if nv <= 0 or nf <= 0 or len(lines) != start + nv + nf:
        return None
    if any(len(ln.split()) != 3 for ln in lines[start : start + nv]):  # ~10 ms for 60k
        return None  # (a short line and a long one would shift coordinates silently)
    V = _parse_numbers(" ".join(lines[start : start + nv]), np.float64, 3 * nv)
    F = _parse_numbers(" ".join(lines[start + nv :]), np.int64, 4 * nf)
    if V is None or F is None:
        return None
    F = F.reshape(nf, 4)
    if not bool((F[:, 0] == 3).all()):
        return None
    return V.reshape(nv, 3), F[:, 1:]


def _read_off(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Any ASCII OFF file: polygons, colours, extra vertex columns; precise error messages."""
    text = _file_bytes(path).decode("utf-8", errors="replace")

    def fail(what: str) -> MeshError:
        return MeshError(f"{path}: could not read the file as OFF: {what}")

    if "\x00" in text:
        raise fail(
            "it holds binary data (binary OFF is not supported); convert it to ASCII OFF or "
            "PLY (e.g. with MeshLab)"
        )
    lines = text.splitlines()
    if "#" in text:
        lines = [ln.split("#", 1)[0] for ln in lines]
    toks = [ln.split() for ln in lines]
    keep = [i for i, t in enumerate(toks) if t]
    if len(keep) != len(toks):
        lines, toks = [lines[i] for i in keep], [toks[i] for i in keep]
    lineno = [i + 1 for i in keep]  # line numbers in the file, for messages
    if not toks:
        raise fail("it is empty; check the file")
    key = toks[0][0]
    if not re.fullmatch(r"(ST)?C?N?4?n?OFF", key):
        raise fail(
            f"it does not start with 'OFF' (found {key[:20]!r} on line {lineno[0]}); check "
            "that it is an OFF file"
        )
    if "4" in key or "n" in key:
        raise fail(
            f"{key!r} files (4D or nD vertices) are not supported; convert it to a 3D OFF, OBJ "
            "or PLY file"
        )
    rest, start = toks[0][1:], 1
    if rest and rest[0].upper() == "BINARY":
        raise fail("binary OFF is not supported; convert it to ASCII OFF or PLY (e.g. MeshLab)")
    if not rest:
        if len(toks) < 2:
            raise fail("no vertex and face counts after the header; the file is truncated")
        rest, start = toks[1], 2
    head = lineno[start - 1]
    try:
        nv, nf = int(rest[0]), int(rest[1])
    except (IndexError, ValueError):
        raise fail(
            f"line {head} should hold the vertex and face counts, found "
            f"{' '.join(rest)[:40]!r}; fix the header"
        ) from None
    if nv < 0 or nf < 0:
        raise fail(f"negative counts ({nv} vertices, {nf} faces) on line {head}; fix the header")
    have = len(toks) - start
    if have < nv + nf:
        raise fail(
            f"line {head} declares {nv} vertices and {nf} faces but {have} lines follow; the "
            "file is truncated or the counts are wrong"
        )
    if have > nv + nf:
        raise fail(
            f"{have - nv - nf} lines after the {nv} vertices and {nf} faces declared on line "
            f"{head} (from line {lineno[start + nv + nf]}); the counts are wrong or the file is "
            "corrupt, fix it"
        )
    # vertices: x y z and maybe colour, normal, texture columns (ignored)
    vt = toks[start : start + nv]
    width = np.fromiter(map(len, vt), dtype=np.int64, count=nv)
    V = None
    if nv and (width == width[0]).all() and width[0] >= 3:
        V = _parse_numbers(" ".join(lines[start : start + nv]), np.float64, nv * int(width[0]))
        V = None if V is None else V.reshape(nv, -1)[:, :3]
    elif (width >= 3).all():
        V = _parse_numbers(" ".join([" ".join(t[:3]) for t in vt]), np.float64, 3 * nv)
    if V is None:
        for k, t in enumerate(vt):
            if len(t) < 3 or _parse_numbers(" ".join(t[:3]), np.float64, 3) is None:
                raise fail(
                    f"cannot parse vertex {k} on line {lineno[start + k]} "
                    f"({' '.join(t)[:60]!r}); each vertex line needs three numbers, the file "
                    "may be corrupt or the counts wrong"
                )
        raise fail("cannot parse the vertices")
    V = np.ascontiguousarray(V).reshape(nv, 3)
    if nf == 0:
        raise _no_faces(path)
    # faces: 'k i1 .. ik' and maybe a colour (ignored)
    f0 = start + nv
    ft = toks[f0:]
    ntok = np.fromiter(map(len, ft), dtype=np.int64, count=nf)
    counts = _parse_numbers(" ".join([t[0] for t in ft]), np.int64, nf)
    if counts is None or (counts < 0).any() or (ntok < counts + 1).any():
        for k, t in enumerate(ft):
            c = _parse_numbers(t[0], np.int64, 1)
            if c is None or c[0] < 0 or len(t) < int(c[0]) + 1:
                raise fail(
                    f"cannot parse face {k} on line {lineno[f0 + k]} ({' '.join(t)[:60]!r}); a "
                    "face line is a corner count then that many vertex indices, the file may "
                    "be corrupt or the counts wrong"
                )
        raise fail("cannot parse the faces")
    corners = None
    if (ntok == counts + 1).all():  # no colours: every number but the counts
        every = _parse_numbers(" ".join(lines[f0:]), np.int64, int(ntok.sum()))
        if every is not None:
            mask = np.ones(every.size, dtype=bool)
            mask[np.cumsum(ntok) - ntok] = False
            corners = every[mask]
    else:
        corners = _parse_numbers(
            " ".join([" ".join(t[1 : 1 + int(c)]) for t, c in zip(ft, counts, strict=True)]),
            np.int64,
            int(counts.sum()),
        )
    if corners is None:
        for k, (t, c) in enumerate(zip(ft, counts, strict=True)):
            if _parse_numbers(" ".join(t[1 : 1 + int(c)]), np.int64, int(c)) is None:
                raise fail(
                    f"face {k} on line {lineno[f0 + k]} has vertex indices that are not "
                    f"integers ({' '.join(t)[:60]!r}); the file may be corrupt"
                )
        raise fail("cannot parse the faces")

    def locate(j: int) -> str:
        return f"face {j} (line {lineno[f0 + j]})"

    return V, _polygons_to_triangles(path, V, counts, corners, locate)


# ------------------------------------------------------------------ PLY
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}


_STRUCT_CODES = {"i1": "b", "u1": "B", "i2": "h", "u2": "H", "i4": "i", "u4": "I", "f4": "f",
                 "f8": "d"}


class _PlyElement:
    """One ``element`` of a PLY header: name, count, properties ``(name, type, list type)``."""

    def __init__(self, name: str, count: int) -> None:
        self.name = name
        self.count = count
        self.props: list[tuple[str, str, str | None]] = []  # (name, value type, count type)

    @property
    def has_lists(self) -> bool:
        return any(p[2] is not None for p in self.props)


def _ply_error(path: Path, what: str) -> MeshError:
    return MeshError(f"{path}: could not read the file as PLY: {what}")


def _ply_header(path: Path, raw: bytes) -> tuple[str, list[_PlyElement], int]:
    """Format, elements and the offset of the body of a PLY file."""
    if not raw.startswith(b"ply"):
        raise _ply_error(path, "it does not start with 'ply'; check that it is a PLY file")
    m = re.search(rb"(^|[\r\n])end_header[ \t]*(\r\n|\n|\r)", raw[: 1 << 20])
    if m is None:
        raise _ply_error(
            path, "no 'end_header' line in its first MB; the file is truncated or not a PLY file"
        )
    fmt = None
    elements: list[_PlyElement] = []
    for no, line in enumerate(raw[: m.start()].decode("ascii", errors="replace").splitlines()):
        t = line.split()
        if not t or t[0] in ("ply", "comment", "obj_info"):
            continue
        bad = f"header line {no + 1} ({line.strip()[:60]!r}) is malformed; fix the header"
        if t[0] == "format":
            if len(t) < 2 or t[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise _ply_error(path, bad)
            fmt = t[1]
        elif t[0] == "element":
            if len(t) != 3 or not re.fullmatch(r"\d+", t[2]):
                raise _ply_error(path, bad)
            elements.append(_PlyElement(t[1], int(t[2])))
        elif t[0] == "property":
            if not elements:
                raise _ply_error(path, bad)
            if len(t) == 3 and t[1] in _PLY_TYPES:
                elements[-1].props.append((t[2], _PLY_TYPES[t[1]], None))
            elif len(t) == 5 and t[1] == "list" and t[2] in _PLY_TYPES and t[3] in _PLY_TYPES:
                if _PLY_TYPES[t[2]][0] == "f":
                    raise _ply_error(path, bad)
                elements[-1].props.append((t[4], _PLY_TYPES[t[3]], _PLY_TYPES[t[2]]))
            else:
                raise _ply_error(path, bad)
        else:
            raise _ply_error(path, bad)
    if fmt is None:
        raise _ply_error(path, "no 'format' line in the header; fix the header")
    return fmt, elements, m.end()


def _ply_ascii(
    path: Path, raw: bytes, body: int, elements: list[_PlyElement], key: str
) -> tuple[dict[str, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Scalar columns of ``vertex`` and the ``key`` lists of ``face`` of an ASCII PLY body.

    Returns ``({property: column}, (counts, flat values))``; one row per line.
    """
    text = raw[body:].decode("ascii", errors="replace")
    lines = [t for t in (ln.split() for ln in text.splitlines()) if t]
    elements = [e for e in elements if e.props]  # rows without properties are blank lines
    need = sum(e.count for e in elements)
    declared = ", ".join(f"{e.count} {e.name}" for e in elements)
    if len(lines) != need:
        raise _ply_error(
            path, f"the header declares {need} rows ({declared}) but the body has "
            f"{len(lines)} lines; the file is truncated or corrupt, or the counts are wrong",
        )
    vertex: dict[str, np.ndarray] = {}
    faces = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    pos = 0
    for e in elements:
        rows = lines[pos : pos + e.count]
        first = pos + 1
        pos += e.count
        if e.name == "vertex":  # scalar properties only (checked by the caller)
            width = len(e.props)
            vals = None
            if all(len(t) == width for t in rows):
                vals = _parse_numbers(" ".join(" ".join(t) for t in rows), np.float64,
                                      width * e.count)
            if vals is None:
                k = next((i for i, t in enumerate(rows) if len(t) != width or _parse_numbers(
                    " ".join(t), np.float64, width) is None), 0)
                raise _ply_error(
                    path, f"cannot parse vertex {k} (line {first + k} of the body: "
                    f"{' '.join(rows[k])[:60]!r}); it should hold {width} numbers, the file "
                    "is corrupt or the header wrong",
                )
            vals = vals.reshape(e.count, width)
            # values as stored: 'float' properties are float32, as in a binary file
            with np.errstate(over="ignore"):  # 1e39 is inf in float32 (validation says so)
                vertex = {
                    name: vals[:, i].astype(np.float32) if t == "f4" else vals[:, i]
                    for i, (name, t, _) in enumerate(e.props)
                }
        elif e.name == "face":
            faces = _ply_ascii_lists(path, rows, e, key, first)
    return vertex, faces


def _ply_ascii_lists(
    path: Path, rows: list[list[str]], e: _PlyElement, key: str, first: int
) -> tuple[np.ndarray, np.ndarray]:
    """Counts and flat values of the list property ``key`` of ASCII rows of element ``e``."""
    n = len(rows)
    ntok = np.fromiter(map(len, rows), dtype=np.int64, count=n)
    # float index lists (legal, odd) are parsed as floats; the caller checks they are integers
    vtype = np.float64 if next(p[1] for p in e.props if p[0] == key)[0] == "f" else np.int64
    if len(e.props) == 1:  # the usual face layout: 'count i0 i1 ...' and nothing else
        counts = _parse_numbers(" ".join(t[0] for t in rows), np.int64, n)
        if counts is not None and (counts >= 0).all() and (ntok == counts + 1).all():
            flat = _parse_numbers(" ".join(" ".join(t[1:]) for t in rows), vtype,
                                  int(counts.sum()))
            if flat is not None:
                return counts, flat
    cnt: list[int] = []
    vals: list[str] = []
    for k, t in enumerate(rows):
        i = 0
        try:
            for name, _, ctype in e.props:
                if ctype is None:
                    i += 1
                    continue
                c = int(t[i])
                if c < 0 or i + 1 + c > len(t):
                    raise ValueError
                if name == key:
                    cnt.append(c)
                    vals.extend(t[i + 1 : i + 1 + c])
                i += 1 + c
            if i != len(t):
                raise ValueError
            if _parse_numbers(" ".join(vals[len(vals) - cnt[-1]:]), vtype, cnt[-1]) is None:
                raise ValueError
        except (ValueError, IndexError):
            raise _ply_error(
                path, f"cannot parse {e.name} {k} (line {first + k} of the body: "
                f"{' '.join(t)[:60]!r}); it does not match the header's properties or holds "
                "indices that are not integers, the file is corrupt"
            ) from None
    flat = _parse_numbers(" ".join(vals), vtype, len(vals))
    if flat is None:  # pragma: no cover - every row was parsed above
        raise _ply_error(path, f"cannot parse the {e.name} lists; the file is corrupt")
    return np.array(cnt, dtype=np.int64), flat


def _ply_binary(
    path: Path, raw: bytes, body: int, elements: list[_PlyElement], key: str, endian: str
) -> tuple[dict[str, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Same as :func:`_ply_ascii` for a binary body of either byte order."""
    vertex: dict[str, np.ndarray] = {}
    faces = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    off = body
    size = len(raw)

    def short(name: str) -> MeshError:
        return _ply_error(
            path, f"the {name} rows end past the end of the file; the file is truncated or the "
            "header's counts are wrong"
        )

    for e in elements:
        if not e.has_lists:
            rec = np.dtype([(f"p{i}", endian + p[1]) for i, p in enumerate(e.props)])
            if off + rec.itemsize * e.count > size:
                raise short(e.name)
            arr = np.frombuffer(raw, dtype=rec, count=e.count, offset=off)
            off += rec.itemsize * e.count
            if e.name == "vertex":
                vertex = {p[0]: arr[f"p{i}"] for i, p in enumerate(e.props)}
            continue
        # rows of variable size: walk them, reading only the list counts
        fmts = [
            (struct.Struct(endian + _STRUCT_CODES[p[2] or p[1]]), np.dtype(p[1]).itemsize, p[2])
            for p in e.props
        ]
        ikey = next(i for i, p in enumerate(e.props) if p[0] == key) if e.name == "face" else -1
        if len(fmts) == 1 and e.count and off + fmts[0][0].size <= size:
            # the usual face layout, all rows alike ('3 i j k' each): one structured read
            st, isize, ctype = fmts[0]
            (c0,) = st.unpack_from(raw, off)
            if 0 <= c0 and off + (st.size + c0 * isize) * e.count <= size:
                rec = np.dtype([("c", endian + str(ctype)), ("v", endian + e.props[0][1], (c0,))])
                arr = np.frombuffer(raw, dtype=rec, count=e.count, offset=off)
                if (arr["c"] == c0).all():
                    off += rec.itemsize * e.count
                    if e.name == "face":
                        faces = (np.full(e.count, c0, dtype=np.int64), arr["v"].ravel())
                    continue
        starts: list[int] = []
        counts: list[int] = []
        for _ in range(e.count):
            for i, (st, isize, ctype) in enumerate(fmts):
                if ctype is None:
                    off += st.size
                    continue
                if off + st.size > size:
                    raise short(e.name)
                (c,) = st.unpack_from(raw, off)
                off += st.size
                if c < 0:
                    raise _ply_error(
                        path, f"a {e.name} list has a negative length ({c}); the file is corrupt"
                    )
                if i == ikey:
                    starts.append(off)
                    counts.append(c)
                off += c * isize
            if off > size:
                raise short(e.name)
        if e.name == "face":
            cnt = np.array(counts, dtype=np.int64)
            isize = fmts[ikey][1]
            # byte offsets of every value of every row, then one gather
            before = np.cumsum(cnt) - cnt
            pos = np.repeat(np.array(starts, dtype=np.int64) - before * isize, cnt)
            pos = pos + np.arange(int(cnt.sum()), dtype=np.int64) * isize
            byte = np.frombuffer(raw, dtype=np.uint8)
            vals = byte[pos[:, None] + np.arange(isize)].view(endian + e.props[ikey][1]).ravel()
            faces = (cnt, vals)
    return vertex, faces


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """ASCII or binary PLY: ``x y z`` of ``vertex``, the index list of ``face``, in order."""
    raw = _file_bytes(path)
    fmt, elements, body = _ply_header(path, raw)
    names = [e.name for e in elements]
    vert = elements[names.index("vertex")] if "vertex" in names else None
    if vert is None:
        raise _ply_error(path, "no 'vertex' element in the header; the file holds no vertices")
    if not {"x", "y", "z"} <= {p[0] for p in vert.props}:
        raise _ply_error(path, "the 'vertex' element has no x, y, z properties; fix the header")
    if vert.has_lists:
        raise _ply_error(
            path, "the 'vertex' element has list properties, which this reader does not "
            "support; save the file without them (e.g. with MeshLab)"
        )
    face = elements[names.index("face")] if "face" in names else None
    if face is None or face.count == 0:
        raise _no_faces(path)
    lists = [p[0] for p in face.props if p[2] is not None]
    key: str | None = next((n for n in ("vertex_indices", "vertex_index") if n in lists), None)
    if key is None and len(lists) == 1:
        key = lists[0]
    if key is None:
        raise _ply_error(
            path, "the 'face' element has no 'vertex_indices' list property; fix the header"
        )
    if fmt == "ascii":
        vertex, (counts, corners) = _ply_ascii(path, raw, body, elements, key)
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        vertex, (counts, corners) = _ply_binary(path, raw, body, elements, key, endian)
    V = np.stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"], axis=1)
    if corners.dtype.kind == "f":  # float indices (odd but legal): must be integers
        if not np.isfinite(corners).all() or (corners != np.round(corners)).any():
            raise _ply_error(path, "the face indices are not integers; the file is corrupt")
        if corners.size and np.abs(corners).max() >= 2**62:
            raise _ply_error(path, "the face indices are out of range; the file is corrupt")
    corners = corners.astype(np.int64)
    return V, _polygons_to_triangles(path, V, counts, corners, lambda j: f"face {j}")


# ------------------------------------------------------------------ STL, GLB, glTF
def _load_trimesh(path: Path, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and faces of every triangle mesh trimesh finds in ``path``, concatenated.

    ``trimesh.load(path, process=False)``; a scene is flattened by ``Scene.dump`` (node
    transforms applied, in the order of its graph). Vertices are not merged here.
    """
    import trimesh

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            loaded = trimesh.load(path, process=False, file_type=fmt.lower())
            parts = loaded.dump() if isinstance(loaded, trimesh.Scene) else [loaded]
            meshes = [
                (np.asarray(g.vertices, dtype=np.float64), np.asarray(g.faces, dtype=np.int64))
                for g in parts
                if isinstance(g, trimesh.Trimesh)
            ]
    except Exception as exc:  # trimesh raises many kinds of errors on bad input
        raise MeshError(
            f"{path}: could not read the file as {fmt} ({type(exc).__name__}: {exc}); "
            f"check that it is a valid, complete {fmt} file (it may be truncated or corrupt)"
        ) from exc
    meshes = [(v.reshape(-1, 3), f.reshape(-1, 3)) for v, f in meshes if f.size]
    if not meshes:
        raise _no_faces(path)
    shift = np.cumsum([0] + [v.shape[0] for v, _ in meshes[:-1]])
    V = np.concatenate([v for v, _ in meshes])
    F = np.concatenate([f + s for (_, f), s in zip(meshes, shift, strict=True)])
    return V, F


def _merge_vertices(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical coordinates, drop unused ones; order of first appearance.

    ``-0.0`` equals ``0.0``; NaN coordinates are never merged. Face indices must be in range.

    Examples
    --------
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    >>> V2, F2 = _merge_vertices(V, np.array([[0, 1, 2], [3, 5, 4]]))
    >>> V2.tolist(), F2.tolist()
    ([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0]], [[0, 1, 2], [1, 3, 2]])
    """
    Vc = np.ascontiguousarray(V, dtype=np.float64) + 0.0  # -0.0 + 0.0 == +0.0
    key = Vc.view(np.dtype((np.void, Vc.dtype.itemsize * 3))).ravel()
    _, first, inverse = np.unique(key, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    F2 = rank[inverse.ravel()][F]
    used = np.zeros(order.size, dtype=bool)
    used[F2.ravel()] = True
    renum = np.cumsum(used) - 1
    return Vc[first[order][used]], renum[F2]


def _read_merged(path: Path, fmt: str) -> tuple[np.ndarray, np.ndarray]:
    V, F = _load_trimesh(path, fmt)
    bad = (F < 0) | (F >= V.shape[0])
    if bad.any():
        raise MeshError(
            f"{path}: face indices out of range (e.g. {int(F[bad][0])}, valid: 0.."
            f"{V.shape[0] - 1}); the file is corrupt, fix the face list"
        )
    return _merge_vertices(V, F)


def read_arrays(path: str | os.PathLike[str]) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a mesh file (no validation, no torch).

    OFF, OBJ and PLY files keep every vertex in file order; STL, GLB and glTF files have
    their exact-duplicate vertices merged, in order of first appearance (see the module
    docstring). Polygons are triangulated (:func:`triangulate_polygons`).

    Parameters
    ----------
    path : str or os.PathLike
        ``.off``, ``.obj``, ``.ply``, ``.stl``, ``.glb`` or ``.gltf`` file (the extension
        decides, case-insensitive); OFF, OBJ and PLY also compressed (``.off.gz``,
        ``.ply.bz2``, ``.obj.xz``).

    Returns
    -------
    V : numpy.ndarray of float64, shape (n, 3)
    F : numpy.ndarray of int64, shape (m, 3)
        Zero-based; triangle indices are not range-checked here (:class:`~torchheat.mesh.Mesh`
        does).

    Raises
    ------
    MeshError
        Missing, unreadable or unsupported file, no faces, malformed numbers or counts,
        polygons with fewer than three or repeated corners, or polygon indices out of range.

    Examples
    --------
    >>> read_arrays("missing.off")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    torchheat.meshio.MeshError: missing.off: no such file; check the path ...
    """
    p = Path(path)
    if not p.exists():
        raise MeshError(
            f"{path}: no such file; check the path (relative paths start at {Path.cwd()})"
        )
    if p.is_dir():
        raise MeshError(f"{path}: is a directory, not a mesh file; pass the path of a file")
    ext = p.suffix.lower()
    if ext in COMPRESSED:  # cat0.off.gz: the format is the extension before
        inner = Path(p.stem).suffix.lower()
        if inner not in ORDER_KEEPING_FORMATS:
            raise MeshError(
                f"{path}: a compressed {inner or 'file without a mesh extension'} is not read; "
                f"compressed {', '.join(ORDER_KEEPING_FORMATS)} files are (e.g. mesh.off.gz), "
                "otherwise decompress it first"
            )
        ext = inner
    elif ext not in SUPPORTED_FORMATS:
        raise MeshError(
            f"{path}: unsupported mesh format {p.suffix or '(no extension)'!r}; supported "
            f"formats are {', '.join(SUPPORTED_FORMATS)}, OFF, OBJ and PLY also compressed "
            f"({', '.join(COMPRESSED)}) (convert it, e.g. with trimesh or MeshLab)"
        )
    try:
        if ext == ".obj":
            V, F = _parse_obj(p)
        elif ext == ".off":
            fast = _parse_off(p)
            V, F = fast if fast is not None else _read_off(p)
        elif ext == ".ply":
            V, F = _read_ply(p)
        else:
            V, F = _read_merged(p, ext[1:].upper())
    except OSError as exc:
        raise MeshError(f"{path}: cannot read the file ({exc}); check its permissions") from exc
    except MemoryError as exc:
        raise MeshError(
            f"{path}: not enough memory to read the file; its counts may be corrupt"
        ) from exc
    if F.shape[0] == 0:
        raise _no_faces(p)
    return np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)
