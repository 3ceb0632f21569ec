"""Shapes and collections of shapes: :class:`Shape` (a mesh file with its cached eigenpairs,
HKS and mass), :class:`ShapeCollection` (a ``torch.utils.data.Dataset`` that fills and reads the
cache, also one task per shape on any executor), DataLoader helpers.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import sys
import time
import warnings
import zipfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from .._arrays import to_numpy
from .._files import atomic_write
from ..heat import HeatKernel
from ..mesh import Mesh, MeshWarning, load_mesh
from ..meshio import COMPRESSED
from .cache import (
    _ARRAY_KEYS,
    _SCALAR_KEYS,
    CACHE_VERSION,
    PathLike,
    Preprocess,
    default_cache_dir,
    file_sha256,
    host_id,
)


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------
def _natural_key(s: str) -> list:
    """Sort key that orders ``cat2`` before ``cat10``."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)]


def _class_from_stem(stem: str) -> str:
    """``"cat10" -> "cat"``; a stem that is all digits is kept as is."""
    return re.sub(r"\d+$", "", stem) or stem


def collate_list(batch: list) -> list:
    """Identity collate for :class:`~torch.utils.data.DataLoader`: a batch is a plain list.

    Shapes have different vertex counts, so the default collate (stacking) does not apply.

    Examples
    --------
    >>> collate_list([1, 2])
    [1, 2]
    """
    return list(batch)


def worker_init(worker_id: int | None = None) -> None:
    """``worker_init_fn`` for a :class:`~torch.utils.data.DataLoader` with ``num_workers > 0``.

    Sets torch and BLAS (scipy's OpenBLAS, used by the eigensolver) to one thread in the
    worker. Without it every worker inherits all cores for both: on a 2-core machine two
    workers' eigensolves were measured 10-30x slower (4-8 s instead of 0.3 s per TOSCA 5k
    shape) through oversubscribed, busy-waiting BLAS threads.

    Examples
    --------
    >>> from torch.utils.data import DataLoader
    >>> loader = DataLoader(ShapeCollection([]), num_workers=2, collate_fn=collate_list,
    ...                     worker_init_fn=worker_init)
    """
    from threadpoolctl import threadpool_limits

    torch.set_num_threads(1)
    threadpool_limits(limits=1)


# --------------------------------------------------------------------------------------------
# shapes
# --------------------------------------------------------------------------------------------
@dataclass
class Shape:
    """One mesh of a collection, with its (cached) preprocessing.

    Attributes
    ----------
    name : str
        File stem (e.g. ``"cat0"``).
    path : pathlib.Path
    cls : str
        Class name (e.g. ``"cat"``).
    mesh : Mesh
    data : dict or None
        Output of :class:`Preprocess` (see :meth:`Preprocess.__call__`), ``None`` when the
        collection has no preprocessing.
    preprocess : Preprocess or None
        The parameters ``data`` was computed with.

    Examples
    --------
    >>> shape = ShapeCollection(["cat0.off"], preprocess=Preprocess())[0]  # doctest: +SKIP
    >>> hk = shape.heat_kernel(rtol=1e-8)  # doctest: +SKIP
    """

    name: str
    path: Path
    cls: str
    mesh: Mesh
    data: dict[str, Any] | None = None
    preprocess: Preprocess | None = field(default=None, repr=False)

    @property
    def n_vertices(self) -> int:
        """Number of vertices of the mesh."""
        return int(self.mesh.n_vertices)

    def heat_kernel(self, **kw: Any) -> HeatKernel:
        """A :class:`HeatKernel` rebuilt from the cached eigenpairs and ``lambda_max``.

        No eigensolve and no Lanczos run happen when ``data`` is present. Keyword arguments go
        to :class:`HeatKernel` (e.g. ``rtol``, ``method``, ``times``, ``dtype``). A different
        ``kind`` / ``boundary`` than the cached one, or a larger ``k``, falls back to a fresh
        computation; a smaller ``k`` uses the first ``k`` cached eigenpairs. Without ``data``
        the solver is computed from scratch with the collection's (or default) parameters.
        """
        pp = self.preprocess or Preprocess()
        if self.data is None:
            return pp.heat_kernel(self.mesh, **kw)
        d = self.data
        params: dict[str, Any] = {
            "times": d["times"],
            "kind": pp.kind,
            "boundary": pp.boundary,
        }
        params.update(kw)
        if params["kind"] != pp.kind or params["boundary"] != pp.boundary:
            params.setdefault("k", pp.k)
            return HeatKernel(self.mesh, **params)
        params.setdefault("lambda_max", d["lambda_max"])
        lam, phi = d["eigenvalues"], d["eigenvectors"]
        k = params.pop("k", None)
        if k is None or k == pp.k or k == lam.numel():
            params.setdefault("eigenpairs", (lam, phi))
        elif k < lam.numel():
            params.setdefault("eigenpairs", (lam[:k], phi[:, :k]))
        else:
            params["k"] = k  # more eigenpairs than cached: solve again
        return HeatKernel(self.mesh, **params)


