"""Shape-matching datasets with an on-disk cache of the per-shape preprocessing.

PyTorch-Geometric style: a :class:`ShapeCollection` is a :class:`torch.utils.data.Dataset` of
mesh files; with a :class:`Preprocess` it returns every :class:`Shape` together with its
eigenpairs, ``lambda_max``, HKS and lumped mass, computed once and then read back from an
``.npz`` cache. A :class:`PairCollection` serves :class:`Pair` items (two shapes and a
ground-truth correspondence as parallel 0-based index arrays) and loads its shapes through one
:class:`ShapeCollection`, so pairs that share a shape share its cache entry.

Cache
-----
* Directory: ``cache_dir`` argument, else ``$TORCHHEAT_CACHE``, else ``~/.cache/torchheat``.
* Key: sha256 of the **file bytes**, :meth:`Preprocess.key` (all parameters) and
  :data:`CACHE_VERSION`. Editing the mesh file or changing any parameter therefore never reuses a
  stale entry; the key is also stored inside the file and checked on load (an entry that does not
  match or cannot be read is recomputed and overwritten).
* Writes are atomic (temporary file in the same directory, then :func:`os.replace`), so
  concurrent DataLoader workers may compute the same shape safely.

Filling the cache on a cluster
------------------------------
:meth:`ShapeCollection.fill_cache` computes every missing entry as one task per shape on any
executor with ``map`` — in-process, a process pool, or a :class:`torchheat.executors.
DaskExecutor` (the mesh files and ``cache_dir`` must then be visible to every worker at the
same paths) — and checks afterwards that the entries are visible here; ``torchheat preprocess
CONFIG_OR_FOLDER --cache DIR --dask ADDRESS`` does the same from the command line. A later
``DataLoader`` over the collection (same :class:`Preprocess`, same folder) then runs no
eigensolve, and :func:`torchheat.match` / :func:`torchheat.prepare` take its shapes and pairs
directly.

Data loaders
------------
:func:`tosca_remeshed_5k`, :func:`tosca_remeshed_5k_symmetry`, :func:`scape`,
:func:`tosca_hires`, :func:`kids` read the layouts of the ``shared/data`` folder described in its
README (``root`` argument, else ``$TORCHHEAT_DATA``, else ``<repo>/../shared/data``). That data is
licensed for academic use and is **not** part of this repository. Index conventions: ``.vts``
files are 1-based, ``.pid`` landmark files 0-based; every index returned here is 0-based.
:func:`folder` and :func:`pairs_from_list` build collections from any folder of meshes.

Examples
--------
>>> from torchheat.datasets import Preprocess, ShapeCollection, collate_list
>>> from torch.utils.data import DataLoader
>>> ds = ShapeCollection(["a.off", "b.off"], preprocess=Preprocess(k=30))  # doctest: +SKIP
>>> for batch in DataLoader(ds, batch_size=2, collate_fn=collate_list):  # doctest: +SKIP
...     hk = batch[0].heat_kernel()  # no eigensolve: eigenpairs come from the cache
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
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from ._files import atomic_write
from .eigen import DEFAULT_EIGENPAIRS
from .heat import HeatKernel
from .mesh import Mesh, load_mesh

__all__ = [
    "CACHE_VERSION",
    "Barycentric",
    "BarycentricGT",
    "CacheJob",
    "Pair",
    "PairCollection",
    "Preprocess",
    "Shape",
    "ShapeCollection",
    "IdentityGT",
    "VtsGT",
    "VtsSymmetryGT",
    "collate_list",
    "data_root",
    "default_cache_dir",
    "file_sha256",
    "fill_cache_entry",
    "folder",
    "host_id",
    "kids",
    "landmarks",
    "pairs_from_list",
    "read_barycentric",
    "scape",
    "shrec16_partial",
    "tosca_hires",
    "tosca_remeshed_5k",
    "tosca_remeshed_5k_symmetry",
    "worker_init",
]

#: Bumped whenever the layout or meaning of a cache entry changes (old entries are ignored).
CACHE_VERSION = 1

_KINDS = ("cotan", "fem", "robust")
_BOUNDARIES = ("neumann", "dirichlet")
_ARRAY_KEYS = ("eigenvalues", "eigenvectors", "hks", "mass", "times")
_SCALAR_KEYS = ("lambda_max", "area")

PathLike = str | os.PathLike


# --------------------------------------------------------------------------------------------
# small helpers
# --------------------------------------------------------------------------------------------
def _natural_key(s: str) -> list:
    """Sort key that orders ``cat2`` before ``cat10``."""
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", s)]


def _class_from_stem(stem: str) -> str:
    """``"cat10" -> "cat"``; a stem that is all digits is kept as is."""
    return re.sub(r"\d+$", "", stem) or stem


def file_sha256(path: PathLike, chunk: int = 1 << 20) -> str:
    """sha256 hex digest of a file's bytes.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> p = pathlib.Path(tempfile.mkdtemp()) / "x.txt"
    >>> _ = p.write_bytes(b"abc")
    >>> file_sha256(p)[:12]
    'ba7816bf8f01'
    """
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def default_cache_dir() -> Path:
    """``$TORCHHEAT_CACHE`` if set, else ``~/.cache/torchheat``.

    Examples
    --------
    >>> default_cache_dir()  # doctest: +SKIP
    PosixPath('/home/me/.cache/torchheat')
    """
    env = os.environ.get("TORCHHEAT_CACHE")
    if env:
        return Path(env).expanduser()
    return Path("~/.cache/torchheat").expanduser()


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


def _to_numpy(x: Any) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


# --------------------------------------------------------------------------------------------
# preprocessing
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Preprocess:
    """Parameters of the per-shape preprocessing, and the computation itself.

    Parameters
    ----------
    times : tuple of float, optional
        Heat-kernel times (unit-area scale) for the HKS and for :meth:`Shape.heat_kernel`;
        ``None`` = :func:`torchheat.default_times`. Lists, arrays and tensors are converted to a
        tuple of floats. Note that ``None`` and the same values spelled out give different
        cache keys (the results are identical).
    k : int
        Number of eigenpairs (clipped to ``n - 1`` on tiny meshes, as in :class:`HeatKernel`);
        default :data:`~torchheat.eigen.DEFAULT_EIGENPAIRS` (100), what :func:`torchheat.match`
        uses, so that ``match(pair)`` reads its eigenpairs from the cache.
    kind : {"cotan", "fem", "robust"}
        Laplacian discretisation (:func:`torchheat.laplacian`).
    boundary : {"neumann", "dirichlet"}
        Boundary condition.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> s = trimesh.creation.icosphere(2)
    >>> pp = Preprocess(k=10)
    >>> d = pp(Mesh(s.vertices, s.faces))
    >>> tuple(d["eigenvectors"].shape), tuple(d["hks"].shape)
    ((162, 10), (162, 10))
    >>> pp.key() == Preprocess(k=10).key() != Preprocess(k=11).key()
    True
    """

    times: tuple[float, ...] | None = None
    k: int = DEFAULT_EIGENPAIRS
    kind: str = "cotan"
    boundary: str = "neumann"

    def __post_init__(self) -> None:
        if self.times is not None:
            t = tuple(float(x) for x in np.asarray(_to_numpy(self.times), dtype=np.float64).ravel())
            if not t or min(t) <= 0:
                raise ValueError("times must be a non-empty sequence of positive numbers")
            object.__setattr__(self, "times", t)
        if int(self.k) < 1:
            raise ValueError(f"k must be >= 1, got {self.k}")
        object.__setattr__(self, "k", int(self.k))
        if self.kind not in _KINDS:
            raise ValueError(f"unknown kind {self.kind!r}; use one of {_KINDS}")
        if self.boundary not in _BOUNDARIES:
            raise ValueError(f"unknown boundary {self.boundary!r}; use one of {_BOUNDARIES}")

    def params(self) -> dict:
        """The parameters as a JSON-serialisable dict."""
        d = asdict(self)
        d["times"] = None if self.times is None else list(self.times)
        return d

    def key(self) -> str:
        """Stable hash (hex, 16 characters) of the parameters and :data:`CACHE_VERSION`.

        Floats are serialised with :func:`repr` (shortest round-trip form), so the key is the
        same across processes, platforms and Python versions.
        """
        payload = json.dumps(
            {"preprocess": self.params(), "version": CACHE_VERSION}, sort_keys=True
        )
        return hashlib.sha256(payload.encode()).hexdigest()[:16]

    def heat_kernel(self, mesh: Mesh, **kw: Any) -> HeatKernel:
        """A fresh :class:`HeatKernel` with these parameters (``kw`` overrides)."""
        params: dict[str, Any] = {
            "times": self.times,
            "k": self.k,
            "kind": self.kind,
            "boundary": self.boundary,
        }
        params.update(kw)
        return HeatKernel(mesh, **params)

    def __call__(self, mesh: Mesh) -> dict[str, Any]:
        """Compute the preprocessing of one mesh.

        Returns
        -------
        dict
            ``eigenvalues`` (k,), ``eigenvectors`` (n, k) mass-orthonormal, ``hks`` (n, J),
            ``mass`` (n,) lumped mass at unit total area, ``times`` (J,) — float64 tensors —
            and the floats ``lambda_max`` (spectral bound used by Chebyshev) and ``area``
            (surface area before normalisation).
        """
        hk = self.heat_kernel(mesh)
        return {
            "eigenvalues": hk.eigenvalues,
            "eigenvectors": hk.eigenvectors,
            "lambda_max": float(hk.lambda_max),
            "hks": hk.hks(),
            "mass": hk.laplacian.mass,
            "area": float(hk.laplacian.area),
            "times": hk.times.clone(),
        }


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
        self.names = [p.stem for p in self.paths] if names is None else [str(n) for n in names]
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

    def __len__(self) -> int:
        return len(self.paths)

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
        if self.preprocess is None:
            mesh = load_mesh(path)
        else:
            sha = file_sha256(path)
            mesh = load_mesh(path)
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
        arrays = {k: _to_numpy(data[k]).astype(np.float64, copy=False) for k in _ARRAY_KEYS}
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


def host_id() -> str:
    """``hostname:pid`` of this process (where a task ran).

    Examples
    --------
    >>> host_id().count(":")
    1
    """
    import socket

    return f"{socket.gethostname()}:{os.getpid()}"


# --------------------------------------------------------------------------------------------
# pairs and ground truth
# --------------------------------------------------------------------------------------------
@dataclass
class Pair:
    """Two shapes and a ground-truth correspondence (0-based, source vertex -> target vertex).

    Attributes
    ----------
    source, target : Shape
    gt_src, gt_tgt : torch.LongTensor, shape (m,), or None
        ``gt_tgt[i]`` is the true match on ``target`` of vertex ``gt_src[i]`` of ``source``.
        The map may be partial and repeat source vertices (TOSCA ``.vts``); ``None`` when the
        collection has no ground truth.
    gt_sym_tgt : torch.LongTensor, shape (m,), or None
        True match of ``gt_src`` under the intrinsic left/right symmetry, when known.
    name : str
        ``"<source>-<target>"``.
    cls : str
        Class of the pair (``"<src cls>-<tgt cls>"`` for inter-class pairs).
    """

    source: Shape
    target: Shape
    gt_src: torch.Tensor | None
    gt_tgt: torch.Tensor | None
    gt_sym_tgt: torch.Tensor | None
    name: str
    cls: str
    gt_bary: Barycentric | None = None
    gt_sym_bary: Barycentric | None = None


@dataclass(frozen=True)
class Barycentric:
    """Points on a mesh's triangles, as three corner vertices and barycentric weights.

    Attributes
    ----------
    corners : torch.LongTensor, shape (m, 3)
        0-based vertex indices of the triangle of each point, in the order the face lists them.
    weights : torch.DoubleTensor, shape (m, 3)
        Non-negative barycentric weights summing to 1: point ``i`` is
        ``sum_j weights[i, j] * V[corners[i, j]]``.

    Examples
    --------
    >>> b = Barycentric(torch.tensor([[0, 1, 2]]), torch.tensor([[0.2, 0.7, 0.1]],
    ...                 dtype=torch.float64))
    >>> b.nearest_corner().tolist()  # the corner of largest weight
    [1]
    """

    corners: torch.Tensor
    weights: torch.Tensor

    def nearest_corner(self) -> torch.Tensor:
        """The corner of largest weight of every point (the field's ``.vts`` convention)."""
        j = torch.argmax(self.weights, dim=1, keepdim=True)
        return torch.gather(self.corners, 1, j).squeeze(1)

    def __len__(self) -> int:
        return int(self.corners.shape[0])


GTResult = tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor | None]


