#!/usr/bin/env python
"""Out-of-sample partial check on TOSCA 5k classes absent from the SHREC'16 training set
(victoria, wolf; any class works): a piece of pose A matched into pose B with
``match(..., partial=True)``, errors against TOSCA's ground truth.

Pieces (the largest connected piece of what is kept):

* ``fixed`` (the default): per pair, twelve holes punched (the two-rings of farthest-point
  vertices) and everything below the 60 % height quantile (the eleventh session's pieces).
* ``--random N``: N cut and N holed pieces per class, drawn from its test pairs in turn, as
  SHREC'16 makes them: cuts by one or two random planes (14-88 % of the area kept), holes by
  4-9 Euclidean balls of radius 3-9 % of the diagonal around random vertices (at least 14 % of
  the area kept). Seeded by ``--seed`` and the class: a run with the same N is repeatable.

Errors: geodesic on B / sqrt(area of B) (the Princeton protocol SHREC'16 uses), direct and
against TOSCA's symmetric ground truth (flip-aware: the better of the two for the whole map), on
``--points`` random piece vertices with ground truth (default 500, seeded; 0: all of them: one
geodesic solve per distinct true image, seconds per piece).
Each piece is one JSON line of OUT (pair, kind, area share, vertices, share under 0.25 and 0.05,
mean, flip-aware share, quality, suspect, way kept, seconds); a piece already in OUT is not
run again (resume), and a summary per class and kind is printed at the end.

Usage::

    python scripts/partial_unseen.py OUT.jsonl victoria0-victoria1,wolf0-wolf1   # fixed pieces
    python scripts/partial_unseen.py OUT.jsonl victoria,wolf --random 10         # random pieces
    python scripts/partial_unseen.py OUT.jsonl wolf --random 10 --match refine_samples=49
"""

from __future__ import annotations

import argparse
import json
import time
import warnings
import zlib
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import yaml

import torchheat
from torchheat import Mesh
from torchheat.datasets import tosca_remeshed_5k
from torchheat.descriptors import farthest_point_sampling
from torchheat.evaluate import GeodesicSolver, geodesic_errors
from torchheat.matching.pipeline import check_options


def kring(F: np.ndarray, seeds: list[int], k: int) -> np.ndarray:
    """The vertices within ``k`` edges of ``seeds``."""
    s = set(seeds)
    for _ in range(k):
        s |= set(np.unique(F[np.isin(F, list(s)).any(axis=1)]).tolist())
    return np.array(sorted(s))


def fixed_pieces(V: np.ndarray, F: np.ndarray) -> dict[str, np.ndarray]:
    """Faces kept by the holed and the cut piece of a mesh."""
    ring = kring(F, farthest_point_sampling(V, 12).numpy().tolist(), 2)
    c = np.quantile(V[:, 1], 0.6)
    return {"holes": ~np.isin(F, ring).any(axis=1), "cut": (V[F, 1] <= c).all(axis=1)}


