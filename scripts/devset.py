#!/usr/bin/env python
"""Development subset: match a fixed list of pairs and report errors and the best hypothesis.

    python scripts/devset.py [OPTIONS_JSON] [--set scape|tosca|all] [--geo N] [--out FILE]

Pairs (fixed, chosen from the 2026-12-01 runs): SCAPE's 13 failing/weak pairs of
``configs/scape.yaml``, 4 pairs of far-apart poses and 2 good ones; TOSCA 5k: 10 failing
michael pairs, the 2 failing cats, victoria0-victoria21 and 9 pairs of other classes. One
process, one thread; prepared shapes are reused between pairs (as in the batch runs).

Per pair: the fraction of ground-truth points whose image lies within 0.25 / 0.05 sqrt(area)
of the true one, Euclidean (``e25``, ``e05``; an upper bound of the Princeton figure) and,
with ``--geo N``, the Princeton geodesic error on N evenly spaced ground-truth points
(``g25``, ``gmean``); ``orc`` is the best hypothesis' fraction of refinement samples within
0.25 sqrt(area) (Euclidean) of their true images, and ``zorc`` the same for the ZoomOut
candidates (the seeding's ceiling).
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import torchheat  # noqa: E402
from torchheat import datasets  # noqa: E402

SCAPE = [(8, 9), (7, 9), (19, 1), (5, 7), (8, 10), (7, 8), (5, 6), (3, 4), (2, 3), (13, 14),
         (11, 13), (12, 14), (14, 16), (0, 10), (3, 13), (6, 16), (2, 17), (0, 1), (9, 11)]
TOSCA = [("michael10", "michael19"), ("michael19", "michael8"), ("michael13", "michael19"),
         ("michael13", "michael3"), ("michael4", "michael8"), ("michael19", "michael5"),
         ("michael4", "michael5"), ("michael1", "michael11"), ("michael0", "michael11"),
         ("michael16", "michael8"), ("cat5", "cat9"), ("cat7", "cat9"),
         ("victoria0", "victoria21"), ("david0", "david11"), ("centaur1", "centaur4"),
         ("dog2", "dog8"), ("horse14", "horse7"), ("cat0", "cat2"), ("victoria1", "victoria2"),
         ("michael0", "michael1"), ("david1", "david6"), ("wolf0", "wolf1")]

_PREP: dict = {}


def _prepared(shape):
    key = id(shape)
    if key not in _PREP:
        _PREP[key] = (shape, torchheat.prepare(shape.mesh))
    return _PREP[key][1]


def _frac(V, a, b, area, tol):
    return float((np.linalg.norm(V[a] - V[b], axis=1) / math.sqrt(area) < tol).mean())


def run_pair(pr, opts, geo):
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    ps, pt = _prepared(pr.source), _prepared(pr.target)
    t1 = time.perf_counter()
    corr = torchheat.match(ps, pt, **opts)
    f = corr.map.numpy()
    t2 = time.perf_counter()
    S, T = pr.source.mesh, pr.target.mesh
    Vs, _ = S.numpy()
    V, F = T.numpy()
    area = T.area()
    gs, gt = pr.gt_src.numpy(), pr.gt_tgt.numpy()
    out = {"name": pr.name, "prep": t1 - t0, "match": t2 - t1,
           "e25": _frac(V, f[gs], gt, area, 0.25), "e05": _frac(V, f[gs], gt, area, 0.05),
           "orient": corr.orientation}
    if pr.gt_sym_tgt is not None:
        out["s25"] = _frac(V, f[gs], pr.gt_sym_tgt.numpy(), area, 0.25)
    # true image of any source vertex: that of the nearest ground-truth source vertex
    nn = cKDTree(Vs[gs]).query(Vs)[1]
    true = gt[nn]
    samp = corr.info["refine_samples"].numpy()
    hyps = [_frac(V, g.numpy(), true[samp], area, 0.08) for g in corr.info["hypothesis_images"]]
    out["orc"] = max(hyps) if hyps else float("nan")
    zc = corr.info.get("zoomout_candidates") or []
    out["zc"] = [(round(_frac(V, im.numpy(), true[rows.numpy()], area, 0.08), 3),
                  round(res, 4), round(o, 2), ch) for rows, im, res, o, ch, *_ in zc]
    out["zorc"] = max((z[0] for z in out["zc"]), default=float("nan"))
    if geo:
        from torchheat.evaluate import GeodesicSolver, geodesic_errors
        sel = np.linspace(0, len(gs) - 1, min(geo, len(gs))).astype(int)
        err = geodesic_errors(T, f[gs[sel]], gt[sel], solver=GeodesicSolver(T))
        out["g25"] = float((err < 0.25).mean())
        out["gmean"] = float(err.mean())
    return out


def main(argv):
    opts, which, geo, outf = {}, "all", 0, None
    it = iter(argv)
    for a in it:
        if a == "--set":
            which = next(it)
        elif a == "--geo":
            geo = int(next(it))
        elif a == "--out":
            outf = next(it)
        else:
            opts = json.loads(a)
    pairs = []
    if which in ("all", "scape"):
        pairs.append(datasets.scape(pairs=SCAPE))
    if which in ("all", "tosca"):
        pairs.append(datasets.tosca_remeshed_5k(pairs=TOSCA))
    if which.startswith("scape:") or which.startswith("tosca:"):
        ds, idx = which.split(":")
        pc = datasets.scape(pairs=SCAPE) if ds == "scape" else datasets.tosca_remeshed_5k(
            pairs=TOSCA)
        pairs.append([pc[int(i)] for i in idx.split(",")])
    res = []
    for pc in pairs:
        for i in range(len(pc)):
            r = run_pair(pc[i], opts, geo)
            res.append(r)
            zc = " ".join(f"{a:.2f}/{b:.3g}/{c:+.2f}{'*' if d else ''}" for a, b, c, d in r["zc"])
            print(f"{r['name']:22s} e25 {r['e25']:.3f} e05 {r['e05']:.3f} "
                  f"s25 {r.get('s25', float('nan')):.3f} orc {r['orc']:.2f} zorc {r['zorc']:.2f} "
                  f"o {r['orient']:+.2f} t {r['match']:.2f}+{r['prep']:.2f} "
                  + (f"g25 {r['g25']:.3f} gm {r['gmean']:.3f} " if geo else "") + zc,
                  flush=True)
    for grp in ("mesh", "michael", ""):
        sub = [r for r in res if r["name"].startswith(grp)] if grp else res
        if not sub:
            continue
        print(f"[{grp or 'all'}] n={len(sub)} e25 {np.mean([r['e25'] for r in sub]):.4f} "
              f"e05 {np.mean([r['e05'] for r in sub]):.4f} "
              f"min {min(r['e25'] for r in sub):.3f} "
              f"match {np.mean([r['match'] for r in sub]):.2f}s"
              + (f" g25 {np.mean([r['g25'] for r in sub]):.4f}"
                 f" gmean {np.mean([r['gmean'] for r in sub]):.4f}" if geo else ""))
    if outf:
        Path(outf).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
