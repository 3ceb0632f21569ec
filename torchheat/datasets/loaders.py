"""Loaders of the benchmark folders in ``shared/data`` (TOSCA 5k, SCAPE, TOSCA high
resolution, KIDS, SHREC'16 partial) and of any folder of meshes; the data root.
"""

from __future__ import annotations

import fnmatch
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..meshio import COMPRESSED, ORDER_KEEPING_FORMATS, SUPPORTED_FORMATS
from .cache import PathLike
from .ground_truth import BarycentricGT, VtsGT, VtsSymmetryGT
from .pairs import PairCollection
from .shapes import ShapeCollection, _class_from_stem, _natural_key


# --------------------------------------------------------------------------------------------
# data folders
# --------------------------------------------------------------------------------------------
def data_root(root: PathLike | None = None) -> Path:
    """Folder holding the datasets: ``root``, else ``$TORCHHEAT_DATA``, else
    ``<repo>/../shared/data``.

    Raises
    ------
    FileNotFoundError
        With instructions, if the folder does not exist.
    """
    if root is None:
        env = os.environ.get("TORCHHEAT_DATA")
        root = env if env else Path(__file__).resolve().parents[3] / "shared" / "data"
    root = Path(root).expanduser()
    if not root.is_dir():
        raise FileNotFoundError(
            f"dataset folder {root} not found. Pass root=... or set the environment variable "
            "TORCHHEAT_DATA to the folder that holds tosca_remeshed_5k/, tosca_hires/, scape/ "
            "and kids/ (the shared/data folder next to the repository). The data is "
            "academic-use only and is not shipped with torchheat."
        )
    return root


def _dataset_dir(root: PathLike | None, name: str, marker: str) -> Path:
    """``root/name`` or ``root`` itself if it already is that dataset (contains ``marker``)."""
    base = data_root(root)
    for cand in (base / name, base):
        if (cand / marker).exists():
            return cand
    raise FileNotFoundError(
        f"{name} not found under {base} (looked for {base / name / marker}). Pass root=... or "
        "set TORCHHEAT_DATA to the folder holding the datasets."
    )


def _sorted_files(d: Path, pattern: str) -> list[Path]:
    """Files of ``d`` whose names match one of the ``|``-separated glob patterns, ignoring
    case (``CAT1.OFF``, ``scan.Obj``: exports from Windows and macOS tools; a case-sensitive
    glob dropped them from the collection without a word), in natural name order. A pattern
    with a ``/`` (a subfolder) is globbed as given."""
    pats = [p.strip() for p in pattern.split("|") if p.strip()]
    names = [q.lower() for q in pats if "/" not in q]
    files = {p for p in d.iterdir()
             if p.is_file() and any(fnmatch.fnmatchcase(p.name.lower(), q) for q in names)}
    files |= {p for q in pats if "/" in q for p in d.glob(q) if p.is_file()}
    return sorted(files, key=lambda p: _natural_key(p.name))


def _shape_kw(kw: dict) -> dict:
    allowed = {"preprocess", "cache_dir"}
    bad = set(kw) - allowed
    if bad:
        raise TypeError(f"unexpected keyword arguments {sorted(bad)}; allowed: {sorted(allowed)}")
    return kw


def _within_class_pairs(shapes: ShapeCollection, mode: str) -> list[tuple[int, int]]:
    by_cls: dict[str, list[int]] = {}
    for i, c in enumerate(shapes.classes):
        by_cls.setdefault(c, []).append(i)
    out: list[tuple[int, int]] = []
    for idx in by_cls.values():
        if mode == "all":
            out += [(a, b) for j, a in enumerate(idx) for b in idx[j + 1 :]]
        elif mode == "ordered":
            out += [(a, b) for a in idx for b in idx if a != b]
        elif mode == "first":
            out += [(idx[0], b) for b in idx[1:]]
        else:
            raise ValueError(f"unknown pairs mode {mode!r}")
    return out


