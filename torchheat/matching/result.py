"""The result of matching: :class:`Correspondence`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from ..mesh import Mesh
from .prepared import PreparedShape
from .quality import MapQuality

__all__ = ["Correspondence"]


# ------------------------------------------------------------------------------------------
# the pipeline
# ------------------------------------------------------------------------------------------
class Correspondence:
    """Result of :func:`match` / :func:`symmetry`.

    Attributes
    ----------
    map : torch.Tensor, int64, shape (n_source,)
        Target vertex of every source vertex (the direct map); None from
        ``match(final_map=False)``.
    landmarks : list of (int, int)
        Landmark pairs (p, q) the direct map was computed from (first: the one-point match;
        with refinement, followed by the augmented landmarks).
    candidates : torch.Tensor, int64, shape (c,)
        Target candidates for the first source landmark, ranked best first.
    scores : torch.Tensor, float64, shape (c,)
        Their scores ``E(p, q)`` (ascending).
    symmetric_map : torch.Tensor or None
        The intrinsic-symmetric alternative, if one was found.
    symmetric_landmarks : list of (int, int) or None
    orientation : float
        Orientation score of the direct map (+1 preserving), NaN if not tested.
    info : dict
        Timings (s) per stage, the options used and the hypotheses considered.
    source_vertex_map, target_vertex_map : torch.Tensor or None
        int64, shapes (n_source,) and (n_target,): the index in the input file of every
        vertex of the matched meshes (their :attr:`Mesh.vertex_map`), for a mesh that
        ``largest_component=True`` cut; None for one that kept all its vertices.
    n_source_input : int or None
        Number of vertices of the source file (:attr:`Mesh.n_input_vertices`); needed
        with ``source_vertex_map``.
    n_source : int or None
        Number of source vertices matched (the length of :attr:`map`, known without it).
    quality : MapQuality or None
        The map's own evidence of being right (:func:`~torchheat.matching.quality.
        map_quality`: isometry defect of its functional map and its orientation), computed on
        first access; ``quality.quality`` in [0, 1], higher is better.
    suspect : bool or None
        ``quality.suspect``: the map is probably wrong (not near-isometric, or the mirror).
    rival_map : torch.Tensor or None
        The best *different* whole map the choice passed over (its images agree with the
        direct map's within 0.1 sqrt(area) on fewer than half of the ZoomOut samples; the
        map behind :attr:`MapQuality.margin <torchheat.matching.quality.MapQuality>`), dense
        at the size the candidates were compared at (100 modes); None without one (method
        ``"paper"``, ``zoomout=False``, partial matches). When the choice is ambiguous
        (``quality.ambiguous``), this is the map to look at: on TOSCA 284 + SCAPE 50 pairs
        the direct or the rival map was right on 10 of the 11 ambiguous ones (RESULTS.md,
        eleventh session).

    Notes
    -----
    **Vertex numbering.** ``map``, ``symmetric_map``, ``landmarks`` and ``candidates`` use
    the vertex indices of the meshes that were matched, so that ``target.vertices[map]``
    is the image of ``source.vertices``. They differ from the files' indices only for meshes
    loaded with ``largest_component=True`` (``--largest-component`` on the command line):
    :meth:`full_map` and :meth:`full_symmetric_map` give the maps in the files' numbering,
    one entry per vertex of the source file, ``-1`` for a source vertex that was dropped
    (they are what ``torchheat match`` writes).


    ``map`` and ``symmetric_map`` may be given as zero-argument callables: the dense map is
    then computed on first access and kept (the refined pipeline's last round is a dense
    ``n x m`` search, the most expensive single step on large meshes, so a caller that only
    needs one of the two maps pays for one). :attr:`has_symmetric_map` tells whether there is
    a symmetric map without computing it. Until then the result keeps references to the two
    prepared shapes.
    """

    def __init__(
        self,
        map: torch.Tensor | Callable[[], torch.Tensor] | None,
        landmarks: list,
        candidates: torch.Tensor,
        scores: torch.Tensor,
        symmetric_map: torch.Tensor | Callable[[], torch.Tensor] | None = None,
        symmetric_landmarks: list | None = None,
        orientation: float = float("nan"),
        info: dict | None = None,
        *,
        source_vertex_map: torch.Tensor | None = None,
        target_vertex_map: torch.Tensor | None = None,
        n_source_input: int | None = None,
        n_source: int | None = None,
        quality: MapQuality | Callable[[Correspondence], MapQuality] | None = None,
        rival_map: torch.Tensor | Callable[[], torch.Tensor] | None = None,
    ) -> None:
        self._map = map
        self._rival_map = rival_map
        self._quality = quality
        self._symmetric_map = symmetric_map
        self.landmarks = landmarks
        self.candidates = candidates
        self.scores = scores
        self.symmetric_landmarks = symmetric_landmarks
        self.orientation = orientation
        self.info = {} if info is None else info
        if source_vertex_map is not None and n_source_input is None:
            raise ValueError("source_vertex_map needs n_source_input (the number of vertices "
                             "of the source file)")
        self.source_vertex_map = source_vertex_map
        self.target_vertex_map = target_vertex_map
        self.n_source_input = n_source_input
        self._n_source = n_source

    @property
    def quality(self) -> MapQuality | None:
        if callable(self._quality):
            self._quality = self._quality(self)
        return self._quality

    @property
    def suspect(self) -> bool | None:
        q = self.quality
        return None if q is None else q.suspect

    def report(self) -> dict:
        """A JSON-able summary: torchheat's version, the options given that differ from
        :func:`~torchheat.match`'s defaults, vertex counts, method, the search that gave the map
        (``match(staged=True)``: ``"first stage"`` or ``"full ..."``), the near gap (how much
        worse the best partly different candidate scored), the tie-break of an
        ambiguous choice (``[chosen error, rival error]``), landmarks, orientation, quality,
        suspect, timings (what ``torchheat match --report`` writes, with the file
        names)."""
        from .. import __version__

        q = self.quality
        o = self.orientation
        return {
            "version": __version__,
            # the options given that differ from match's defaults (symmetry's own included)
            "options": dict(self.info.get("options", {})),
            "n_source": self.n_source,
            "n_target": None if self.info.get("n_target") is None
            else int(self.info["n_target"]),
            "method": self.info.get("method"),
            "zoomout": self.info.get("zoomout"),
            "fine_k": self.info.get("fine_k"),
            **({"search": self.info["search"]} if self.info.get("search") else {}),
            # how much worse the best partly different candidate scored (select._near_gap)
            **({"near_gap": float(self.info["near_gap"])}
               if self.info.get("near_gap") is not None else {}),
            # an ambiguous choice: wave kernel signature errors of the map and of its rival
            **({"tie_break": [float(e) for e in self.info["tie_break"]]}
               if self.info.get("tie_break") else {}),
            "landmarks": [[int(a), int(b)] for a, b in self.landmarks],
            "orientation": None if o != o else float(o),
            **({} if q is None else q.as_dict()),
            "symmetric_map": self.has_symmetric_map,
            "rival_map": self.has_rival_map,
            "timings": {k: float(v) for k, v in self.info.get("timings", {}).items()},
            **({"partial": part} if (part := self.partial_summary()) else {}),
        }

    def partial_summary(self) -> dict | None:
        """How a partial match was made (JSON-able): the area ratio, the share of the whole the
        piece covers once its holes are closed (``closed_ratio``), the way kept (``"piece"``,
        ``"filled"`` or ``"unit"``), why, and each way's agreement and quality; None for a
        full match."""
        part = self.info.get("partial")
        if not part:
            return None
        return {k: part[k] for k in ("ratio", "closed_ratio", "scale", "chosen_by", "agreement",
                                     "quality", "closed_quality") if k in part}

    @property
    def n_source(self) -> int | None:
        """Number of source vertices (the rows of :attr:`map`), also without a map."""
        if self._n_source is not None:
            return self._n_source
        m = self.map
        return None if m is None else int(m.numel())

    @property
    def map(self) -> torch.Tensor | None:
        if callable(self._map):
            self._map = self._map()
        return self._map

    @map.setter
    def map(self, value: torch.Tensor | None) -> None:
        self._map = value

    @property
    def symmetric_map(self) -> torch.Tensor | None:
        if callable(self._symmetric_map):
            self._symmetric_map = self._symmetric_map()
        return self._symmetric_map

    @symmetric_map.setter
    def symmetric_map(self, value: torch.Tensor | None) -> None:
        self._symmetric_map = value

    @property
    def has_symmetric_map(self) -> bool:
        """Whether a symmetric map was found (without computing it)."""
        return self._symmetric_map is not None

    @property
    def rival_map(self) -> torch.Tensor | None:
        if callable(self._rival_map):
            self._rival_map = self._rival_map()
        return self._rival_map

    @property
    def has_rival_map(self) -> bool:
        """Whether the choice had a rival (a different whole map), without computing it."""
        return self._rival_map is not None

    def swapped(
        self,
        *,
        orientation: float = float("nan"),
        quality: MapQuality | Callable[[Correspondence], MapQuality] | None = None,
    ) -> Correspondence:
        """The same match with the direct and the symmetric map exchanged.

        For when the symmetric alternative is the map wanted: :func:`~torchheat.symmetry`
        takes a shape's match with itself this way (its direct map is near the identity).
        Maps not yet computed stay deferred, and are computed once for both results. The
        candidates, scores, info and vertex numbering are shared; there is no rival map
        (the rival was the direct map's).

        Parameters
        ----------
        orientation : float
            Orientation score of the new direct map (default NaN: not tested).
        quality : MapQuality or callable, optional
            Its quality, or a function of the new result computing it on first access.

        Returns
        -------
        Correspondence

        Raises
        ------
        ValueError
            Without a symmetric map.

        Examples
        --------
        >>> c = Correspondence(torch.tensor([0, 1]), [(0, 0)], torch.tensor([0]),
        ...                    torch.tensor([0.0]), symmetric_map=torch.tensor([1, 0]),
        ...                    symmetric_landmarks=[(0, 1)])
        >>> s = c.swapped()
        >>> s.map.tolist(), s.symmetric_map.tolist(), s.landmarks
        ([1, 0], [0, 1], [(0, 1)])
        """
        if not self.has_symmetric_map:
            raise ValueError("this correspondence has no symmetric map to swap in")
        def shared(read: Callable[[], torch.Tensor | None]) -> Callable[[], torch.Tensor]:
            # through this result's property, which computes a deferred map once and keeps it
            def compute() -> torch.Tensor:
                out = read()
                assert out is not None  # (a deferred map returns one)
                return out
            return compute

        return Correspondence(
            map=(shared(lambda: self.symmetric_map) if callable(self._symmetric_map)
                 else self._symmetric_map),
            landmarks=list(self.symmetric_landmarks or []),
            candidates=self.candidates,
            scores=self.scores,
            symmetric_map=shared(lambda: self.map) if callable(self._map) else self._map,
            symmetric_landmarks=self.landmarks,
            orientation=orientation,
            info=self.info,
            source_vertex_map=self.source_vertex_map,
            target_vertex_map=self.target_vertex_map,
            n_source_input=self.n_source_input,
            n_source=self._n_source,
            quality=quality,
        )

    def full_map(self) -> torch.Tensor | None:
        """The direct map in the numbering of the input files.

        Returns
        -------
        torch.Tensor or None
            int64, shape (n_source_input,): for every vertex of the source *file*, the index
            in the target *file* of its image, or ``-1`` if the vertex was dropped by
            ``largest_component=True``. Equal to :attr:`map` when no vertex was dropped.
            None when :attr:`map` is (``match(final_map=False)``).

        Examples
        --------
        >>> import numpy as np, trimesh
        >>> from torchheat import Mesh, match
        >>> m = trimesh.creation.icosphere(2)
        >>> V = m.vertices * [1.0, 0.8, 0.6]
        >>> V2 = np.vstack([V, V[:3] + [5.0, 0, 0]])  # plus a stray triangle, far away
        >>> F2 = np.vstack([m.faces, [[162, 163, 164]]])
        >>> M = Mesh(V2, F2, largest_component=True)  # the triangle's vertices are dropped
        >>> corr = match(M, M, method="paper")
        >>> corr.map.shape, corr.full_map().shape
        (torch.Size([162]), torch.Size([165]))
        >>> corr.full_map()[-3:].tolist()
        [-1, -1, -1]
        """
        return self._in_files(self.map)

    def full_symmetric_map(self) -> torch.Tensor | None:
        """:attr:`symmetric_map` in the numbering of the input files (see :meth:`full_map`).

        Returns
        -------
        torch.Tensor or None
            int64, shape (n_source_input,), ``-1`` for dropped source vertices; None when
            there is no symmetric map.
        """
        return self._in_files(self.symmetric_map)

    def full_rival_map(self) -> torch.Tensor | None:
        """:attr:`rival_map` in the numbering of the input files (see :meth:`full_map`).

        Returns
        -------
        torch.Tensor or None
            int64, shape (n_source_input,), ``-1`` for dropped source vertices; None when
            the choice had no rival.
        """
        return self._in_files(self.rival_map)

    def _in_files(self, f: torch.Tensor | None) -> torch.Tensor | None:
        if f is None:
            return None
        if self.target_vertex_map is not None:
            f = self.target_vertex_map.to(f.device)[f]
        svm = self.source_vertex_map
        if svm is None or svm.numel() == self.n_source_input:
            return f  # nothing dropped: vertex_map is the identity
        assert self.n_source_input is not None  # (required with source_vertex_map)
        full = torch.full((int(self.n_source_input),), -1, dtype=f.dtype, device=f.device)
        full[svm.to(f.device)] = f
        return full

    def __repr__(self) -> str:
        n = ("lazy" if callable(self._map) else None if self._map is None
             else tuple(self._map.shape))
        return (f"Correspondence(map={n}, landmarks={len(self.landmarks)}, "
                f"symmetric={self.has_symmetric_map}, orientation={self.orientation:+.3f})")


def _numbering(src: PreparedShape, tgt: PreparedShape) -> dict:
    """The vertex numbering of the files behind two prepared shapes (Correspondence args);
    None for a mesh that kept all its vertices."""
    def vertex_map(mesh: Mesh) -> torch.Tensor | None:
        return None if mesh.n_vertices == mesh.n_input_vertices else mesh.vertex_map

    return {"source_vertex_map": vertex_map(src.mesh), "target_vertex_map": vertex_map(tgt.mesh),
            "n_source_input": src.mesh.n_input_vertices, "n_source": src.n}
