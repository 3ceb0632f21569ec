"""Pictures of correspondences: colour transfer through a vertex map.

:func:`color_transfer` paints the target with a smooth colour field (RGB from its normalised
x, y, z coordinates) and pulls the colours back to the source through the map
(``colour_src[x] = colour_tgt[map[x]]``): a correct map shows the same colours at
corresponding places, a wrong one shows patches of foreign colour, a mirror map shows the
colours swapped left/right.

Rendering is a small painter's-algorithm projection drawn with matplotlib's 2D
``PolyCollection`` on an Agg canvas created directly (the global backend is not touched):
orthographic camera, Lambert shading, faces sorted back to front. This is much faster than
``mpl_toolkits.mplot3d`` (a 20k-vertex / 40k-face mesh renders in about a second per panel);
meshes with more than ``max_faces`` faces are drawn as a depth-sorted vertex scatter instead.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ._arrays import to_numpy
from ._files import atomic_write

if TYPE_CHECKING:  # pragma: no cover
    from .mesh import Mesh

__all__ = ["color_transfer", "coordinate_colors", "view_direction", "picture_format"]

#: Picture formats :func:`color_transfer` writes, chosen by the file's extension
PICTURE_FORMATS = ("png", "pdf", "svg", "jpg", "jpeg")


def picture_format(path: str | os.PathLike[str]) -> str:
    """The format of a picture file from its extension: one of :data:`PICTURE_FORMATS`
    (``"png"`` for a name without one); a ``ValueError`` for any other.

    Examples
    --------
    >>> picture_format("cat.PDF"), picture_format("cat")
    ('pdf', 'png')
    """
    suffix = Path(path).suffix.lower().lstrip(".")
    if not suffix:
        return "png"
    if suffix not in PICTURE_FORMATS:
        raise ValueError(f"{path}: unknown picture format '.{suffix}'; use .png, .pdf, .svg "
                         "or .jpg")
    return suffix


def _arrays(mesh: Any) -> tuple[np.ndarray, np.ndarray]:
    """``(V, F)`` as float64 / int64 numpy arrays from a Mesh or a pair."""
    if hasattr(mesh, "numpy") and callable(mesh.numpy):
        V, F = mesh.numpy()
    else:
        V, F = mesh
    return to_numpy(V, dtype=np.float64), to_numpy(F, dtype=np.int64)


def _label(mesh: Any, default: str) -> str:
    name = getattr(mesh, "name", None)
    return Path(name).name if name else default


def coordinate_colors(V: np.ndarray) -> np.ndarray:
    """Smooth RGB colour field from the normalised vertex coordinates.

    Parameters
    ----------
    V : numpy.ndarray, shape (n, 3)
        Vertex coordinates.

    Returns
    -------
    numpy.ndarray, shape (n, 3)
        RGB in ``[0.1, 0.95]`` (x -> red, y -> green, z -> blue, each rescaled to the
        bounding box).

    Examples
    --------
    >>> import numpy as np
    >>> coordinate_colors(np.array([[0.0, 0, 0], [1, 2, 3]])).tolist()
    [[0.1, 0.1, 0.1], [0.95, 0.95, 0.95]]
    """
    V = np.asarray(V, dtype=np.float64)
    lo, hi = V.min(axis=0), V.max(axis=0)
    span = np.where(hi - lo > 0, hi - lo, 1.0)
    return 0.1 + 0.85 * (V - lo) / span


def _face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Area-weighted (unnormalised) face normals, shape (m, 3)."""
    return np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])