#: Every file :func:`torchheat.load_mesh` reads (OFF, OBJ and PLY also compressed), as globs
_MESH_FILES = "|".join([f"*{e}" for e in SUPPORTED_FORMATS]
                       + [f"*{e}{c}" for e in ORDER_KEEPING_FORMATS for c in COMPRESSED])


def folder(
    path: PathLike,
    pattern: str = _MESH_FILES,
    classes: Sequence[str] | None = None,
    **kw: Any,
) -> ShapeCollection:
    """All meshes of a folder (natural name order) as a :class:`ShapeCollection`.

    Parameters
    ----------
    path : path-like
        The folder (not searched recursively).
    pattern : str
        Glob patterns separated by ``|`` (case-insensitive; default: every format
        :func:`torchheat.load_mesh` reads, OFF, OBJ and PLY also compressed).
    classes : sequence of str, optional
        Class per file; default: stem without trailing digits.
    **kw
        ``preprocess``, ``cache_dir`` (see :class:`ShapeCollection`).

    Examples
    --------
    >>> shapes = folder("meshes/", preprocess=Preprocess(k=30))  # doctest: +SKIP
    """
    d = Path(path).expanduser()
    if not d.is_dir():
        raise FileNotFoundError(f"mesh folder {d} does not exist")
    files = _sorted_files(d, pattern)
    if not files:
        raise FileNotFoundError(f"no files matching {pattern!r} in {d}")
    return ShapeCollection(files, classes=classes, **_shape_kw(kw))


def tosca_remeshed_5k(
    root: PathLike | None = None,
    pairs: str | Sequence[tuple[str, str]] = "test",
    classes: Sequence[str] | None = None,
    **kw: Any,
) -> PairCollection:
    """TOSCA isometric shapes remeshed to ~5k vertices (Ren et al. 2018, BCICP data).

    76 shapes in 8 classes; ground truth from the 1-based ``vtx_5k/corres/<name>.vts`` files:
    ``A.vts[k]-1 -> B.vts[k]-1`` (5000 entries, partial: some source vertices repeat), and the
    symmetric map ``A.vts[k]-1 -> B.sym.vts[k]-1`` in ``gt_sym_tgt``. About 0.5 % of the rows
    (1.3 % on victoria: hands and lower legs of victoria2, 7, 17, 21, 23) contradict their
    neighbours' rows by over 0.1 sqrt(area) (:func:`torchheat.evaluate.gt_disagreement`);
    batch summaries report the figures without them beside the standard ones.

    Parameters
    ----------
    root : path-like, optional
        Data folder (see :func:`data_root`) or the ``tosca_remeshed_5k`` folder itself.
    pairs : "test", "all", "ordered" or sequence of (name, name)
        ``"test"``: the 284 pairs of ``test_pairs.txt`` (the paper's protocol); ``"all"``: every
        within-class pair ``(i, j)``, ``i < j`` in natural name order (414 pairs);
        ``"ordered"``: both directions of every within-class pair (828 pairs).
    classes : sequence of str, optional
        Keep only these classes (e.g. ``["cat", "wolf"]``).
    **kw
        ``preprocess``, ``cache_dir`` (see :class:`ShapeCollection`).

    Examples
    --------
    >>> pc = tosca_remeshed_5k(preprocess=Preprocess())  # doctest: +SKIP
    >>> len(pc), pc[0].name, pc[0].gt_src.shape  # doctest: +SKIP
    (284, 'cat0-cat1', torch.Size([5000]))
    """
    d = _dataset_dir(root, "tosca_remeshed_5k", "vtx_5k")
    files = _sorted_files(d / "vtx_5k", "*.off")
    if classes is not None:
        keep = set(classes)
        files = [f for f in files if _class_from_stem(f.stem) in keep]
    shapes = ShapeCollection(files, **_shape_kw(kw))
    if isinstance(pairs, str) and pairs == "test":
        lines = (d / "test_pairs.txt").read_text().splitlines()
        plist = [tuple(ln.split()) for ln in lines if ln.strip()]
        if classes is not None:
            plist = [p for p in plist if p[0] in shapes and p[1] in shapes]
        idx = [(shapes.index(a), shapes.index(b)) for a, b in plist]
    elif isinstance(pairs, str):
        idx = _within_class_pairs(shapes, pairs)
    else:
        idx = [(shapes.index(a), shapes.index(b)) for a, b in pairs]
    return PairCollection(shapes, idx, gt=VtsGT(d / "vtx_5k" / "corres"))


