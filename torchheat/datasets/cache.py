"""The on-disk cache of per-shape preprocessing: :class:`Preprocess` (what is computed and its
key), content hashes of mesh files, the cache folder, the host id of a cache entry's writer.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .._arrays import to_numpy
from ..eigen import DEFAULT_EIGENPAIRS
from ..heat import HeatKernel
from ..matching.options import _PREPARE_LEAST, _check_numbers
from ..mesh import Mesh
from ..operators import check_kind

#: Bumped whenever the layout or meaning of a cache entry changes (old entries are ignored).
CACHE_VERSION = 1


_ARRAY_KEYS = ("eigenvalues", "eigenvectors", "hks", "mass", "times")


_SCALAR_KEYS = ("lambda_max", "area")


PathLike = str | os.PathLike


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
        Number of eigenpairs, an integer as for :func:`torchheat.prepare` (``3.0`` is refused
        with a ``TypeError``, as there), clipped to ``n - 1`` on tiny meshes, as in
        :class:`HeatKernel`;
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
            t = tuple(float(x) for x in to_numpy(self.times, dtype=np.float64).ravel())
            if not t or not all(math.isfinite(x) and x > 0 for x in t):
                raise ValueError("times must be a non-empty sequence of positive finite "
                                 f"numbers, got {list(t)[:5]}")
            object.__setattr__(self, "times", t)
        # prepare's rule (5.5 was 5 eigenpairs; 3.0 is refused there too, not truncated)
        _check_numbers({"k": self.k}, _PREPARE_LEAST)
        object.__setattr__(self, "k", int(self.k))
        check_kind(self.kind, self.boundary)  # the Laplacian's own check

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


def host_id() -> str:
    """``hostname:pid`` of this process (where a task ran).

    Examples
    --------
    >>> host_id().count(":")
    1
    """
    import socket

    return f"{socket.gethostname()}:{os.getpid()}"