def view_direction(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """A camera direction (unit vector from the shape towards the viewer).

    For an open surface whose area-weighted mean normal is substantial (a face, a height
    field) the camera looks at its front; otherwise (closed shapes) a fixed oblique view
    ``(1, 0.6, 1.6)`` (normalised) is used.

    Parameters
    ----------
    V : numpy.ndarray, shape (n, 3)
    F : numpy.ndarray, shape (m, 3)

    Returns
    -------
    numpy.ndarray, shape (3,)

    Examples
    --------
    >>> import numpy as np
    >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]])
    >>> view_direction(V, np.array([[0, 1, 2]])).round(3).tolist()
    [0.0, 0.0, 1.0]
    """
    fn = _face_normals(V, F)
    total = fn.sum(axis=0)
    area = np.linalg.norm(fn, axis=1).sum()
    if area > 0 and np.linalg.norm(total) > 0.2 * area:
        return total / np.linalg.norm(total)
    d = np.array([1.0, 0.6, 1.6])
    return d / np.linalg.norm(d)


def _camera(view: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Orthonormal screen basis ``(right, up, towards viewer)`` for a view direction."""
    d = np.asarray(view, dtype=np.float64)
    d = d / np.linalg.norm(d)
    world_up = np.array([0.0, 1.0, 0.0]) if abs(d[1]) < 0.9 else np.array([0.0, 0.0, 1.0])
    right = np.cross(world_up, d)
    right /= np.linalg.norm(right)
    up = np.cross(d, right)
    return right, up, d


def _draw_panel(
    ax: Any,
    V: np.ndarray,
    F: np.ndarray,
    vertex_values: np.ndarray,
    view: np.ndarray,
    *,
    cmap: Any = None,
    norm: Any = None,
    max_faces: int,
) -> Any:
    """Draw one shaded mesh into a 2D axes; returns the artist."""
    from matplotlib.collections import PolyCollection

    right, up, d = _camera(view)
    centre = 0.5 * (V.min(axis=0) + V.max(axis=0))
    P = V - centre
    xy = np.stack([P @ right, P @ up], axis=1)
    depth = P @ d
    if cmap is not None:
        rgb_v = np.asarray(cmap(norm(vertex_values)))[:, :3]
    else:
        rgb_v = np.asarray(vertex_values, dtype=np.float64)[:, :3]

    if F.shape[0] > max_faces:  # fast path: depth-sorted vertex scatter
        vn = np.zeros_like(V)
        fn = _face_normals(V, F)
        for k in range(3):
            np.add.at(vn, F[:, k], fn)
        vn /= np.maximum(np.linalg.norm(vn, axis=1, keepdims=True), 1e-300)
        shade = 0.35 + 0.65 * np.abs(vn @ d)
        order = np.argsort(depth)
        art = ax.scatter(xy[order, 0], xy[order, 1], s=1.0, linewidths=0,
                         c=np.clip(rgb_v[order] * shade[order, None], 0, 1))
    else:
        fn = _face_normals(V, F)
        fn /= np.maximum(np.linalg.norm(fn, axis=1, keepdims=True), 1e-300)
        shade = 0.35 + 0.65 * np.abs(fn @ d)  # two-sided Lambert
        rgb_f = rgb_v[F].mean(axis=1) * shade[:, None]
        order = np.argsort(depth[F].mean(axis=1))  # back to front
        colors = np.clip(rgb_f[order], 0.0, 1.0)
        art = PolyCollection(xy[F[order]], facecolors=colors, edgecolors=colors,
                             linewidths=0.25, antialiased=False)
        ax.add_collection(art)
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    pad = 0.03 * float((hi - lo).max())
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(lo[1] - pad, hi[1] + pad)
    ax.set_aspect("equal")
    ax.set_axis_off()
    return art


def _check_map(fmap: Any, n_source: int, n_target: int) -> np.ndarray:
    f = to_numpy(fmap).reshape(-1)
    if f.size != n_source:
        raise ValueError(
            f"map has {f.size} entries but the source has {n_source} vertices; pass one "
            "target index per source vertex"
        )
    if not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"map has dtype {f.dtype}; pass integer target vertex indices")
    if f.size and (f.min() < 0 or f.max() >= n_target):
        raise ValueError(
            f"map indices must lie in 0..{n_target - 1} (target vertices), found "
            f"{int(f.min())}..{int(f.max())}"
        )
    return f.astype(np.int64, copy=False)


def color_transfer(
    source: Mesh | tuple[Any, Any],
    target: Mesh | tuple[Any, Any],
    fmap: Any,
    path: str | os.PathLike[str],
    *,
    title: str | None = None,
    errors: Any = None,
    view: Sequence[float] | None = None,
    max_faces: int = 300_000,
    dpi: int = 110,
) -> Path:
    """Write a picture (PNG; PDF, SVG or JPEG by the extension) showing a vertex map as a
    colour transfer.

    Left panel: the target coloured by RGB = its normalised x, y, z coordinates. Middle
    panel: the source, vertex ``x`` coloured like target vertex ``fmap[x]``. With ``errors``,
    a third panel shows the source coloured by the per-vertex error, with a colour bar.
    Both meshes are drawn by the same orthographic camera (same view direction, each shape
    centred in its panel).

    Parameters
    ----------
    source : Mesh or (V, F)
        Source shape, ``n`` vertices.
    target : Mesh or (V, F)
        Target shape, ``m`` vertices.
    fmap : array_like or torch.Tensor of int, shape (n,)
        Target vertex of every source vertex (0-based).
    path : str or os.PathLike
        Output picture, its format from the extension (:func:`picture_format`). Written
        atomically (a temporary file in the same directory, then
        ``os.replace``): on failure no partial file is left behind.
    title : str, optional
        Figure title.
    errors : array_like, shape (n,), optional
        Error of every source vertex (e.g. geodesic error / sqrt(area)); adds the third panel.
    view : sequence of 3 floats, optional
        Direction from the shapes towards the camera (default: :func:`view_direction` of the
        target).
    max_faces : int
        Above this many faces a mesh is drawn as a vertex scatter (faster, coarser).
    dpi : int
        Resolution (each panel is 4.5 x 4.5 inches).

    Returns
    -------
    pathlib.Path
        ``path``.

    Raises
    ------
    ValueError
        ``fmap`` (or ``errors``) of the wrong length, dtype or range.
    OSError
        The file cannot be written.

    Examples
    --------
    >>> import numpy as np, trimesh, tempfile, os
    >>> from torchheat import Mesh
    >>> s = trimesh.creation.icosphere(2)
    >>> M = Mesh(s.vertices, s.faces)
    >>> out = os.path.join(tempfile.mkdtemp(), "identity.png")
    >>> color_transfer(M, M, np.arange(M.n_vertices), out).suffix
    '.png'
    """
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    Vs, Fs = _arrays(source)
    Vt, Ft = _arrays(target)
    f = _check_map(fmap, len(Vs), len(Vt))
    err = None
    if errors is not None:
        err = to_numpy(errors, dtype=np.float64).reshape(-1)
        if err.size != len(Vs):
            raise ValueError(
                f"errors has {err.size} entries but the source has {len(Vs)} vertices"
            )
    cam = view_direction(Vt, Ft) if view is None else np.asarray(view, dtype=np.float64)
    colors_t = coordinate_colors(Vt)
    colors_s = colors_t[f]

    panels = 2 if err is None else 3
    fig = Figure(figsize=(4.5 * panels, 4.9 if title else 4.6), dpi=dpi)
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, panels, squeeze=False)[0]
    _draw_panel(axes[0], Vt, Ft, colors_t, cam, max_faces=max_faces)
    axes[0].set_title(f"target: {_label(target, 'target')}\n(colour = normalised x, y, z)",
                      fontsize=9)
    _draw_panel(axes[1], Vs, Fs, colors_s, cam, max_faces=max_faces)
    axes[1].set_title(f"source: {_label(source, 'source')}\n(colour pulled back through the map)",
                      fontsize=9)
    if err is not None:
        finite = err[np.isfinite(err)]
        vmax = float(np.percentile(finite, 99)) if finite.size else 1.0
        norm = Normalize(vmin=0.0, vmax=vmax if vmax > 0 else 1.0)
        cmap = colormaps["viridis"]
        _draw_panel(axes[2], Vs, Fs, np.nan_to_num(err, nan=vmax), cam, cmap=cmap, norm=norm,
                    max_faces=max_faces)
        axes[2].set_title("error per source vertex", fontsize=9)
        from matplotlib.cm import ScalarMappable

        fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ax=axes[2], fraction=0.046,
                     pad=0.02)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.subplots_adjust(left=0.01, right=0.97 if err is not None else 0.99, bottom=0.01,
                        top=0.86 if title else 0.9, wspace=0.04)

    fmt = picture_format(path)
    return atomic_write(Path(path), lambda tmp: fig.savefig(tmp, format=fmt, dpi=dpi))
