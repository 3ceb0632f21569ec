"""Geometry of triangle meshes from arrays, numpy only (no torch): one function per concept,
shared by every module that needs it (the command line calls them before torch is imported,
the eigensolve workers inside their processes).

Examples
--------
>>> import numpy as np
>>> V = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
>>> float(face_areas(V, np.array([[0, 1, 2], [1, 3, 2]])).sum())
1.0
"""

from __future__ import annotations

import numpy as np

__all__ = ["face_areas"]


def face_areas(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Unsigned triangle areas.

    Parameters
    ----------
    V : numpy.ndarray of float, shape (n, 3)
    F : numpy.ndarray of int, shape (m, 3)

    Returns
    -------
    numpy.ndarray of float, shape (m,)
        Half the norm of each face's edge cross product.

    Examples
    --------
    >>> face_areas(np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]))
    array([0.5])
    """
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