def tosca_remeshed_5k_symmetry(
    root: PathLike | None = None,
    classes: Sequence[str] | None = None,
    **kw: Any,
) -> PairCollection:
    """Self-symmetry ground truth of the 76 TOSCA 5k shapes: one pair ``(A, A)`` per shape.

    ``gt_src = A.vts - 1``, ``gt_tgt = A.sym.vts - 1`` (the intrinsic left/right symmetry);
    ``gt_sym_tgt`` is ``None``.

    Examples
    --------
    >>> sym = tosca_remeshed_5k_symmetry(classes=["cat"])  # doctest: +SKIP
    >>> p = sym[0]; p.source is p.target  # doctest: +SKIP
    True
    """
    d = _dataset_dir(root, "tosca_remeshed_5k", "vtx_5k")
    files = _sorted_files(d / "vtx_5k", "*.off")
    if classes is not None:
        keep = set(classes)
        files = [f for f in files if _class_from_stem(f.stem) in keep]
    shapes = ShapeCollection(files, **_shape_kw(kw))
    return PairCollection(
        shapes, [(i, i) for i in range(len(shapes))], gt=VtsSymmetryGT(d / "vtx_5k" / "corres")
    )


def scape(
    root: PathLike | None = None,
    pairs: Sequence[tuple[int | str, int | str]] | None = None,
    **kw: Any,
) -> PairCollection:
    """SCAPE, 20 poses of one person (12500 vertices each), identity ground truth.

    Parameters
    ----------
    root : path-like, optional
        Data folder (see :func:`data_root`) or the ``scape`` folder itself.
    pairs : sequence of (int or str, int or str), optional
        Default: the 40 pairs ``(i, (i + d) % 20)`` for ``d`` in (1, 2) — every pose against its
        next and next-but-one pose, so each shape is a source twice and a target twice.
    **kw
        ``preprocess``, ``cache_dir``.

    Notes
    -----
    ``gt_sym_tgt`` is ``None``: SCAPE's symmetry information (:func:`landmarks`) covers 36
    landmarks only, not a dense map. Class name: ``"scape"``.

    Examples
    --------
    >>> pc = scape()  # doctest: +SKIP
    >>> len(pc), pc.names[0]  # doctest: +SKIP
    (40, 'mesh000-mesh001')
    """
    d = _dataset_dir(root, "scape", "mesh000.off")
    files = _sorted_files(d, "mesh*.off")
    shapes = ShapeCollection(files, classes=["scape"] * len(files), **_shape_kw(kw))
    n = len(shapes)
    if pairs is None:
        pairs = [(i, (i + dd) % n) for dd in (1, 2) for i in range(n)]
    return PairCollection(shapes, pairs, gt="identity")