def _shape_name(path: Path) -> str:
    """A shape's name from its file: the stem, and for a compressed file (``cat0.off.gz``)
    the stem of the file inside (``cat0``)."""
    p = Path(path)
    return Path(p.stem).stem if p.suffix.lower() in COMPRESSED else p.stem


class ShapeCollection(Dataset):
    """A dataset of mesh files with an optional, disk-cached :class:`Preprocess`.

    Parameters
    ----------
    paths : sequence of path-like
        Mesh files (anything :func:`torchheat.load_mesh` reads).
    classes : sequence of str, optional
        Class name per file; default: the file stem without trailing digits (``cat10 -> cat``).
    preprocess : Preprocess, optional
        Per-shape preprocessing; ``None`` (default) returns shapes with ``data=None`` and
        touches no cache.
    cache_dir : path-like, optional
        Where ``.npz`` cache entries live (created on first write); default
        :func:`default_cache_dir`.
    names : sequence of str, optional
        Shape names; default: file stems (must be unique).

    Examples
    --------
    >>> from torch.utils.data import DataLoader
    >>> ds = ShapeCollection(["cat0.off", "cat1.off"], preprocess=Preprocess())  # doctest: +SKIP
    >>> shapes = next(iter(DataLoader(ds, batch_size=2, num_workers=2,
    ...                               collate_fn=collate_list)))  # doctest: +SKIP
    >>> shapes[0].data["hks"].shape  # doctest: +SKIP
    torch.Size([5000, 10])
    """

    def __init__(
        self,
        paths: Sequence[PathLike],
        classes: Sequence[str] | None = None,
        preprocess: Preprocess | None = None,
        cache_dir: PathLike | None = None,
        names: Sequence[str] | None = None,
    ) -> None:
        if isinstance(paths, str | os.PathLike):
            paths = [paths]
        self.paths = [Path(p) for p in paths]
        self.names = ([_shape_name(p) for p in self.paths] if names is None
                      else [str(n) for n in names])
        if classes is None:
            classes = [_class_from_stem(n) for n in self.names]
        self.classes = [str(c) for c in classes]
        if not (len(self.names) == len(self.classes) == len(self.paths)):
            raise ValueError("paths, names and classes must have the same length")
        if len(set(self.names)) != len(self.names):
            raise ValueError("shape names must be unique (pass names=...)")
        if preprocess is not None and not isinstance(preprocess, Preprocess):
            raise TypeError("preprocess must be a torchheat.datasets.Preprocess or None")
        self.preprocess = preprocess
        self.cache_dir = Path(cache_dir).expanduser() if cache_dir else default_cache_dir()
        self._index = {n: i for i, n in enumerate(self.names)}
        self._warned: set[tuple[str, str]] = set()  # (file, MeshWarning) already shown

    def __len__(self) -> int:
        return len(self.paths)

    def __contains__(self, name: object) -> bool:
        """Whether the collection holds a shape of that name (no file is read).

        Without it, ``"cat0" in shapes`` fell back to iterating the collection: every shape
        loaded (and solved, with a preprocess), each compared with the string, and False.

        Examples
        --------
        >>> shapes = ShapeCollection(["cat0.off", "cat1.off"])
        >>> "cat1" in shapes, "dog0" in shapes, 0 in shapes
        (True, False, False)
        """
        return isinstance(name, str) and name in self._index

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}({len(self)} shapes, preprocess={self.preprocess}, "
            f"cache_dir='{self.cache_dir}')"
        )

    def index(self, name_or_index: str | int) -> int:
        """Position of a shape given its name (or a possibly negative index)."""
        if isinstance(name_or_index, str):
            try:
                return self._index[name_or_index]
            except KeyError:
                raise KeyError(f"no shape named {name_or_index!r} in this collection") from None
        i = int(name_or_index)
        if not -len(self) <= i < len(self):
            raise IndexError(f"shape index {i} out of range for {len(self)} shapes")
        return i % len(self)

    def cache_path(self, i: int | str, sha: str | None = None) -> Path:
        """Cache file of shape ``i`` for the current :attr:`preprocess` (hashes the file)."""
        if self.preprocess is None:
            raise ValueError("this collection has no preprocess, hence no cache")
        i = self.index(i)
        sha = sha or file_sha256(self.paths[i])
        digest = hashlib.sha256(
            f"{sha}:{self.preprocess.key()}:v{CACHE_VERSION}".encode()
        ).hexdigest()
        stem = re.sub(r"[^A-Za-z0-9_.-]", "_", self.names[i])[:64]
        return self.cache_dir / f"{stem}.{digest[:32]}.npz"

    def is_cached(self, i: int | str) -> bool:
        """Whether shape ``i`` has a valid cache entry (for the current :attr:`preprocess`),
        i.e. ``self[i]`` runs no eigensolve. Reads the file and the entry's metadata only.

        Examples
        --------
        >>> ds = ShapeCollection(["cat0.off"], preprocess=Preprocess())  # doctest: +SKIP
        >>> ds.is_cached(0)  # doctest: +SKIP
        False
        """
        i = self.index(i)
        sha = file_sha256(self.paths[i])
        cpath = self.cache_path(i, sha)
        try:
            with np.load(cpath, allow_pickle=False) as z:
                return str(z["meta"]) == self._meta(sha)
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile):
            return False

    def cache_job(self, i: int | str) -> CacheJob:
        """A small picklable description of shape ``i``'s cache entry, for
        :func:`fill_cache_entry` on another process or machine."""
        if self.preprocess is None:
            raise ValueError("this collection has no preprocess, hence no cache")
        i = self.index(i)
        return CacheJob(str(self.paths[i]), self.names[i], self.classes[i], self.preprocess,
                        str(self.cache_dir))

    def fill_cache(self, executor: Any = None, progress: bool = False) -> list[dict[str, Any]]:
        """Compute every missing cache entry, one task per shape, e.g. on a Dask cluster.

        Afterwards every ``self[i]`` (in a :class:`~torch.utils.data.DataLoader`, say) reads
        its preprocessing from the cache. Entries already cached are checked, not recomputed.

        Parameters
        ----------
        executor : object with ``map(fn, iterable)``, optional
            Where the tasks run: in-process by default; a :class:`torchheat.executors.
            DaskExecutor` spreads them over a cluster (the mesh files and :attr:`cache_dir`
            must then be visible to every worker at the same paths: shared storage), a
            :class:`concurrent.futures.ProcessPoolExecutor` over local processes.
        progress : bool
            tqdm progress bar on stderr.

        Returns
        -------
        list of dict
            One per shape, in collection order: ``name``, ``path`` (the cache entry),
            ``computed`` (an eigensolve ran), ``seconds``, ``host`` (where it ran).

        Raises
        ------
        RuntimeError
            If entries written by the workers are not visible here (a cache folder that is
            not shared between the workers and this process).

        Examples
        --------
        >>> from torchheat.executors import DaskExecutor
        >>> shapes = tosca_remeshed_5k(preprocess=Preprocess(), cache_dir="/shared/cache").shapes
        ... # doctest: +SKIP
        >>> with DaskExecutor("tcp://scheduler:8786") as ex:  # doctest: +SKIP
        ...     done = shapes.fill_cache(ex, progress=True)
        >>> sum(d["computed"] for d in done)  # eigensolves run  # doctest: +SKIP
        76
        """
        from tqdm import tqdm

        jobs = [self.cache_job(i) for i in range(len(self))]
        mapper = map if executor is None else executor.map
        out: dict[str, dict[str, Any]] = {}
        with tqdm(total=len(jobs), disable=not progress, desc="preprocess", unit="shape",
                  file=sys.stderr, dynamic_ncols=True) as bar:
            for rec in mapper(fill_cache_entry, jobs):
                out[rec["name"]] = rec
                bar.update(1)
        missing = [n for i, n in enumerate(self.names) if not self.is_cached(i)]
        if missing:
            raise RuntimeError(
                f"{len(missing)} cache entries computed by the workers are not visible in "
                f"{self.cache_dir} here (e.g. {missing[0]}): the cache folder must be on "
                "storage shared by the workers and this process, at the same path")
        return [out[n] for n in self.names]

    def __getitem__(self, i: int | str) -> Shape:
        i = self.index(i)
        path = self.paths[i]
        data = None
        mesh = self._load_mesh(path)
        if self.preprocess is not None:
            sha = file_sha256(path)
            cpath = self.cache_path(i, sha)
            data = self._load_cache(cpath, sha, mesh)
            if data is None:
                data = self.preprocess(mesh)
                self._save_cache(cpath, sha, data)
        return Shape(
            name=self.names[i],
            path=path,
            cls=self.classes[i],
            mesh=mesh,
            data=data,
            preprocess=self.preprocess,
        )

    def _load_mesh(self, path: Path) -> Mesh:
        """:func:`load_mesh`, each :class:`MeshWarning` of a file shown once per collection.

        A shape is read again whenever it is asked for (a whole in many pairs, a dataset
        iterated twice), and Python's own once-per-place memory does not hold here: every
        ``catch_warnings`` resets it, the readers' own included. Other warnings pass as they
        come; warning filters apply as usual (``"error"`` still raises).
        """
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", MeshWarning)
            mesh = load_mesh(path)
        for w in caught:
            if issubclass(w.category, MeshWarning):
                key = (str(path), str(w.message))
                if key in self._warned:
                    continue
                self._warned.add(key)
            warnings.warn(w.message, w.category, stacklevel=3)  # the caller of __getitem__
        return mesh

    # ---------------------------------------------------------------------------------
    def _meta(self, sha: str) -> str:
        assert self.preprocess is not None
        return json.dumps(
            {
                "version": CACHE_VERSION,
                "file_sha256": sha,
                "preprocess_key": self.preprocess.key(),
                "preprocess": self.preprocess.params(),
            },
            sort_keys=True,
        )

    def _load_cache(self, cpath: Path, sha: str, mesh: Mesh) -> dict[str, Any] | None:
        if not cpath.is_file():
            return None
        try:
            with np.load(cpath, allow_pickle=False) as z:
                if str(z["meta"]) != self._meta(sha):
                    raise ValueError("metadata does not match")
                data: dict[str, Any] = {k: torch.from_numpy(z[k].copy()) for k in _ARRAY_KEYS}
                data.update({k: float(z[k]) for k in _SCALAR_KEYS})
            if data["eigenvectors"].shape[0] != int(mesh.n_vertices):
                raise ValueError("vertex count does not match the mesh")
            return data
        except (OSError, EOFError, KeyError, ValueError, zipfile.BadZipFile) as exc:
            warnings.warn(f"ignoring unusable cache entry {cpath}: {exc}", stacklevel=3)
            return None

    def _save_cache(self, cpath: Path, sha: str, data: dict[str, Any]) -> None:
        # (arrays and numpy scalars; Any, as np.savez's stubs read ** as its allow_pickle too)
        arrays: dict[str, Any] = {k: to_numpy(data[k]).astype(np.float64, copy=False)
                                  for k in _ARRAY_KEYS}
        arrays.update({k: np.float64(data[k]) for k in _SCALAR_KEYS})
        arrays["meta"] = np.array(self._meta(sha))
        atomic_write(cpath, lambda tmp: np.savez(tmp, **arrays))  # tmp ends in .npz as cpath


