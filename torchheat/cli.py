"""Command line interface: ``torchheat match | symmetry | demo | evaluate | preprocess``.

Every command writes its outputs atomically (a temporary file in the destination directory,
then ``os.replace``) and only after all computations succeeded, so a failed run leaves no
output file behind. Bad input (missing or unreadable file, unsupported format, invalid mesh,
landmark out of range, unwritable output, ...) ends with exit status 1 and a single line
``torchheat: error: <file>: <problem>`` on stderr, without a traceback; command-line usage
errors exit with status 2 (argparse). Anything else is a bug and raises with a traceback.

Map files hold one 0-based target vertex index per line, one line per source vertex, in
source vertex order. With ``--largest-component`` the matcher runs on the largest connected
component of each mesh that has several; the map still has one line per vertex of the source
*file*, ``-1`` for the vertices that were dropped, and target indices are those of the target
*file* (``--landmark`` takes file indices too).

Warnings: torchheat's own (:class:`~torchheat.MeshWarning`, e.g. non-manifold edges) are
printed as one line ``torchheat: warning: ...``; warnings of the libraries underneath (numpy,
scipy, torch) are not shown by ``match``, ``symmetry`` and ``demo``.

Examples
--------
>>> main(["--version"])  # doctest: +SKIP
torchheat 0.1.0
0
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from ._files import atomic_writes
from .meshio import FORMATS_HELP

__all__ = ["main", "run", "build_parser", "write_map", "map_format", "inspect_mesh",
           "CLIError"]

PROG = "torchheat"
DATA = Path(__file__).resolve().parent / "data"
#: ``--fine``'s default size (``match(fine_k=...)``; RESULTS.md, nineteenth session)
FINE_K = 200

#: ``torchheat match``'s switches that turn off one stage of the default choice: (flag,
#: ``match`` keyword, help)
_CHOICE_SWITCHES = (
    ("--no-descriptor-seed", "descriptor_seed",
     "leave out the landmark-free hypothesis (a functional map of the shapes' wave kernel "
     "signatures with the orientation-preserving term) from the ZoomOut choice; with "
     "--partial, the partial functional map that seeds and scores the piece's hypotheses"),
    ("--no-trimmed-twins", "trimmed_twins",
     "leave out the orientation-trimmed twins of the ZoomOut candidates (each re-seeded from "
     "its samples whose neighbourhood keeps the orientation)"),
    ("--no-reoriented", "reoriented",
     "leave out the reoriented twins of the best-aligned ZoomOut candidates (each re-fitted as "
     "an orientation-preserving functional map that keeps where its points go) and the tear "
     "term of the ZoomOut score"),
    ("--no-polished", "polished",
     "choose among the ZoomOut candidates as they are; by default, when the full search runs, "
     "the candidates within the clear margin of the best are refined again before the choice "
     "(each distinct map's sample images: correspondence augmentation, then ZoomOut)"),
    ("--no-half-turns", "half_turns",
     "leave out the half-turn partners of the full search's best orientation-preserving "
     "ZoomOut candidates (each composed with the target's half-turn self-map: left/right and "
     "front/back swapped together)"),
    ("--no-tie-break", "tie_break",
     "keep an ambiguous choice as the ZoomOut score made it; by default the chosen map or its "
     "rival, whichever better keeps the wave kernel signatures, is kept"),
    ("--no-staged", "staged",
     "search from all 8 seeding source features at once; by default the hypotheses of the "
     "first 3 are tried first and their choice is kept when it is clear (margin and "
     "orientation), which saves much of the match time on most pairs"),
)


class CLIError(Exception):
    """A user error the CLI reports in one line (exit status 1)."""


# ------------------------------------------------------------------------------------------
# small helpers
# ------------------------------------------------------------------------------------------
def _version() -> str:
    try:
        from importlib.metadata import version

        return version("torchheat")
    except Exception:  # not installed as a distribution
        from . import __version__

        return __version__


def _one_line(msg: str) -> str:
    return " ".join(str(msg).split())


def _os_error_message(exc: OSError) -> str:
    if exc.filename is not None and exc.strerror:
        return f"{exc.filename}: {exc.strerror}"
    return str(exc)


def _check_output(path: Path, what: str = "output") -> Path:
    """Fail early (before any computation) when ``path`` cannot be written."""
    parent = path.parent if str(path.parent) else Path(".")
    if path.is_dir():
        raise CLIError(f"{path}: is a directory; give the {what} file name")
    if not parent.exists():
        raise CLIError(f"{path}: cannot write {what}: directory {parent} does not exist")
    if not parent.is_dir():
        raise CLIError(f"{path}: cannot write {what}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise CLIError(f"{path}: cannot write {what}: directory {parent} is not writable")
    return path


def _check_picture(path: str | None) -> Path | None:
    """``--png PATH`` checked before any work: writable, and a format the picture can take
    (from the extension: a .pdf or .svg was written as PNG bytes under that name)."""
    if not path:
        return None
    from .viz import picture_format

    try:
        picture_format(path)
    except ValueError as exc:
        raise CLIError(str(exc)) from None
    return _check_output(Path(path), "picture")


def write_map(path: str | os.PathLike[str], fmap: Any) -> None:
    """Write a vertex map in source vertex order: one 0-based target index per line, or a
    NumPy ``.npy`` file of int64 (``np.load`` reads it back).

    Parameters
    ----------
    path : str or os.PathLike
        Output file (overwritten; not atomic by itself, the CLI writes to a temporary file
        first).
    fmap : array_like or torch.Tensor of int, shape (n,)

    The format comes from ``path``'s extension (:func:`map_format`; the CLI's temporary files
    keep the extension of the name they will get).

    Examples
    --------
    >>> import os, tempfile
    >>> import numpy as np
    >>> d = tempfile.mkdtemp()
    >>> write_map(os.path.join(d, "map.txt"), [2, 0, 1])
    >>> open(os.path.join(d, "map.txt")).read()
    '2\\n0\\n1\\n'
    >>> write_map(os.path.join(d, "map.npy"), [2, 0, 1])
    >>> np.load(os.path.join(d, "map.npy")).tolist()
    [2, 0, 1]
    """
    import numpy as np

    from ._arrays import to_numpy

    f = to_numpy(fmap, dtype=np.int64).reshape(-1)
    if map_format(path) == "npy":
        with open(path, "wb") as fh:  # a handle: np.save would append .npy to a bare name
            np.save(fh, f)
        return
    with open(path, "w", encoding="ascii") as fh:
        if f.size:
            fh.write("\n".join(map(str, f.tolist())))
            fh.write("\n")


def map_format(path: str | os.PathLike[str]) -> str:
    """``"npy"`` for a path ending in ``.npy`` (any case), else ``"txt"`` (see
    :func:`write_map`)."""
    return "npy" if Path(path).suffix.lower() == ".npy" else "txt"


def _plausible(V: Any, F: Any) -> bool:
    """Whether ``(V, F)`` may be a triangle mesh (faces, in range); :class:`Mesh` checks the
    rest. Implausible arrays are never sent to an eigensolve worker (a doomed solve)."""
    import numpy as np

    F = np.asarray(F)
    return bool(F.ndim == 2 and F.shape[1] == 3 and F.size > 0
                and np.issubdtype(F.dtype, np.integer) and F.min() >= 0 and F.max() < len(V))


def _largest_piece(V: Any, F: Any) -> Any:
    """The vertices ``Mesh(V, F, largest_component=True)`` keeps, computed without torch.

    None when nothing is dropped, or when the arrays are ones :class:`Mesh` refuses anyway
    (no faces, indices out of range): its error is then reported.
    """
    import numpy as np

    from .topology import largest_component

    if not _plausible(V, F):
        return None
    return largest_component(np.asarray(F).astype(np.int64, copy=False), len(V))


def _closed_source(solved: list[tuple[Any, Any]]) -> tuple[Any, Any] | None:
    """The first mesh (a piece) with its holes closed (:func:`torchheat.topology.fill_holes`,
    its faces first oriented as :class:`torchheat.Mesh` orients them) when the filled way of a
    partial match will want it — it has holes, and closed it covers at least
    :data:`torchheat.topology.FILLED_LEAST` of the second mesh's area — else None. Numpy only
    (it runs before torch is imported)."""
    import numpy as np

    from .geometry import face_areas
    from .topology import FILLED_LEAST, fill_holes, orient_faces, orient_outward

    (V, F), (Vt, Ft) = solved[0], solved[1]
    if not (_plausible(V, F) and _plausible(Vt, Ft)):
        return None
    V, F = np.asarray(V, dtype=np.float64), np.asarray(F, dtype=np.int64)
    try:
        F = orient_faces(F, len(V))[0]  # as Mesh turns them (SHREC'16's david and michael)
        F = orient_outward(V, F)[0]
        V2, F2 = fill_holes(V, F)
    except Exception:  # noqa: BLE001 - the match itself reports what is wrong with the piece
        return None
    Vt, Ft = np.asarray(Vt, dtype=np.float64), np.asarray(Ft, dtype=np.int64)
    if len(V2) == len(V) or face_areas(V2, F2).sum() < FILLED_LEAST * face_areas(Vt, Ft).sum():
        return None
    return V2, F2


#: the eigensolve workers' nice value: ``import torch`` in this process is what the command waits
#: on first, and on two cores three busy processes slowed it (BENCHMARKS.md, twenty-eighth
#: session)
_WORKER_NICE = 10


def _load_and_prepare(paths: Sequence[str], args: argparse.Namespace,
                      check: Callable[[list[Any]], Any] | None = None,
                      close_source: bool = False,
                      ) -> tuple[list[Any], list[Any], Any, dict[str, float]]:
    """Read ``paths``, solve their eigenpairs in background processes, prepare the shapes.

    The files are read with numpy only; the eigensolves (the costliest step of preparing a
    shape) start in worker processes (:class:`torchheat.eigen.EigenWorkers`, ``--workers``)
    *before* torch is imported, so that ``import torch`` and both solves share the cores (the
    workers at a lower priority, ``_WORKER_NICE``: the import is what the command waits on).
    With ``--largest-component`` the workers solve the largest component of each mesh (found
    with numpy, :func:`torchheat.topology.largest_component`, as :class:`Mesh` does).
    Meshes too small to match are refused (:func:`torchheat.matching._check_matchable`), then
    ``check(meshes)`` runs on the validated meshes before anything is prepared. Returns the
    meshes, the prepared shapes, what ``check`` returned and timings.

    ``close_source``: the first mesh is a piece to match ``partial=True`` into the second; its
    holes are closed with numpy too and the closed mesh is solved by the workers as well
    (:func:`_closed_source`), then given to the prepared piece
    (:func:`torchheat.matching.partial_scale.offer_filled`) for the filled way.
    """
    import numpy as np

    from .eigen import DEFAULT_EIGENPAIRS, EigenWorkers, fine_k_problem
    from .meshio import read_arrays
    from .topology import restrict_faces

    t0 = time.perf_counter()
    arrays = [read_arrays(p) for p in paths]
    largest = bool(getattr(args, "largest_component", False))
    pieces = [_largest_piece(V, F) if largest else None for V, F in arrays]
    solved = [(V, F) if k is None else (np.asarray(V)[k], restrict_faces(np.asarray(F), k, len(V)))
              for (V, F), k in zip(arrays, pieces, strict=True)]
    workers = args.workers if all(_plausible(V, F) for V, F in arrays) else 0  # Mesh refuses
    closed = _closed_source(solved) if close_source and workers != 0 else None
    jobs = solved if closed is None else [*solved, closed]
    ks = [DEFAULT_EIGENPAIRS] * len(jobs)
    fine = getattr(args, "fine", None)
    if fine is not None and (why := fine_k_problem(int(fine), min(len(V) for V, _ in solved))):
        raise CLIError(f"--fine {fine}: {why}")  # before any worker solves it
    n_fine = len(solved) if fine is not None and fine > DEFAULT_EIGENPAIRS and workers != 0 \
        else 0
    if n_fine:  # --fine: each mesh's larger basis too, solved after the default one
        assert fine is not None  # (n_fine)
        jobs, ks = [*jobs, *solved], [*ks, *[int(fine)] * n_fine]
    with EigenWorkers(jobs, k=ks, processes=workers, nice=_WORKER_NICE) as bg:
        from .mesh import Mesh  # imports torch, while the workers solve

        meshes = []
        for (V, F), p in zip(arrays, paths, strict=True):
            meshes.append(Mesh(V, F, name=str(p), largest_component=largest))
        from .matching import _check_matchable, prepare

        for m in meshes:
            _check_matchable(m, DEFAULT_EIGENPAIRS, remedy="use a finer mesh (subdivide it)")
        checked = check(meshes) if check is not None else None

        def eigenpairs(i: int) -> Any:
            # the workers' vertices must be the mesh's (they are: same rule, same arrays)
            n, piece = len(solved[i][0]), pieces[i]
            if n != meshes[i].n_vertices or (piece is not None and not np.array_equal(
                    piece, meshes[i].vertex_map.numpy())):
                return None
            return bg.get(i)

        t1 = time.perf_counter()
        prepared = [prepare(m, times=args.times, k=DEFAULT_EIGENPAIRS, eigenpairs=eigenpairs(i),
                            num_threads=args.threads) for i, m in enumerate(meshes)]
        if closed is not None and (eig := bg.get(len(solved))) is not None:
            from .matching.partial_scale import offer_filled

            offer_filled(prepared[0], *closed, eig)
        for i in range(n_fine):
            if eigenpairs(i) is not None and (eig := bg.get(len(ks) - n_fine + i)) is not None:
                from .matching.prepared import offer_basis

                offer_basis(prepared[i], *eig)
        n_bg = bg.running
    t2 = time.perf_counter()
    where = f"in {n_bg} background process{'es' if n_bg != 1 else ''}" if n_bg \
        else "in-process"
    return meshes, prepared, checked, {"read + import torch": t1 - t0,
                                       f"prepare (eigensolves {where})": t2 - t1}


def _timings(t_prep: dict[str, float], corr: Any) -> dict[str, float]:
    """The command's preparation timings, then those of ``match``; its own "prepare" (~0 for
    prepared shapes, but a partial match's filled way prepares the closed piece there) is
    shown as "match prepare" when it takes 10 ms or more."""
    names = {"total": "match total", "prepare": "match prepare"}
    return {**t_prep, **{names.get(k, k): v for k, v in corr.info.get("timings", {}).items()
                         if k != "prepare" or v >= 0.01}}


def _mesh_index(v: int, mesh: Any, path: str, name: str, role: str) -> int:
    """The mesh's index of the file's vertex ``v`` (they differ with --largest-component)."""
    import numpy as np

    n_in = mesh.n_input_vertices
    if not 0 <= v < n_in:
        raise CLIError(
            f"{path}: --landmark {name}={v} is out of range; the {role} has "
            f"{n_in} vertices (valid 0..{n_in - 1})"
        )
    if mesh.n_vertices == n_in:
        return v
    kept = mesh.vertex_map.numpy()  # sorted
    i = int(np.searchsorted(kept, v))
    if i < kept.size and kept[i] == v:
        return i
    raise CLIError(
        f"{path}: --landmark {name}={v} is on a piece dropped by --largest-component (the "
        f"largest connected component keeps {mesh.n_vertices} of the {n_in} vertices); "
        f"choose a {role} vertex of the largest component"
    )


def _check_landmark(landmark: list[int] | None, source: Any, target: Any,
                    src_path: str, tgt_path: str) -> int | tuple[int, int] | None:
    """``--landmark P [Q]`` (file indices) as indices of the meshes that are matched."""
    if not landmark:
        return None
    if len(landmark) > 2:
        raise CLIError(f"--landmark takes P or P Q (two vertex indices), got {len(landmark)}")
    p = _mesh_index(landmark[0], source, src_path, "P", "source")
    if len(landmark) == 1:
        return p
    return (p, _mesh_index(landmark[1], target, tgt_path, "Q", "target"))


def _in_files(idx: Any, vertex_map: Any) -> list[int]:
    """Mesh vertex indices as indices of the file (``vertex_map``; None: the same)."""
    idx = [int(i) for i in idx]
    return idx if vertex_map is None else [int(vertex_map[i]) for i in idx]


def _pieces(mesh: Any) -> str:
    """`` (largest component: k of n vertices, n - k written as -1)`` or ``""``, and a note
    when the surface was wound inside out (its faces reversed at load)."""
    n, n_in = mesh.n_vertices, mesh.n_input_vertices
    out = "" if n == n_in else f" ({n} in the largest connected component, {n_in - n} dropped)"
    if getattr(mesh, "turned_outward", False):
        out += " (wound inside out: its faces were reversed to face outward)"
    return out


def _fmt_pairs(pairs: Sequence[tuple[int, int]], k: int = 5) -> str:
    head = ", ".join(f"({int(a)}, {int(b)})" for a, b in list(pairs)[:k])
    more = len(pairs) - k
    return head + (f", ... (+{more})" if more > 0 else "")


def _report(corr: Any, *, label: str = "map", k: int = 5) -> None:
    """Print the landmarks, candidate scores, orientation and timings of a correspondence."""
    import math

    svm, tvm = corr.source_vertex_map, corr.target_vertex_map  # printed as file indices
    lms = list(zip(_in_files([a for a, _ in corr.landmarks], svm),
                   _in_files([b for _, b in corr.landmarks], tvm), strict=True))
    print(f"landmarks ({len(lms)} pairs source -> target): {_fmt_pairs(lms)}")
    cands = _in_files(corr.candidates.tolist()[:k], tvm)
    scores = corr.scores.tolist()[:k]
    ranked = ", ".join(f"{c}: {s:.3e}" for c, s in zip(cands, scores, strict=True))
    p = corr.info.get("p", corr.landmarks[0][0] if corr.landmarks else None)
    if p is not None:
        p = _in_files([p], svm)[0]
        print(f"top candidates for p={p} (target vertex: score E, lower is better): {ranked}")
    else:  # the landmark was a vertex added to close a hole (partial_scale="filled")
        print(f"top candidates for the first landmark (a vertex of a filled hole): {ranked}")
    o = corr.orientation
    if isinstance(o, float) and math.isnan(o):
        print("orientation score: not tested (method 'paper')")
    else:
        print(f"orientation score of the {label}: {o:+.3f} (+1 preserving, -1 reversing)")
    print(f"symmetric alternative: {'found' if corr.has_symmetric_map else 'none'}")
    part = corr.partial_summary()
    if part:
        how = f" ({part['chosen_by']})" if part.get("chosen_by") else ""
        print(f"partial: the source is {100 * part['ratio']:.0f} % of the target's area; "
              f"matched as '{part['scale']}'{how}")
    q = corr.quality
    if q is not None:
        verdict = ("SUSPECT: probably wrong (not near-isometric, or the mirror map)"
                   if q.suspect else "plausible")
        print(f"quality of the {label}: {q.quality:.2f} ({verdict}; isometry defect "
              f"{q.defect:.2f}, 0 = isometric)")
        if q.margin is not None:
            note = ("AMBIGUOUS: a different whole map scored nearly as well"
                    if q.ambiguous else "clear")
            print(f"margin of the choice: {q.margin:.2f} ({note}; the best rival scored that "
                  "much worse; --rival-out writes it)")
            tb = corr.info.get("tie_break")
            if tb:
                print(f"settled by the wave kernel signatures: mean log-WKS error {tb[0]:.4f} "
                      f"against the rival's {tb[1]:.4f}")
    search = corr.info.get("search")
    if search:  # which stage of the staged search gave the map (match(staged=...))
        print(f"search: {search}")
    timings = corr.info.get("timings", {})
    if timings:
        print("timings: " + ", ".join(f"{name} {sec:.2f} s" for name, sec in timings.items()))


def _repairs(mesh: Any) -> dict:
    """What loading changed in a file (JSON-able): faces reversed, whether the whole surface
    was turned outward, vertices dropped with ``--largest-component``."""
    return {"flipped_faces": int(getattr(mesh, "flipped_faces", 0)),
            "turned_outward": bool(getattr(mesh, "turned_outward", False)),
            "dropped_vertices": int(mesh.n_input_vertices - mesh.n_vertices)}


def _write_report(path: Path, corr: Any, source: str, target: str,
                  meshes: tuple[Any, Any] | None = None) -> None:
    import json
    import re

    from ._provenance import provenance

    rep = {"source": str(source), "target": str(target), **corr.report(),
           "provenance": provenance()}  # versions, git commit, BLAS, CPU, time
    if meshes is not None:  # what loading repaired in each file
        rep["repairs"] = {"source": _repairs(meshes[0]), "target": _repairs(meshes[1])}
    svm, tvm = corr.source_vertex_map, corr.target_vertex_map  # file indices, as the map
    rep["landmarks"] = [list(p) for p in zip(_in_files([a for a, _ in corr.landmarks], svm),
                                             _in_files([b for _, b in corr.landmarks], tvm),
                                             strict=True)]
    rep["n_source"] = corr.n_source_input or rep["n_source"]
    text = json.dumps(rep, indent=1)
    text = re.sub(r"\[\s+(-?\d+),\s+(-?\d+)\s+\]", r"[\1, \2]", text)  # pairs on one line
    Path(path).write_text(text + "\n")


# ------------------------------------------------------------------------------------------
# commands
# ------------------------------------------------------------------------------------------
def _cmd_match(args: argparse.Namespace) -> int:
    out = _check_output(Path(args.output), "map")
    sym_out = _check_output(Path(args.symmetric_out), "symmetric map") \
        if args.symmetric_out else None
    rival_out = _check_output(Path(args.rival_out), "rival map") if args.rival_out else None
    png = _check_picture(args.png)
    method = args.method or ("paper" if args.landmarks > 1 else "refine")
    if args.landmarks < 1:
        raise CLIError(f"--landmarks must be >= 1, got {args.landmarks}")
    if args.landmarks > 1 and method == "refine":
        print(f"{PROG}: note: --landmarks {args.landmarks} is used by method 'paper' only; "
              "method 'refine' places its own landmarks", file=sys.stderr)
    if args.fine is not None and (args.partial or not args.zoomout or method == "paper"):
        raise CLIError("--fine refines the default pipeline's spectral maps of whole shapes: "
                       "drop --partial, --no-zoomout and --method paper to use it")

    t_start = time.perf_counter()
    (source, target), (ps, pt), landmark, t_prep = _load_and_prepare(
        [args.source, args.target], args,
        check=lambda ms: _check_landmark(args.landmark, ms[0], ms[1], args.source, args.target),
        close_source=args.partial and args.partial_scale in (None, "auto", "filled"))

    from .matching import match

    if args.partial_margin is not None and not args.partial:
        raise CLIError("--partial-margin needs --partial")
    if args.partial_scale is not None and not args.partial:
        raise CLIError("--partial-scale needs --partial")
    part_kw: dict[str, Any] = {"partial": True} if args.partial else {}
    if args.partial_scale is not None:
        part_kw["partial_scale"] = args.partial_scale
    if args.partial_margin is not None:
        if not args.partial_margin >= 0:
            raise CLIError(f"--partial-margin must be >= 0, got {args.partial_margin}")
        part_kw["partial_margin"] = args.partial_margin
    corr = match(ps, pt, landmark=landmark, landmarks=args.landmarks, method=method,
                 engine=args.engine, num_threads=args.threads, zoomout=args.zoomout,
                 fine_k=args.fine, verify_stage=args.verify_stage,
                 **{dest: getattr(args, dest) for _, dest, _ in _CHOICE_SWITCHES},
                 **part_kw)
    corr.map  # noqa: B018 - the dense map is computed on first access: time it here
    if sym_out is not None:
        corr.symmetric_map  # noqa: B018
    if rival_out is not None:
        corr.rival_map  # noqa: B018
    elapsed = time.perf_counter() - t_start
    corr.info["timings"] = _timings(t_prep, corr)
    if sym_out is not None and corr.symmetric_map is None:
        print(f"{PROG}: warning: no symmetric map was found; {sym_out} is not written",
              file=sys.stderr)
    if rival_out is not None and corr.rival_map is None:
        print(f"{PROG}: warning: the choice had no rival (a different whole map; only the "
              f"default method with ZoomOut has them); {rival_out} is not written",
              file=sys.stderr)
    with atomic_writes() as outs:
        # the files' numbering
        outs.stage(out, lambda p: write_map(p, corr.full_map()))
        if args.report:
            outs.stage(_check_output(Path(args.report), "report"),
                       lambda p: _write_report(p, corr, args.source, args.target,
                                               (source, target)))
        if sym_out is not None and corr.symmetric_map is not None:
            outs.stage(sym_out, lambda p: write_map(p, corr.full_symmetric_map()))
        if rival_out is not None and corr.rival_map is not None:
            outs.stage(rival_out, lambda p: write_map(p, corr.full_rival_map()))
        if png is not None:
            from .viz import color_transfer

            outs.stage(png, lambda p: color_transfer(  # the matched pieces
                source, target, corr.map, p,
                title=f"{Path(args.source).name} -> {Path(args.target).name} ({method})"))
    print(f"source {args.source}: {source.n_input_vertices} vertices{_pieces(source)}; "
          f"target {args.target}: {target.n_input_vertices} vertices{_pieces(target)}; "
          f"method {method}; read, prepared and matched in {elapsed:.2f} s")
    _report(corr, label="direct map")
    dropped = source.n_input_vertices - source.n_vertices
    print(f"map written to {out}" + (f" ({dropped} dropped source vertices written as -1)"
                                     if dropped else ""))
    if sym_out is not None and corr.symmetric_map is not None:
        print(f"symmetric map written to {sym_out}")
    if rival_out is not None and corr.rival_map is not None:
        print(f"rival map written to {rival_out}")
    if png is not None:
        print(f"colour transfer written to {png}")
    return 0


def inspect_mesh(path: str | os.PathLike[str], largest_component: bool = False) -> dict:
    """What loading a mesh file finds, as :func:`torchheat.load_mesh` and ``match`` see it
    (JSON-able): whether it can be matched, else why (``error``); its size, area, bounding-box
    diagonal, boundary loops, Euler characteristic and genus, what loading repaired (faces
    reversed, the surface turned outward, vertices dropped) and the warnings it gave.

    Parameters
    ----------
    path : str or os.PathLike
    largest_component : bool
        As ``--largest-component``: keep the largest connected component.

    Returns
    -------
    dict
        ``{"file", "ok", "error", "warnings"}`` and, when it loads, ``vertices, faces, area,
        diagonal, boundary_loops`` (their vertex counts, longest first), ``euler, genus``
        (None unless an orientable manifold), ``nonmanifold_edges``, ``pinched_vertices``
        (boundary vertices where two holes touch) and ``repairs``.

    Examples
    --------
    >>> import os, tempfile, trimesh
    >>> p = os.path.join(tempfile.mkdtemp(), "ball.off")
    >>> _ = trimesh.creation.icosphere(3).export(p)
    >>> r = inspect_mesh(p)
    >>> r["ok"], r["vertices"], r["boundary_loops"], r["genus"]
    (True, 642, [], 0)
    """
    import warnings as _w

    from .mesh import MeshError, load_mesh
    from .topology import boundary_loops, pinched_vertices

    out: dict[str, Any] = {"file": str(path), "ok": False, "error": None}
    with _w.catch_warnings(record=True) as caught:
        _w.simplefilter("always")
        try:
            mesh = load_mesh(path, largest_component=largest_component)
            from .eigen import DEFAULT_EIGENPAIRS
            from .matching import _check_matchable

            _check_matchable(mesh, DEFAULT_EIGENPAIRS, remedy="use a finer mesh (subdivide it)")
        except MeshError as exc:
            out["error"] = str(exc)
            mesh = None
    out["warnings"] = [str(w.message) for w in caught
                       if type(w.message).__module__.startswith("torchheat")]
    if mesh is None:
        return out
    V, F = mesh.numpy()
    loops = sorted((len(lp) for lp in boundary_loops(F, mesh.n_vertices)), reverse=True)
    _, counts = mesh._edges_cached()
    nonmanifold = int((counts > 2).sum())
    pinched = int(pinched_vertices(F, mesh.n_vertices).size)  # no manifold there
    euler = mesh.n_vertices - int(counts.size) + mesh.n_faces
    # the genus of an orientable manifold surface (none for other surfaces)
    surface = getattr(mesh, "_oriented", False) and not nonmanifold and not pinched
    out.update(ok=True, vertices=mesh.n_vertices, faces=mesh.n_faces, area=mesh.area(),
               diagonal=mesh.bbox_diagonal(), boundary_loops=loops, euler=euler,
               genus=(2 - euler - len(loops)) // 2 if surface else None,
               nonmanifold_edges=nonmanifold, pinched_vertices=pinched,
               repairs=_repairs(mesh))
    return out


def _check_line(r: dict) -> str:
    """One :func:`inspect_mesh` report as the line ``torchheat check`` prints."""
    from .meshio import _plural

    if not r["ok"]:
        return f"{r['file']}: REFUSED: {r['error']}"
    loops = r["boundary_loops"]
    shape = "closed" if not loops else (
        f"{_plural(len(loops), 'boundary loop')} ({', '.join(map(str, loops[:5]))}"
        f"{', ...' if len(loops) > 5 else ''} vertices)")
    if r["genus"] is not None:
        genus = f"genus {r['genus']}"
    elif r["nonmanifold_edges"]:
        genus = _plural(r["nonmanifold_edges"], "non-manifold edge")
    elif r["pinched_vertices"]:
        genus = f"{_plural(r['pinched_vertices'], 'pinched vertex')} (holes touching: no genus)"
    else:
        genus = "not orientable"
    rep = r["repairs"]
    fixed = [text for n, text in ((rep["flipped_faces"], f"{rep['flipped_faces']} faces reversed"),
                                  (rep["turned_outward"], "turned outward"),
                                  (rep["dropped_vertices"], f"{rep['dropped_vertices']} vertices "
                                   "dropped (other components)")) if n]
    return (f"{r['file']}: ok: {r['vertices']} vertices, {r['faces']} faces, {shape}, {genus}; "
            f"area {r['area']:.4g}, diagonal {r['diagonal']:.4g}; repairs: "
            f"{', '.join(fixed) if fixed else 'none'}")


def _cmd_check(args: argparse.Namespace) -> int:
    import json

    reports = [inspect_mesh(p, args.largest_component) for p in args.meshes]
    refused = sum(not r["ok"] for r in reports)
    if args.json:
        print(json.dumps(reports, indent=1))
        return 0 if not refused else 1
    for r in reports:
        print(_check_line(r))
        for w in r["warnings"]:
            print(f"  warning: {w}")
    if len(reports) > 1:
        print(f"{len(reports)} files: {len(reports) - refused} can be matched, {refused} "
              f"refused, {sum(bool(r['warnings']) for r in reports)} with warnings")
    return 0 if not refused else 1


def _cmd_symmetry(args: argparse.Namespace) -> int:
    out = _check_output(Path(args.output), "map")
    png = _check_picture(args.png)
    if args.fine is not None and not args.zoomout:
        raise CLIError("--fine refines the spectral self-map: drop --no-zoomout to use it")
    t_start = time.perf_counter()
    (mesh,), (shape,), landmark, t_prep = _load_and_prepare(
        [args.mesh], args,
        check=lambda ms: _check_landmark(args.landmark, ms[0], ms[0], args.mesh, args.mesh))
    if isinstance(landmark, tuple):
        raise CLIError("symmetry takes --landmark P (one source vertex) only")

    from .matching import symmetry

    corr = symmetry(shape, landmark=landmark, engine=args.engine, num_threads=args.threads,
                    zoomout=args.zoomout, fine_k=args.fine)
    corr.map  # noqa: B018 - computed on first access: time it here
    elapsed = time.perf_counter() - t_start
    corr.info["timings"] = _timings(t_prep, corr)
    if not corr.has_symmetric_map:
        print(f"{PROG}: warning: no orientation-reversing self-map was found; the written "
              "map is the best direct self-map (close to the identity)", file=sys.stderr)
    with atomic_writes() as outs:
        # the file's numbering
        outs.stage(out, lambda p: write_map(p, corr.full_map()))
        if args.report:
            outs.stage(_check_output(Path(args.report), "report"),
                       lambda p: _write_report(p, corr, args.mesh, args.mesh, (mesh, mesh)))
        if png is not None:
            from .viz import color_transfer

            outs.stage(png, lambda p: color_transfer(
                mesh, mesh, corr.map, p, title=f"symmetry of {Path(args.mesh).name}"))
    print(f"mesh {args.mesh}: {mesh.n_input_vertices} vertices{_pieces(mesh)}; read, prepared "
          f"and symmetry found in {elapsed:.2f} s")
    _report(corr, label="symmetry map")
    dropped = mesh.n_input_vertices - mesh.n_vertices
    print(f"self-map written to {out}" + (f" ({dropped} dropped vertices written as -1)"
                                          if dropped else ""))
    if png is not None:
        print(f"colour transfer written to {png}")
    return 0


def _demo_dir(args: argparse.Namespace) -> Path:
    out_dir = Path(args.out)
    try:
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CLIError(f"{out_dir}: cannot create the output directory "
                       f"({exc.strerror or exc})") from exc
    return out_dir


#: The piece of the partial demo: the faces of the cow Spot in front of this fraction of its
#: length (head, front legs and most of the body; both sides, so the map has an orientation to
#: keep), matched into the whole cow moved and renumbered.
_DEMO_CUT = 0.66


def _cmd_demo_partial(args: argparse.Namespace) -> int:
    import numpy as np

    from .mesh import Mesh, load_mesh

    out_dir = _demo_dir(args)
    map_path = _check_output(out_dir / "spot_partial_map.txt", "map")
    png_path = _check_output(out_dir / "spot_partial_map.png", "PNG")
    path = DATA / "spot.obj"
    t0 = time.perf_counter()
    whole = load_mesh(path)
    V, F = whole.numpy()
    cut = np.quantile(V[:, 2], _DEMO_CUT)
    piece = Mesh(V, F[(V[F, 2] <= cut).all(axis=1)], name=f"{path.name}, z <= {cut:.3f}",
                 largest_component=True)
    # the whole, rotated and with its vertices renumbered: nothing is shared but the surface
    rng = np.random.default_rng(0)
    order = rng.permutation(len(V))
    c, s_ = np.cos(0.9), np.sin(0.9)
    R = np.array([[c, -s_, 0.0], [s_, c, 0.0], [0.0, 0.0, 1.0]])
    inverse = np.argsort(order)
    target = Mesh(V[order] @ R.T, inverse[F], name=f"{path.name}, moved and renumbered")
    from .matching import match, prepare

    corr = match(prepare(piece), prepare(target), partial=True, num_threads=args.threads)
    f = corr.map.numpy()
    elapsed = time.perf_counter() - t0
    truth = inverse[piece.vertex_map.numpy()]
    W = target.vertices.numpy()
    diag = target.bbox_diagonal()
    dist = np.linalg.norm(W[f] - W[truth], axis=1) / diag
    within = float(np.mean(dist <= 0.02))
    with atomic_writes() as outs:
        outs.stage(map_path, lambda p: write_map(p, f))
        from .viz import color_transfer

        outs.stage(png_path, lambda p: color_transfer(
            piece, target, f, p, errors=dist,
            title=(f"partial: front {100 * _DEMO_CUT:.0f} % of Spot -> the whole (moved, "
                   f"renumbered): {100 * within:.1f} % within 2 % of the bbox diagonal")))
    print(f"demo (partial): the front of {path.name} ({piece.n_vertices} of {whole.n_vertices} "
          f"vertices, {100 * corr.info['partial']['ratio']:.0f} % of the area, cut at run time) "
          f"-> the whole cow, rotated and renumbered; ground truth: the cut's vertex map")
    print(f"time: {elapsed:.1f} s (loading + matching; '{corr.info['partial']['scale']}' "
          "chosen, see 'partial:' below)")
    _report(corr, label="direct map")
    print(f"within 2 % of the bounding-box diagonal: {100 * within:.1f} % of the piece's "
          f"vertices; mean error {100 * float(dist.mean()):.2f} % of the diagonal (Euclidean)")
    print(f"map written to {map_path}")
    print(f"colour transfer written to {png_path}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    import numpy as np

    if args.partial:
        return _cmd_demo_partial(args)
    out_dir = _demo_dir(args)
    map_path = _check_output(out_dir / "ogre_map.txt", "map")
    png_path = _check_output(out_dir / "ogre_map.png", "PNG")
    src_path, tgt_path = DATA / "bs_rest.obj", DATA / "bs_smile.obj"

    t0 = time.perf_counter()
    (source, target), (ps, pt), _, t_prep = _load_and_prepare([str(src_path), str(tgt_path)],
                                                              args)

    from .matching import match

    corr = match(ps, pt, method=args.method, engine=args.engine, num_threads=args.threads)
    corr.map  # noqa: B018 - computed on first access: time it here
    elapsed = time.perf_counter() - t0
    corr.info["timings"] = _timings(t_prep, corr)

    n = source.n_vertices
    f = corr.map.numpy()
    W = target.vertices.numpy()
    diag = target.bbox_diagonal()
    dist = np.linalg.norm(W[f] - W[np.arange(n)], axis=1) / diag  # ground truth: identity
    exact = float(np.mean(f == np.arange(n)))
    within = float(np.mean(dist <= 0.01))
    sym_note = ""
    if corr.symmetric_map is not None:
        fs = corr.symmetric_map.numpy()
        ds = np.linalg.norm(W[fs] - W, axis=1) / diag
        sym_within = float(np.mean(ds <= 0.01))
        sym_note = (f"symmetric alternative map (not written): "
                    f"{100 * np.mean(fs == np.arange(n)):.1f} % exact, "
                    f"{100 * sym_within:.1f} % within 1 % (Euclidean)")
        if sym_within > within:
            sym_note += ("\nnote: the symmetric alternative is closer to the ground truth than "
                         "the direct map, i.e. the direct map is the left/right mirror; "
                         "intrinsic descriptors cannot tell a map from its mirror image")
    with atomic_writes() as outs:
        outs.stage(map_path, lambda p: write_map(p, f))
        from .viz import color_transfer

        outs.stage(png_path, lambda p: color_transfer(
            source, target, f, p, errors=dist,
            title=(f"ogre bs_rest -> bs_smile ({args.method}): {100 * exact:.1f} % exact, "
                   f"{100 * within:.1f} % within 1 % of the bbox diagonal "
                   "(error = Euclidean / diagonal)")))

    print(f"demo: ogre blend shapes {src_path.name} -> {tgt_path.name} "
          f"(ground truth: identity)")
    print(f"vertices: {n} source, {target.n_vertices} target")
    print(f"time: {elapsed:.1f} s (loading + matching, method {args.method})")
    _report(corr, label="direct map")
    print(f"mapped exactly (map[i] == i): {100 * exact:.1f} % of vertices")
    print(f"within 1 % of the bounding-box diagonal ({diag:.3f}; Euclidean distance between "
          f"target vertices map[i] and i, not geodesic): {100 * within:.1f} % of vertices")
    print(f"mean error: {100 * float(dist.mean()):.2f} % of the diagonal (Euclidean); median "
          f"{100 * float(np.median(dist)):.2f} %")
    if sym_note:
        print(sym_note)
    print(f"map written to {map_path}")
    print(f"colour transfer written to {png_path}")
    return 0


def _cmd_batch(command: str, rest: list[str]) -> int:
    """``evaluate`` / ``preprocess``: parsed and run by :mod:`torchheat.batch`."""
    try:
        from . import batch
    except ModuleNotFoundError as exc:
        if exc.name not in ("torchheat.batch",):
            raise
        raise CLIError(f"the {command} command needs torchheat.batch, which is not available "
                       "in this installation") from exc
    rc = (batch.main if command == "evaluate" else batch.preprocess_main)(list(rest))
    return 0 if rc is None else int(rc)


# ------------------------------------------------------------------------------------------
# parser
# ------------------------------------------------------------------------------------------
class _Formatter(argparse.RawDescriptionHelpFormatter):
    """Wraps one-line paragraphs of descriptions; keeps multi-line blocks (examples) as is."""

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        import textwrap

        paras = text.split("\n\n")
        return "\n\n".join(
            p if "\n" in p else textwrap.fill(p, width, initial_indent=indent,
                                              subsequent_indent=indent)
            for p in paras
        )


def _int_at_least(least: int) -> Callable[[str], int]:
    """An argparse type: an integer of at least ``least`` (a smaller one is refused by
    argparse with the option's name instead of failing later, or being taken for 0)."""
    def parse(text: str) -> int:
        value = int(text)  # not an integer: argparse's "invalid int value"
        if value < least:
            raise argparse.ArgumentTypeError(f"must be at least {least}, not {value}")
        return value

    parse.__name__ = "int"
    return parse


def _add_common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--engine", choices=("auto", "cdist", "kdtree"), default="auto",
                   help="nearest-neighbour engine of the L-infinity searches (default: auto, "
                        "a k-d tree on the CPU)")
    p.add_argument("--times", choices=("adaptive", "paper"), default="adaptive",
                   help="heat kernel time samples: 'adaptive' (from the shape's spectrum) or "
                        "'paper' (10 in [0.001, 2] at unit area); default: adaptive")
    p.add_argument("--threads", type=_int_at_least(1), default=None, metavar="N",
                   help="torch threads (default: torch's own choice)")
    p.add_argument("--workers", type=_int_at_least(0), default=None, metavar="N",
                   help="background processes that solve the meshes' eigenpairs while torch "
                        "is imported (default: one per mesh if 2+ CPUs are usable, Linux; "
                        "0: solve in-process)")