def tosca_hires(
    root: PathLike | None = None,
    classes: Sequence[str] | None = None,
    pairs: str | Sequence[tuple[str, str]] = "first",
    **kw: Any,
) -> PairCollection:
    """TOSCA high-resolution meshes (41 shapes, 7 classes), identity ground truth in a class.

    Parameters
    ----------
    root : path-like, optional
        Data folder (see :func:`data_root`) or the ``tosca_hires`` folder itself.
    classes : sequence of str, optional
        Keep only these classes (cat, centaur, david, dog, horse, victoria, wolf).
    pairs : "first", "all", "ordered" or sequence of (name, name)
        ``"first"`` (default): the first shape of each class (natural order: ``cat0``, ...)
        against every other shape of the class (34 pairs for all classes); ``"all"``: every
        within-class pair ``i < j``; ``"ordered"``: both directions of each.
    **kw
        ``preprocess``, ``cache_dir``.

    Notes
    -----
    Several meshes have small holes and some (centaur3/4, david0/1, horse5/6) inconsistent
    face orientation; the Laplacian uses unsigned areas, so this is harmless.

    Examples
    --------
    >>> pc = tosca_hires(classes=["wolf"])  # doctest: +SKIP
    >>> pc.names  # doctest: +SKIP
    ['wolf0-wolf1', 'wolf0-wolf2']
    """
    d = _dataset_dir(root, "tosca_hires", "landmarks")
    files = _sorted_files(d, "*.off")
    if classes is not None:
        keep = set(classes)
        unknown = keep - {_class_from_stem(f.stem) for f in files}
        if unknown:
            raise ValueError(f"unknown TOSCA classes {sorted(unknown)}")
        files = [f for f in files if _class_from_stem(f.stem) in keep]
    shapes = ShapeCollection(files, **_shape_kw(kw))
    plist = _within_class_pairs(shapes, pairs) if isinstance(pairs, str) else pairs
    return PairCollection(shapes, plist, gt="identity")


SHREC16_KINDS = ("cuts", "holes")


def shrec16_partial(
    root: PathLike | None = None,
    kind: str = "cuts",
    classes: Sequence[str] | None = None,
    **kw: Any,
) -> PairCollection:
    """SHREC'16 Partial Matching of Deformable Shapes, training set (Cosmo et al. 2016).

    Every partial shape ``<kind>_<class>_shape_<i>`` (source) is paired with its class's full
    shape ``null/<class>.off`` (target): the benchmark's direction, partial -> full. Ground truth
    (:class:`BarycentricGT`): a barycentric point of the full shape for every partial vertex,
    direct and left/right symmetric; ``gt_tgt`` / ``gt_sym_tgt`` hold the corners of largest
    weight, ``gt_bary`` / ``gt_sym_bary`` the points (the batch evaluation uses the points, see
    :func:`torchheat.batch.evaluate_pair`).

    Parameters
    ----------
    root : path-like, optional
        Data folder (see :func:`data_root`) or the ``shrec16_partial`` folder itself.
    kind : {"cuts", "holes"}
        Partiality type: shapes cut by planes (90), or with many holes (60).
    classes : sequence of str, optional
        Keep only these classes (cat, centaur, david, dog, horse, michael).
    **kw
        ``preprocess``, ``cache_dir``.

    Examples
    --------
    >>> pc = shrec16_partial(kind="holes", classes=["dog"])  # doctest: +SKIP
    >>> len(pc), pc.names[0]  # doctest: +SKIP
    (10, 'holes_dog_shape_1-dog')
    """
    if kind not in SHREC16_KINDS:
        raise ValueError(f"unknown kind {kind!r}; use one of {SHREC16_KINDS}")
    d = _dataset_dir(root, "shrec16_partial", "null")
    parts = _sorted_files(d / kind, f"{kind}_*_shape_*.off")
    cls_of = {p: p.stem[len(kind) + 1:].rsplit("_shape_", 1)[0] for p in parts}
    if classes is not None:
        keep = set(classes)
        unknown = keep - set(cls_of.values())
        if unknown:
            raise ValueError(f"unknown SHREC'16 {kind} classes {sorted(unknown)}")
        parts = [p for p in parts if cls_of[p] in keep]
    if not parts:
        raise FileNotFoundError(f"no {kind}_*_shape_*.off files in {d / kind}")
    fulls = sorted({cls_of[p] for p in parts})
    missing = [c for c in fulls if not (d / "null" / f"{c}.off").is_file()]
    if missing:
        raise FileNotFoundError(f"full shapes missing in {d / 'null'}: {missing}")
    files = [d / "null" / f"{c}.off" for c in fulls] + parts
    shapes = ShapeCollection(files, classes=fulls + [cls_of[p] for p in parts],
                             **_shape_kw(kw))
    pairs = [(p.stem, cls_of[p]) for p in parts]
    return PairCollection(shapes, pairs, gt=BarycentricGT(d / kind))


