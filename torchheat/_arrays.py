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


def integral(a: np.ndarray) -> bool:
    """Whether every entry of ``a`` is a whole number: an integer dtype, or finite floats with
    no fractional part (``np.loadtxt`` reads vertex indices as floats). Booleans, complex
    numbers, NaN, infinities and strings are not.

    Parameters
    ----------
    a : numpy.ndarray
        Any shape.

    Returns
    -------
    bool

    Examples
    --------
    >>> integral(np.array([3, 4])), integral(np.array([3.0, 4.0])), integral(np.array([1.5]))
    (True, True, False)
    >>> integral(np.array([True])), integral(np.array([np.inf]))
    (False, False)
    """
    if a.dtype.kind in "iu":
        return True
    return a.dtype.kind == "f" and bool(np.all(np.isfinite(a)) and np.all(a == np.round(a)))