def _add_refinement(p: argparse.ArgumentParser) -> None:
    p.add_argument("--no-zoomout", dest="zoomout", action="store_false",
                   help="keep the heat-kernel map of the refined pipeline instead of refining "
                        "it spectrally (ZoomOut, Melzi et al. 2019; the default chooses among "
                        "hypotheses by it too)")
    p.add_argument("--fine", nargs="?", type=_int_at_least(1), const=FINE_K, default=None,
                   metavar="K",
                   help=f"refine the chosen map further, to K eigenmodes (default K: {FINE_K}): "
                        "finer maps (TOSCA's right maps: mean error -11 %%) for about 1.2 s "
                        "more on 5k-vertex meshes (the extra eigenpairs are solved in the "
                        "background workers; K at most a quarter of the smaller mesh's "
                        "vertices)")
    p.add_argument("--report", metavar="PATH.json", default=None,
                   help="also write a JSON report: files, vertex counts, method, landmarks, "
                        "orientation, quality (0..1), suspect, timings, what loading "
                        "repaired in each file (faces reversed, dropped vertices), the options "
                        "given and where it ran (versions, git commit, BLAS, CPU)")


def _add_largest_component(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--largest-component", action="store_true",
                   help="for a mesh with several connected components (or unreferenced "
                        "vertices), which is refused otherwise: match its largest component. "
                        f"The {what} keeps one line per vertex of the source file, -1 for the "
                        "dropped vertices, and target indices of the target file; --landmark "
                        "takes file indices (refused on a dropped vertex)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``torchheat`` command.

    Returns
    -------
    argparse.ArgumentParser

    Examples
    --------
    >>> build_parser().parse_args(["match", "a.off", "b.off", "-o", "m.txt"]).landmarks
    1
    """
    parser = argparse.ArgumentParser(
        prog=PROG,
        formatter_class=_Formatter,
        description="One-point isometric shape matching with the heat kernel "
                    "(Ovsjanikov et al., SGP 2010).",
        epilog="examples:\n"
               "  torchheat match cat0.off cat1.off -o cat0_cat1.txt --png cat.png\n"
               "  torchheat symmetry cat0.off -o cat0_sym.txt\n"
               "  torchheat check scans/*.obj\n"
               "  torchheat demo --out out\n"
               "  torchheat evaluate configs/tosca5k.yaml --workers 2\n"
               "  torchheat evaluate configs/tosca5k.yaml --dask local:2\n"
               "Run 'torchheat COMMAND --help' for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=f"{PROG} {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    m = sub.add_parser(
        "match", formatter_class=_Formatter,
        help="dense map from a source mesh to a target mesh",
        description="Match SOURCE to TARGET and write the map: one 0-based target vertex "
                    "index per line, one line per source vertex, in source vertex order (-1 "
                    "for vertices dropped by --largest-component).\n\n"
                    f"{FORMATS_HELP}\n\n"
                    "The map's quality (0..1, from its own isometry defect and orientation; "
                    "'suspect' below 0.25) is printed and written by --report.\n\n"
                    "Each mesh needs at least 100 vertices (the descriptors use 100 "
                    "eigenpairs of its Laplacian) and an interior vertex.\n\n"
                    "--landmarks K > 1 selects method 'paper' (the paper's greedy extra "
                    "landmarks) unless --method is given; method 'refine' ignores K.",
        epilog="example:\n"
               "  torchheat match wolf0.off wolf1.off -o wolf.txt --symmetric-out wolf_sym.txt "
               "--png wolf.png\n"
               "  torchheat match a.off b.off -o ab.txt --landmark 120 4711   # known pair\n"
               "  torchheat match scan.obj b.off -o sb.txt --largest-component  # stray pieces",
    )
    m.add_argument("source", metavar="SOURCE", help="source mesh file")
    m.add_argument("target", metavar="TARGET", help="target mesh file")
    m.add_argument("-o", "--output", required=True, metavar="MAP.txt",
                   help="output map file")
    m.add_argument("--symmetric-out", metavar="SYM.txt", default=None,
                   help="also write the intrinsically symmetric alternative map, if found")
    m.add_argument("--rival-out", metavar="RIVAL.txt", default=None,
                   help="also write the best different whole map the choice passed over "
                        "(the map behind the printed margin; look at it when the choice is "
                        "AMBIGUOUS)")
    m.add_argument("--landmark", type=int, nargs="+", metavar=("P", "Q"), default=None,
                   help="fix the source landmark P (0-based), or the pair P -> Q (skips the "
                        "landmark search); default: the strongest feature point")
    m.add_argument("--landmarks", type=int, default=1, metavar="K",
                   help="number of landmark pairs of the paper's greedy pipeline (default: 1)")
    m.add_argument("--method", choices=("refine", "paper"), default=None,
                   help="'refine': one-point map + orientation test + correspondence "
                        "augmentation; 'paper': the paper's pipeline (default: refine, or "
                        "paper when --landmarks > 1)")
    _add_common(m)
    _add_largest_component(m, "map (and --symmetric-out, --rival-out)")
    m.add_argument("--png", metavar="PATH", default=None,
                   help="also write a colour-transfer picture of the map (of the matched "
                        "components with --largest-component); PNG, or PDF / SVG / JPEG by the "
                        "extension")
    _add_refinement(m)
    for flag, dest, text in _CHOICE_SWITCHES:
        m.add_argument(flag, dest=dest, action="store_false", help=text)
    m.add_argument("--verify-stage", dest="verify_stage", action="store_true",
                   help="when the first stage's choice is clear but its map reads an isometry "
                        "defect above 0.2, run the full search as well and keep the map of "
                        "lower defect (TOSCA test pairs: 99.3 -> 99.5 %% under 0.25; held out: "
                        "TOSCA high-res 99.4 -> 99.7 %%, michael pairs 98.2 -> 97.9 %%, two "
                        "half-turns; about 0.35 s more per 5k-vertex pair on average)")
    m.add_argument("--partial", action="store_true",
                   help="SOURCE is a piece of TARGET (a cut or holed scan of it, in the same "
                        "units): one scale for both shapes, landmarks and samples away from "
                        "the cut, rectangular functional maps; every source vertex gets a "
                        "target vertex. TARGET must be the whole shape")
    m.add_argument("--partial-margin", type=float, default=None, metavar="D",
                   help="with --partial: no landmark or sample closer than D * sqrt(area of "
                        "TARGET) to the boundary of SOURCE (default 0.02, "
                        "torchheat.matching.partial.PARTIAL_MARGIN)")
    m.add_argument("--partial-scale", choices=("auto", "piece", "filled", "unit"),
                   default=None,
                   help="with --partial: 'piece' matches SOURCE at TARGET's scale (suits a "
                        "piece cut off), 'filled' closes its holes and matches it as a whole "
                        "shape (suits a scan with holes), 'unit' matches it as a whole at unit "
                        "area with its holes open; 'auto' (default) tries filled, keeps it "
                        "when its match is clear, else also piece and keeps the map that "
                        "agrees best with the landmark-free partial map")
    m.set_defaults(func=_cmd_match)

    s = sub.add_parser(
        "symmetry", formatter_class=_Formatter,
        help="intrinsic (left/right) symmetry self-map of a mesh",
        description="Find the orientation-reversing intrinsic symmetry of MESH and write the "
                    "self-map (same format as 'match').",
        epilog="example:\n  torchheat symmetry cat0.off -o cat0_sym.txt --png cat0_sym.png",
    )
    s.add_argument("mesh", metavar="MESH", help="mesh file")
    s.add_argument("-o", "--output", required=True, metavar="MAP.txt", help="output map file")
    s.add_argument("--landmark", type=int, nargs=1, metavar="P", default=None,
                   help="source landmark (default: the strongest feature point)")
    _add_common(s)
    _add_largest_component(s, "self-map")
    s.add_argument("--png", metavar="PATH", default=None,
                   help="also write a colour-transfer picture of the self-map (PNG, or PDF / "
                        "SVG / JPEG by the extension)")
    _add_refinement(s)
    s.set_defaults(func=_cmd_symmetry)

    c = sub.add_parser(
        "check", formatter_class=_Formatter,
        help="what loading mesh files finds: matchable or why not, topology, repairs",
        description="Load each MESH as 'match' would and report whether it can be matched "
                    "(else the reason and what to do), its vertices, faces, boundary loops, "
                    "genus, area and diagonal, what loading repaired (faces reversed, the "
                    "surface turned outward, vertices dropped) and its warnings. Exit status "
                    "1 if any file is refused.",
        epilog="examples:\n  torchheat check scans/*.obj\n"
               "  torchheat check scan.ply --largest-component --json",
    )
    c.add_argument("meshes", nargs="+", metavar="MESH", help="mesh files")
    c.add_argument("--largest-component", action="store_true",
                   help="keep the largest connected component, as match does with this flag")
    c.add_argument("--json", action="store_true", help="print one JSON list instead")
    c.set_defaults(func=_cmd_check)

    d = sub.add_parser(
        "demo", formatter_class=_Formatter,
        help="match two bundled ogre blend shapes and report the accuracy",
        description="Match the bundled ogre blend shapes bs_rest.obj -> bs_smile.obj (19985 "
                    "vertices, identity ground truth), write DIR/ogre_map.txt and a colour "
                    "transfer DIR/ogre_map.png, and print the fraction of vertices mapped "
                    "exactly and within 1 % of the bounding-box diagonal (Euclidean).",
        epilog="examples:\n  torchheat demo --out out\n  torchheat demo --partial --out out",
    )
    d.add_argument("--out", default="out", metavar="DIR",
                   help="output directory, created if needed (default: out)")
    d.add_argument("--method", choices=("refine", "paper"), default="refine",
                   help="matching method (see 'torchheat match --help'); default: refine")
    d.add_argument("--partial", action="store_true",
                   help="instead: cut the front two thirds of the bundled cow spot.obj at run "
                        "time and match the piece into the whole cow, rotated and renumbered "
                        "(match --partial); writes DIR/spot_partial_map.txt and "
                        "DIR/spot_partial_map.png")
    _add_common(d)
    d.set_defaults(func=_cmd_demo)

    sub.add_parser(
        "evaluate", formatter_class=_Formatter, add_help=False,
        help="batch evaluation from a config file (torchheat.batch)",
        description="Run a batch evaluation described by CONFIG; all arguments are passed to "
                    "torchheat.batch (see 'torchheat evaluate --help').",
        epilog="examples:\n  torchheat evaluate configs/tosca5k.yaml --workers 2\n"
               "  torchheat evaluate configs/tosca5k.yaml --dask local:2\n"
               "  torchheat evaluate configs/tosca5k.yaml --dask tcp://scheduler:8786",
    )
    sub.add_parser(
        "preprocess", formatter_class=_Formatter, add_help=False,
        help="fill the per-shape disk cache of a config's dataset or a folder of meshes",
        description="Compute every shape's eigenpairs into the disk cache, one task per shape "
                    "(locally or on Dask); all arguments are passed to torchheat.batch (see "
                    "'torchheat preprocess --help').",
        epilog="example:\n  torchheat preprocess configs/tosca5k.yaml --cache /shared/cache "
               "--dask local:2",
    )
    return parser


def _own(category: type[Warning]) -> bool:
    """Whether a warning category is torchheat's own (e.g. MeshWarning), not a library's."""
    return category.__module__.split(".")[0] == "torchheat"


class _WarningPrinter:
    """``warnings.showwarning`` of one command: one line ``torchheat: warning: ...`` per
    distinct text (a batch loads one target file for each of its pairs); with ``own_only``,
    torchheat's warnings only.

    Library warnings (numpy, scipy, torch: ``FutureWarning`` about dtypes, torch's sparse
    "beta" notice, ...) say nothing a command-line user can act on. The eigensolve workers
    are forked inside :func:`main`, so they inherit the printer (and what it has shown).
    """

    def __init__(self, own_only: bool) -> None:
        self.own_only = own_only
        self.shown: set[str] = set()

    def __call__(self, message, category, filename, lineno, file=None, line=None) -> None:
        if self.own_only and not _own(category):
            return
        text = _one_line(str(message))
        if text in self.shown:
            return
        self.shown.add(text)
        print(f"{PROG}: warning: {text}", file=sys.stderr if file is None else file)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``torchheat`` command.

    Parameters
    ----------
    argv : sequence of str, optional
        Arguments without the program name (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        Exit status: 0 success, 1 bad input (one-line message on stderr), 2 usage error.

    Examples
    --------
    >>> main(["match", "missing.off", "b.off", "-o", "map.txt"])  # doctest: +SKIP
    torchheat: error: missing.off: no such file; check the path ...
    1
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    with warnings.catch_warnings():
        try:
            if argv and argv[0] in _BATCH:  # torchheat.batch words its own warnings
                warnings.showwarning = _WarningPrinter(own_only=False)
                return _cmd_batch(argv[0], argv[1:])
            warnings.showwarning = _WarningPrinter(own_only=True)
            args = build_parser().parse_args(argv)
            return int(args.func(args))
        except CLIError as exc:
            msg = str(exc)
        except (ValueError, IndexError) as exc:  # MeshError is a ValueError
            msg = str(exc)
        except OSError as exc:
            msg = _os_error_message(exc)
        except KeyboardInterrupt:
            print(f"{PROG}: interrupted", file=sys.stderr)
            return 130
        except Exception as exc:  # a bug of ours: one line, the traceback on request
            if os.environ.get("TORCHHEAT_DEBUG"):
                raise
            print(f"{PROG}: internal error: {type(exc).__name__}: {_one_line(str(exc))} "
                  "(a bug: please report it with the command; TORCHHEAT_DEBUG=1 shows the "
                  "traceback)", file=sys.stderr)
            return 3
    print(f"{PROG}: error: {_one_line(msg)}", file=sys.stderr)
    return 1


_FAST_EXIT = ("match", "symmetry", "demo")
_BATCH = ("evaluate", "preprocess")


def run() -> None:
    """Console-script entry point: :func:`main`, then exit.

    After ``match``, ``symmetry`` and ``demo`` (whose outputs are complete and renamed into
    place by then) the process leaves with ``os._exit`` once stdout and stderr are flushed:
    the interpreter's normal teardown of torch's modules costs about 0.3 s and does nothing
    for these commands. Other commands exit normally.
    """
    argv = sys.argv[1:]
    rc = main(argv)
    if argv and argv[0] in _FAST_EXIT:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(OSError):  # e.g. a closed pipe (torchheat ... | head)
                stream.flush()
        os._exit(rc)
    sys.exit(rc)


if __name__ == "__main__":  # pragma: no cover
    run()