def random_cut(V: np.ndarray, F: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Faces on the kept side of one or two random planes (14-88 % of the vertices kept)."""
    planes = int(rng.integers(1, 3))
    share = rng.uniform(0.14, 0.88)
    keep = np.ones(len(F), bool)
    for _ in range(planes):
        n = rng.normal(size=3)
        s = V @ (n / np.linalg.norm(n))
        keep &= (s >= np.quantile(s, 1 - share ** (1 / planes)))[F].all(axis=1)
    return keep


def random_holes(V: np.ndarray, F: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Faces outside 4-9 Euclidean balls (radius 3-9 % of the diagonal) at random vertices."""
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    inside = np.zeros(len(V), bool)
    for c in rng.choice(len(V), int(rng.integers(4, 10)), replace=False):
        inside |= np.linalg.norm(V - V[c], axis=1) < rng.uniform(0.03, 0.09) * diag
    return ~inside[F].any(axis=1)


def _piece(V: np.ndarray, F: np.ndarray, keep: np.ndarray, name: str) -> Mesh:
    return Mesh(V, F[keep], name=name, largest_component=True)


def _jobs(pc, spec: list[str], n_random: int, seed: int):
    """``(piece name, pair, kind, piece mesh)`` of every piece to run."""
    if not n_random:
        for name in spec:
            if name not in pc.names:
                raise SystemExit(f"{name!r} is no TOSCA 5k test pair (e.g. victoria0-victoria1); "
                                 "a class name needs --random N")
            pr = pc[pc.names.index(name)]
            V, F = pr.source.mesh.numpy()
            for kind, keep in fixed_pieces(V, F).items():
                yield f"{name}:{kind}", pr, kind, _piece(V, F, keep, f"{name}:{kind}")
        return
    for cls in spec:
        pairs = [i for i in range(len(pc)) if pc[i].cls == cls]
        if not pairs:
            raise SystemExit(f"no test pairs of class {cls!r}")
        rng = np.random.default_rng([seed, zlib.crc32(cls.encode())])
        for kind, make in (("cut", random_cut), ("holes", random_holes)):
            for i in range(n_random):
                pr = pc[pairs[i % len(pairs)]]
                V, F = pr.source.mesh.numpy()
                name = f"{pr.name}:{kind}{i}"
                for _ in range(50):  # a draw keeping too little (or too much) is drawn again
                    piece = _piece(V, F, make(V, F, rng), name)
                    r = piece.area() / pr.source.mesh.area()
                    if 0.14 <= r <= (0.88 if kind == "cut" else 0.94) and piece.n_vertices >= 300:
                        break
                yield name, pr, kind, piece


def match_options(items: list[str]) -> dict:
    """``--match KEY=VALUE`` items as keyword options of :func:`torchheat.match` (each VALUE
    read as YAML: ``refine_samples=49`` gives the int 49, ``zoomout=false`` False), checked
    as a batch config's are (:func:`torchheat.matching.pipeline.check_options`: unknown names,
    numbers below their least value). ``partial`` is refused: it is always True here. Raises
    ``ValueError`` (or the check's ``TypeError``)."""
    options = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise ValueError(f"--match {item!r}: expected KEY=VALUE")
        if key == "partial":
            raise ValueError(f"--match {item!r}: the pieces are always matched with partial=True")
        options[key] = yaml.safe_load(value)
    check_options(options)
    return options


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("spec", help="comma-separated pairs (fixed pieces) or classes (--random)")
    ap.add_argument("--random", type=int, default=0, metavar="N",
                    help="N random cut and N random holed pieces per class")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--points", type=int, default=500,
                    help="piece vertices the errors are read on (0: all)")
    ap.add_argument("--match", action="append", default=[], metavar="KEY=VALUE",
                    help="an option of torchheat.match for every piece (repeatable; VALUE is "
                         "read as YAML, e.g. --match refine_samples=49); write to a new OUT")
    args = ap.parse_args(argv)
    try:
        options = match_options(args.match)
    except (TypeError, ValueError) as exc:
        ap.error(str(exc))
    warnings.filterwarnings("ignore")
    torch.set_num_threads(1)
    pc = tosca_remeshed_5k(pairs="test")
    done = {}
    if args.out.exists():
        for line in args.out.read_text().splitlines():
            if line.strip():
                rec = json.loads(line)
                if rec.get("options", {}) != options:  # resume only the same run
                    raise SystemExit(f"{args.out}: its piece {rec['piece']} was matched with "
                                     f"options {rec.get('options', {})}, not {options}: write "
                                     "to a new file")
                done[rec["piece"]] = rec
    solvers: dict[str, GeodesicSolver] = {}
    with open(args.out, "a") as out:
        for piece_name, pr, kind, P in _jobs(pc, args.spec.split(","), args.random,
                                             args.seed):
            if piece_name in done:
                continue
            n = pr.source.mesh.n_vertices
            W, G = pr.target.mesh.numpy()
            gt = np.full(n, -1)
            gt[pr.gt_src.numpy()] = pr.gt_tgt.numpy()
            gsym = np.full(n, -1)
            gsym[pr.gt_src.numpy()] = pr.gt_sym_tgt.numpy()
            t0 = time.perf_counter()
            corr = torchheat.match(P, Mesh(W, G, name=pr.target.name), partial=True, **options)
            seconds = time.perf_counter() - t0
            rows = P.vertex_map.numpy()
            ok = np.flatnonzero(gt[rows] >= 0)
            if 0 < args.points < ok.size:
                ok = np.sort(np.random.default_rng([args.seed, zlib.crc32(piece_name.encode())])
                             .choice(ok, args.points, replace=False))
            if pr.target.name not in solvers:  # one per target (setdefault built it each time)
                solvers[pr.target.name] = GeodesicSolver((W, G))
            solver = solvers[pr.target.name]
            m = corr.map.numpy()[ok]
            e = geodesic_errors((W, G), m, gt[rows][ok], solver=solver)
            es = geodesic_errors((W, G), m, gsym[rows][ok], solver=solver)
            flip = es if es.mean() < e.mean() else e
            rec = {"piece": piece_name, "pair": pr.name, "cls": pr.cls, "kind": kind,
                   "r": P.area() / pr.source.mesh.area(), "n": P.n_vertices,
                   "acc": float((e < 0.25).mean()), "acc05": float((e < 0.05).mean()),
                   "mean": float(e.mean()), "flip_acc": float((flip < 0.25).mean()),
                   "quality": float(corr.quality.quality), "suspect": bool(corr.suspect),
                   "scale": corr.info["partial"]["scale"], "seconds": seconds}
            if options:
                rec["options"] = options
            print(json.dumps(rec), flush=True)
            out.write(json.dumps(rec) + "\n")
            out.flush()
            done[piece_name] = rec
    by = defaultdict(list)
    for rec in done.values():
        by[(rec.get("cls", rec.get("pair", "?")), rec["kind"])].append(rec)
    print(f"{'class':10s} {'kind':6s} {'n':>3s} {'% < 0.25':>9s} {'flip-aware':>10s} "
          f"{'mean':>6s} {'suspect':>7s} {'s/piece':>7s}")
    for (cls, kind), rs in sorted(by.items()):
        def avg(key: str, rs: list = rs) -> float:
            return sum(float(r.get(key, float("nan"))) for r in rs) / len(rs)
        print(f"{cls:10s} {kind:6s} {len(rs):3d} {100 * avg('acc'):9.1f} "
              f"{100 * avg('flip_acc'):10.1f} {avg('mean'):6.3f} "
              f"{sum(bool(r.get('suspect')) for r in rs):7d} {avg('seconds'):7.2f}")


if __name__ == "__main__":
    main()
