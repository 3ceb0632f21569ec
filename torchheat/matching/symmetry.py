"""Intrinsic symmetry detection: a shape matched against itself (:func:`symmetry`).
"""

from __future__ import annotations

from typing import Any

from ..mesh import Mesh
from .pipeline import match
from .prepared import CachedShape, PreparedShape, _as_prepared
from .quality import map_quality
from .result import Correspondence, _numbering

__all__ = ["symmetry"]


#: :func:`symmetry`'s ``fixed_weight`` (see :func:`~torchheat.matching.match`): the symmetric
#: self-map pays this weight times the share of samples it leaves in place. A reflection
#: fixes a band around its plane (0.06-0.35 of the samples on the right TOSCA symmetries);
#: victoria23's landmark-free candidate, part identity, fixed 0.33 against the right map's
#: 0.12 and won by its lower energy. Measured on the 76 TOSCA 5k shapes (in sample; share of
#: the samples' images within 0.08 diameters of the truth): 0.959 without, 0.966 / 0.973 /
#: 0.971 / 0.962 with weights 8 / 10 / 12 / 16; whole maps 97.6 -> 98.8 % under 0.25. Not
#: used for the target's self-symmetry inside :func:`match` (measured there, TOSCA 284: 3
#: pairs better, 3 worse, net -0.25 points).
SYMMETRY_FIXED_WEIGHT = 10.0


def symmetry(
    mesh: Mesh | PreparedShape | CachedShape, **options: Any
) -> Correspondence:
    """Intrinsic symmetry of a shape: the best orientation-reversing self-map.

    The shape is matched against itself (:func:`match`); the identity is excluded by the
    orientation test, so ``.map`` is the symmetry (and ``.symmetric_map`` the direct
    self-map, near the identity).

    Parameters
    ----------
    mesh : Mesh, PreparedShape or torchheat.datasets.Shape
        A dataset shape's cached eigenpairs are used (see :func:`prepare`).
    **options
        Passed to :func:`match`.

    Returns
    -------
    Correspondence
        A self-map; :meth:`Correspondence.full_map` gives it in the file's numbering for a
        mesh loaded with ``largest_component=True``.

    Examples
    --------
    >>> import trimesh
    >>> from torchheat import Mesh
    >>> m = trimesh.creation.icosphere(3)
    >>> V = m.vertices * [1.0, 0.8, 0.6]  # mirror-symmetric ellipsoid
    >>> symmetry(Mesh(V, m.faces)).map.shape
    torch.Size([642])
    """
    t = options.get("times")
    shape = _as_prepared(mesh, times="adaptive" if t is None else t,
                         max_features=options.get("max_features", 50))
    options.setdefault("n_candidates", 8)
    options.setdefault("fixed_weight", SYMMETRY_FIXED_WEIGHT)
    corr = match(shape, shape, **options)
    if not corr.has_symmetric_map:
        return corr
    o = corr.info.get("sym_orientation")  # None with method="paper" (not tested)
    return Correspondence(
        map=corr._symmetric_map,  # still lazy: only the map asked for is computed
        landmarks=corr.symmetric_landmarks,
        candidates=corr.candidates,
        scores=corr.scores,
        symmetric_map=corr._map,
        symmetric_landmarks=corr.landmarks,
        orientation=float("nan") if o is None else float(o),
        info=corr.info,
        quality=lambda c: map_quality(shape, shape, c.map, None, expect=-1),
        **_numbering(shape, shape),
    )