def _check_range(idx: np.ndarray, n: int, what: str) -> torch.Tensor:
    idx = np.asarray(idx, dtype=np.int64).ravel()
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(
            f"ground truth {what} has indices in [{idx.min()}, {idx.max()}], "
            f"outside [0, {n}) — wrong index base or vertex order?"
        )
    return torch.from_numpy(idx)


class IdentityGT:
    """Ground truth of meshes sharing their vertex order: vertex i -> vertex i.

    Examples
    --------
    >>> gt = IdentityGT()  # used by scape(), tosca_hires(), kids()
    """

    def __call__(self, source: Shape, target: Shape) -> GTResult:
        n, m = source.n_vertices, target.n_vertices
        if n != m:
            raise ValueError(
                f"identity ground truth needs equal vertex counts: {source.name} has {n}, "
                f"{target.name} has {m}"
            )
        idx = torch.arange(n, dtype=torch.int64)
        return idx, idx.clone(), None

    def __repr__(self) -> str:
        return "IdentityGT()"


def _read_vts(path: Path) -> np.ndarray:
    """A 1-based ``.vts`` point list as 0-based int64."""
    if not path.is_file():
        raise FileNotFoundError(f"ground-truth file not found: {path}")
    idx = np.loadtxt(path, dtype=np.int64, ndmin=1)
    if idx.size == 0 or idx.min() < 1:
        raise ValueError(f"{path}: expected 1-based vertex indices (min >= 1)")
    return idx - 1