def kids(root: PathLike | None = None, **kw: Any) -> PairCollection:
    """KIDS subject 0001 (3 shapes, 59727 vertices each), identity ground truth.

    Pairs: ``null.0 -> isometry.1``, ``null.0 -> isometry.2``, ``isometry.1 -> isometry.2``.
    Class name: ``"kids"``.

    Examples
    --------
    >>> pc = kids()  # doctest: +SKIP
    >>> len(pc), pc.names[0]  # doctest: +SKIP
    (3, '0001.null.0-0001.isometry.1')
    """
    d = _dataset_dir(root, "kids", "0001.null.0.off")
    names = ["0001.null.0", "0001.isometry.1", "0001.isometry.2"]
    files = [d / f"{n}.off" for n in names]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise FileNotFoundError(f"KIDS files missing: {missing}")
    shapes = ShapeCollection(files, classes=["kids"] * 3, **_shape_kw(kw))
    return PairCollection(shapes, [(0, 1), (0, 2), (1, 2)], gt="identity")


def landmarks(
    root: PathLike | None = None,
    dataset: str = "tosca_hires",
    cls: str | None = None,
) -> tuple[np.ndarray, list[str], np.ndarray]:
    """Sparse landmarks of the Princeton benchmark (Kim et al. 2011) for TOSCA or SCAPE.

    Parameters
    ----------
    root : path-like, optional
        Data folder (see :func:`data_root`) or the dataset folder itself.
    dataset : {"tosca_hires", "scape"}
    cls : str
        TOSCA class (``"cat"``, ...); ignored for SCAPE (one landmark set, ``1.pid``).

    Returns
    -------
    idx : numpy.ndarray of int64, shape (L,)
        0-based vertex index of each landmark (``.pid`` files are 0-based); valid for every
        pose of the class.
    names : list of str
        Description of each landmark (``.info``), e.g. ``"eye, right"``.
    sym_pairs : numpy.ndarray of int64, shape (P, 2)
        Pairs of landmark numbers (rows of ``idx``) that are left/right mirror images
        (first block of ``.sym.info``; the landmarks on the symmetry plane are not returned).

    Examples
    --------
    >>> idx, names, sym = landmarks(dataset="tosca_hires", cls="cat")  # doctest: +SKIP
    >>> len(idx), sym.shape[1]  # doctest: +SKIP
    (21, 2)
    """
    if dataset == "tosca_hires":
        if not cls:
            raise ValueError("cls is required for tosca_hires (e.g. 'cat')")
        d = _dataset_dir(root, "tosca_hires", "landmarks") / "landmarks"
        stem = cls
    elif dataset == "scape":
        d = _dataset_dir(root, "scape", "landmarks") / "landmarks"
        stem = "1"
    else:
        raise ValueError(f"unknown dataset {dataset!r}; use 'tosca_hires' or 'scape'")
    pid = d / f"{stem}.pid"
    if not pid.is_file():
        raise FileNotFoundError(f"no landmark file {pid}")
    rows = np.loadtxt(pid, dtype=np.int64, ndmin=2)
    idx = rows[:, 0].copy()
    names: list[str] = []
    info = d / f"{stem}.info"
    if info.is_file():
        for ln in info.read_text().splitlines():
            if ln.strip():
                names.append(re.sub(r"^\s*\d+\s*:\s*", "", ln).strip())
    sym: list[tuple[int, int]] = []
    sym_file = d / f"{stem}.sym.info"
    if sym_file.is_file():
        for ln in sym_file.read_text().splitlines():
            parts = ln.split()
            if not parts:
                if sym:
                    break  # a blank line ends the pair block
                continue
            if len(parts) != 2:
                break
            sym.append((int(parts[0]), int(parts[1])))
    sym_arr = np.asarray(sym, dtype=np.int64).reshape(-1, 2)
    if sym_arr.size and sym_arr.max() >= idx.size:
        raise ValueError(f"{sym_file}: landmark number out of range")
    return idx, names, sym_arr
