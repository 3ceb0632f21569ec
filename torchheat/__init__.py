"""torchheat — one-point isometric shape matching with the heat kernel, batched in PyTorch.

After M. Ovsjanikov, Q. Mérigot, F. Mémoli, L. Guibas, "One Point Isometric Matching with the
Heat Kernel", SGP 2010. Modules, in the order data flows through them:

``meshio`` (files -> arrays) -> ``mesh`` (Mesh, load_mesh, MeshError) -> ``eigen`` (scipy
operators and eigensolves, no torch) -> ``operators`` (laplacian) -> ``heat`` (HeatKernel)
-> ``descriptors`` -> ``matching`` -> ``evaluate`` / ``datasets`` / ``viz`` -> ``cli``.

The names below are imported on first use (PEP 562), so ``import torchheat`` itself does not
import torch; ``torchheat.match`` and friends do. That lets the command line start its
eigensolves in worker processes before paying for ``import torch``.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"

_EXPORTS = {
    "Correspondence": "matching",
    "HeatKernel": "heat",
    "Laplacian": "operators",
    "Mesh": "mesh",
    "as_mesh": "mesh",
    "MeshError": "meshio",
    "MeshWarning": "meshio",
    "cotmatrix": "operators",
    "default_times": "heat",
    "laplacian": "operators",
    "load_mesh": "mesh",
    "massmatrix": "operators",
    "match": "matching",
    "prepare": "matching",
    "PreparedShape": "matching",
    "symmetry": "matching",
}

__all__ = list(_EXPORTS)

if TYPE_CHECKING:  # pragma: no cover - for type checkers and IDEs (names listed in _EXPORTS)
    from .heat import HeatKernel, default_times  # noqa: F401
    from .matching import Correspondence, PreparedShape, match, prepare  # noqa: F401
    from .matching.symmetry import symmetry  # noqa: F401
    from .mesh import Mesh, as_mesh, load_mesh  # noqa: F401
    from .meshio import MeshError, MeshWarning  # noqa: F401
    from .operators import Laplacian, cotmatrix, laplacian, massmatrix  # noqa: F401


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'torchheat' has no attribute {name!r}")
    value = getattr(importlib.import_module(f".{module}", __name__), name)
    globals()[name] = value  # later lookups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *_EXPORTS])