@dataclass(frozen=True)
class VtsGT:
    """TOSCA/BCICP ``.vts`` ground truth: ``A.vts[k]-1 -> B.vts[k]-1``.

    The symmetric map is ``A.vts[k]-1 -> B.sym.vts[k]-1`` (``None`` if ``B.sym.vts`` is
    missing).

    Parameters
    ----------
    corres_dir : pathlib.Path
        Folder holding ``<name>.vts`` and ``<name>.sym.vts``.
    """

    corres_dir: Path

    def __call__(self, source: Shape, target: Shape) -> GTResult:
        d = Path(self.corres_dir)
        a = _read_vts(d / f"{source.name}.vts")
        b = _read_vts(d / f"{target.name}.vts")
        if a.size != b.size:
            raise ValueError(f"{source.name}.vts and {target.name}.vts differ in length")
        sym_path = d / f"{target.name}.sym.vts"
        bs = _read_vts(sym_path) if sym_path.is_file() else None
        return (
            _check_range(a, source.n_vertices, f"{source.name}.vts"),
            _check_range(b, target.n_vertices, f"{target.name}.vts"),
            None if bs is None else _check_range(bs, target.n_vertices, sym_path.name),
        )


@dataclass(frozen=True)
class VtsSymmetryGT:
    """Self-symmetry ground truth from ``.vts`` files: ``A.vts[k]-1 -> A.sym.vts[k]-1``.

    Used with pairs whose source and target are the same shape; ``gt_sym_tgt`` is ``None``.
    """

    corres_dir: Path

    def __call__(self, source: Shape, target: Shape) -> GTResult:
        d = Path(self.corres_dir)
        a = _read_vts(d / f"{source.name}.vts")
        s = _read_vts(d / f"{target.name}.sym.vts")
        if a.size != s.size:
            raise ValueError(f"{source.name}.vts and {target.name}.sym.vts differ in length")
        return (
            _check_range(a, source.n_vertices, f"{source.name}.vts"),
            _check_range(s, target.n_vertices, f"{target.name}.sym.vts"),
            None,
        )