@dataclass(frozen=True)
class CacheJob:
    """One shape's cache entry to compute (:meth:`ShapeCollection.cache_job`): picklable and
    small (paths and parameters, no arrays), so it can be shipped to a cluster worker."""

    path: str
    name: str
    cls: str
    preprocess: Preprocess
    cache_dir: str

    def collection(self) -> ShapeCollection:
        """A one-shape :class:`ShapeCollection` holding this shape."""
        return ShapeCollection([self.path], classes=[self.cls], preprocess=self.preprocess,
                               cache_dir=self.cache_dir, names=[self.name])


def fill_cache_entry(job: CacheJob) -> dict[str, Any]:
    """Make sure one shape's cache entry exists (compute and write it if not): the task of
    :meth:`ShapeCollection.fill_cache`.

    Returns
    -------
    dict
        ``name``, ``path`` (the entry), ``computed`` (an eigensolve ran), ``seconds``,
        ``host`` (``hostname:pid``).

    Examples
    --------
    >>> job = ShapeCollection(["cat0.off"], preprocess=Preprocess()).cache_job(0)
    ... # doctest: +SKIP
    >>> fill_cache_entry(job)["computed"]  # doctest: +SKIP
    True
    """
    t0 = time.perf_counter()
    sc = job.collection()
    computed = not sc.is_cached(0)
    if computed:
        sc[0]  # noqa: B018 - computes and writes the entry
    return {"name": job.name, "path": str(sc.cache_path(0)), "computed": computed,
            "seconds": time.perf_counter() - t0, "host": host_id()}
