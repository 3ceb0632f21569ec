"""Arrays in: numpy arrays, sequences and torch tensors (CPU or GPU) alike, without importing
torch (the command line reads meshes before torch is imported).
"""

from __future__ import annotations

from typing import Any

import numpy as np


def to_numpy(x: Any, dtype: Any = None) -> np.ndarray:
    """``x`` as a numpy array: a torch tensor is detached and copied to the CPU first.

    Parameters
    ----------
    x : array_like or torch.Tensor
    dtype : numpy dtype, optional
        As in :func:`numpy.asarray` (no copy when ``x`` already has it).

    Returns
    -------
    numpy.ndarray

    Examples
    --------
    >>> import torch
    >>> to_numpy(torch.arange(3), dtype=np.float64)
    array([0., 1., 2.])
    >>> to_numpy([1, 2]).dtype.kind
    'i'
    """
    if hasattr(x, "detach") and hasattr(x, "cpu"):  # a torch tensor, torch not imported here
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)
