"""torchheat — one-point isometric shape matching with the heat kernel, batched in PyTorch.

After M. Ovsjanikov, Q. Mérigot, F. Mémoli, L. Guibas, "One Point Isometric Matching with the
Heat Kernel", SGP 2010. Modules, in the order data flows through them:

``mesh`` (Mesh, load_mesh, MeshError) -> ``operators`` (laplacian) -> ``heat`` (HeatKernel)
-> ``descriptors`` -> ``matching`` -> ``evaluate`` / ``datasets`` / ``viz`` -> ``cli``.
"""

from .heat import HeatKernel, default_times
from .matching import Correspondence, PreparedShape, match, prepare, symmetry
from .mesh import Mesh, MeshError, MeshWarning, load_mesh
from .operators import Laplacian, cotmatrix, laplacian, massmatrix

__version__ = "0.1.0"

__all__ = [
    "Correspondence",
    "HeatKernel",
    "Laplacian",
    "Mesh",
    "MeshError",
    "MeshWarning",
    "cotmatrix",
    "default_times",
    "laplacian",
    "load_mesh",
    "massmatrix",
    "match",
    "prepare",
    "PreparedShape",
    "symmetry",
]