def read_barycentric(path: PathLike, n_faces: int, faces: np.ndarray) -> Barycentric:
    """Read a SHREC'16 ``.baryc_gt`` file: one line per point, ``tri w1 w2 w3`` with a
    **1-based** triangle index into ``faces`` (``n_faces`` rows) and weights on its corners.

    Raises
    ------
    FileNotFoundError, ValueError
        Missing file; wrong column count, triangle index out of ``[1, n_faces]``, negative
        weights or weights not summing to 1 (within 1e-3), non-finite values — naming the file.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"ground-truth file not found: {p}")
    a = np.loadtxt(p, dtype=np.float64, ndmin=2)
    if a.shape[1] != 4:
        raise ValueError(f"{p}: expected 4 columns (tri w1 w2 w3), got {a.shape[1]}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{p}: non-finite values")
    tri = a[:, 0].round().astype(np.int64)
    if tri.min() < 1 or tri.max() > n_faces:
        raise ValueError(f"{p}: triangle indices in [{tri.min()}, {tri.max()}], outside "
                         f"[1, {n_faces}] (1-based) of the full shape")
    w = a[:, 1:]
    if (w < -1e-6).any() or np.abs(w.sum(1) - 1).max() > 1e-3:
        raise ValueError(f"{p}: barycentric weights must be >= 0 and sum to 1")
    w = np.clip(w, 0.0, None)
    w /= w.sum(1, keepdims=True)
    return Barycentric(torch.from_numpy(np.ascontiguousarray(faces[tri - 1], dtype=np.int64)),
                       torch.from_numpy(w))


@dataclass(frozen=True)
class BarycentricGT:
    """SHREC'16 partial ground truth: vertex ``i`` of the partial source lies at a barycentric
    point of the full target (``<source>.baryc_gt``, and ``<source>.baryc_gt_sym`` for the
    left/right symmetric correspondence).

    Returns ``(gt_src, gt_tgt, gt_sym_tgt, gt_bary, gt_sym_bary)``: every source vertex, the
    nearest corners (largest weight) of the direct and symmetric points, and the
    :class:`Barycentric` points themselves.

    Parameters
    ----------
    folder : pathlib.Path
        Folder of the partial shapes and their ``.baryc_gt`` files.
    """

    folder: Path

    def __call__(self, source: Shape, target: Shape) -> tuple:
        _, F = target.mesh.numpy()
        d = Path(self.folder)
        b = read_barycentric(d / f"{source.name}.baryc_gt", len(F), F)
        sym_path = d / f"{source.name}.baryc_gt_sym"
        bs = read_barycentric(sym_path, len(F), F) if sym_path.is_file() else None
        n = source.n_vertices
        for name, x in (("baryc_gt", b), ("baryc_gt_sym", bs)):
            if x is not None and len(x) != n:
                raise ValueError(f"{source.name}.{name} has {len(x)} rows but {source.name} "
                                 f"has {n} vertices")
        return (torch.arange(n, dtype=torch.int64), b.nearest_corner(),
                None if bs is None else bs.nearest_corner(), b, bs)


GroundTruth = Callable[[Shape, Shape], GTResult]


class PairCollection(Dataset):
    """A dataset of shape pairs with ground truth; shapes come from one :class:`ShapeCollection`.

    Parameters
    ----------
    shapes : ShapeCollection
        Every shape any pair refers to (its cache is shared by all pairs).
    pairs : sequence of (int or str, int or str)
        (source, target) by index or name in ``shapes``.
    gt : callable, "identity" or None
        ``gt(source, target) -> (gt_src, gt_tgt, gt_sym_tgt)``, optionally followed by the
        barycentric ground truth ``(gt_bary, gt_sym_bary)`` (:class:`Barycentric`, with
        ``gt_tgt`` / ``gt_sym_tgt`` their nearest corners); must be picklable for
        multi-worker loading (:class:`IdentityGT`, :class:`VtsGT`, :class:`VtsSymmetryGT` or a
        module-level function). ``"identity"`` = :class:`IdentityGT`; ``None`` = no ground
        truth (the three fields are ``None``).

    Examples
    --------
    >>> pc = tosca_remeshed_5k()  # doctest: +SKIP
    >>> p = pc[0]  # doctest: +SKIP
    >>> p.name, p.gt_src.shape  # doctest: +SKIP
    ('cat0-cat1', torch.Size([5000]))
    """

    def __init__(
        self,
        shapes: ShapeCollection,
        pairs: Sequence[tuple[int | str, int | str]],
        gt: GroundTruth | str | None = "identity",
    ) -> None:
        self.shapes = shapes
        self.pairs = [(shapes.index(a), shapes.index(b)) for a, b in pairs]
        if gt == "identity":
            gt = IdentityGT()
        elif isinstance(gt, str):
            raise ValueError(f"unknown gt {gt!r}; use 'identity', None or a callable")
        self.gt = gt

    def __len__(self) -> int:
        return len(self.pairs)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({len(self)} pairs, gt={self.gt!r}, shapes={self.shapes!r})"

    @property
    def names(self) -> list[str]:
        """Pair names ``"<source>-<target>"``."""
        n = self.shapes.names
        return [f"{n[a]}-{n[b]}" for a, b in self.pairs]

    def __getitem__(self, i: int) -> Pair:
        if not -len(self) <= i < len(self):
            raise IndexError(f"pair index {i} out of range for {len(self)} pairs")
        a, b = self.pairs[i]
        src = self.shapes[a]
        tgt = src if b == a else self.shapes[b]
        bary = (None, None)
        if self.gt is None:
            gs, gtg, gsym = None, None, None
        else:
            gs, gtg, gsym, *extra = self.gt(src, tgt)
            if extra:  # barycentric ground truth (direct, symmetric)
                bary = (extra[0], extra[1] if len(extra) > 1 else None)
        cls = src.cls if src.cls == tgt.cls else f"{src.cls}-{tgt.cls}"
        return Pair(src, tgt, gs, gtg, gsym, f"{src.name}-{tgt.name}", cls, *bary)


def pairs_from_list(
    shapes: ShapeCollection,
    pairs: Sequence[tuple[int | str, int | str]],
    gt: GroundTruth | str | None = "identity",
) -> PairCollection:
    """Pairs of an existing :class:`ShapeCollection`, by name or index.

    Examples
    --------
    >>> shapes = folder("meshes/")  # doctest: +SKIP
    >>> pc = pairs_from_list(shapes, [("rest", "smile")], gt="identity")  # doctest: +SKIP
    """
    return PairCollection(shapes, pairs, gt=gt)


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
        root = env if env else Path(__file__).resolve().parents[2] / "shared" / "data"
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
    files = {p for pat in pattern.split("|") for p in d.glob(pat.strip()) if p.is_file()}
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


def folder(
    path: PathLike,
    pattern: str = "*.off|*.ply|*.obj|*.stl|*.glb|*.gltf",
    classes: Sequence[str] | None = None,
    **kw: Any,
) -> ShapeCollection:
    """All meshes of a folder (natural name order) as a :class:`ShapeCollection`.

    Parameters
    ----------
    path : path-like
        The folder (not searched recursively).
    pattern : str
        Glob patterns separated by ``|``.
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
    symmetric map ``A.vts[k]-1 -> B.sym.vts[k]-1`` in ``gt_sym_tgt``.

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
            plist = [p for p in plist if p[0] in shapes._index and p[1] in shapes._index]
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
