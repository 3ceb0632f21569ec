"""Shape-matching datasets with an on-disk cache of the per-shape preprocessing.

PyTorch-Geometric style: a :class:`ShapeCollection` is a :class:`torch.utils.data.Dataset` of
mesh files; with a :class:`Preprocess` it returns every :class:`Shape` together with its
eigenpairs, ``lambda_max``, HKS and lumped mass, computed once and then read back from an
``.npz`` cache. A :class:`PairCollection` serves :class:`Pair` items (two shapes and a
ground-truth correspondence as parallel 0-based index arrays) and loads its shapes through one
:class:`ShapeCollection`, so pairs that share a shape share its cache entry.

Modules, in the order data flows (imports go downward only): :mod:`.cache` (:class:`Preprocess`,
file hashes, the cache folder), :mod:`.shapes` (:class:`Shape`, :class:`ShapeCollection`),
:mod:`.ground_truth` (readers), :mod:`.pairs` (:class:`Pair`, :class:`PairCollection`),
:mod:`.loaders` (the benchmark folders).

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

from .cache import CACHE_VERSION, Preprocess, default_cache_dir, file_sha256, host_id
from .ground_truth import (
    Barycentric,
    BarycentricGT,
    IdentityGT,
    VtsGT,
    VtsSymmetryGT,
    read_barycentric,
)
from .loaders import (
    SHREC16_KINDS,
    data_root,
    folder,
    kids,
    landmarks,
    scape,
    shrec16_partial,
    tosca_hires,
    tosca_remeshed_5k,
    tosca_remeshed_5k_symmetry,
)
from .pairs import Pair, PairCollection, pairs_from_list
from .shapes import CacheJob, Shape, ShapeCollection, collate_list, fill_cache_entry, worker_init

__all__ = [
    "CACHE_VERSION",
    "SHREC16_KINDS",
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
