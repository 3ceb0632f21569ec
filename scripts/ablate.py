#!/usr/bin/env python
"""Quick ablation of matching options on a subset of pairs (Euclidean proxy, no geodesics).

    python scripts/ablate.py tosca 9 '{"mirror_hypothesis": false}' ['{"k": 80}']
    python scripts/ablate.py scape 4

Every ``STRIDE``-th pair of TOSCA 5k's test pairs (or SCAPE's 40) is prepared afresh
(``torchheat.prepare``, so a target's self-symmetry is computed for every pair) and matched
with the given ``torchheat.match`` options, two processes of one thread each. Prints the mean
match and prepare time per pair and the fraction of ground-truth points whose image lies
within 0.25 / 0.08 sqrt(area) (Euclidean) of the true one, direct (d25, d08) and flip-aware
(f25, f08, TOSCA only). Euclidean distance never exceeds the geodesic one, so d25 is an upper
bound of the Princeton figure; d08 is the stricter proxy used to compare options. Per-pair
records go to out/ablate_<dataset>.json. For the field's protocol use scripts/evaluate.py.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy: one BLAS thread per worker
os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import torchheat  # noqa: E402
from torchheat import datasets  # noqa: E402


def _pairs(ds: str):
    if ds == "tosca":
        return datasets.tosca_remeshed_5k()
    if ds == "scape":
        return datasets.scape()
    raise SystemExit(f"unknown dataset {ds!r}; use 'tosca' or 'scape'")


def run_one(args: tuple) -> dict:
    ds, i, opts, prep = args
    torch.set_num_threads(1)
    pr = _pairs(ds)[i]
    S, T = pr.source.mesh, pr.target.mesh
    t0 = time.perf_counter()
    ps, pt = torchheat.prepare(S, **prep), torchheat.prepare(T, **prep)
    t1 = time.perf_counter()
    corr = torchheat.match(ps, pt, **opts)
    f = corr.map.numpy()
    t2 = time.perf_counter()
    V, _ = T.numpy()
    area = T.area()
    gs, gt = pr.gt_src.numpy(), pr.gt_tgt.numpy()
    e = np.linalg.norm(V[f[gs]] - V[gt], axis=1) / math.sqrt(area)
    out = {"name": pr.name, "prep": t1 - t0, "match": t2 - t1,
           "d25": float((e < 0.25).mean()), "d08": float((e < 0.08).mean())}
    if pr.gt_sym_tgt is not None:
        es = np.linalg.norm(V[f[gs]] - V[pr.gt_sym_tgt.numpy()], axis=1) / math.sqrt(area)
        ee = e if e.mean() <= es.mean() else es  # the whole map against one ground truth
        out["f25"], out["f08"] = float((ee < 0.25).mean()), float((ee < 0.08).mean())
    return out


def main(argv: list[str]) -> None:
    if len(argv) < 2:
        raise SystemExit(__doc__)
    ds, stride = argv[0], int(argv[1])
    opts = json.loads(argv[2]) if len(argv) > 2 else {}
    prep = json.loads(argv[3]) if len(argv) > 3 else {}
    idx = list(range(0, len(_pairs(ds)), stride))
    t0 = time.perf_counter()
    with ProcessPoolExecutor(2) as ex:
        res = list(ex.map(run_one, [(ds, i, opts, prep) for i in idx]))
    keys = [k for k in ("d25", "d08", "f25", "f08", "match", "prep") if k in res[0]]
    agg = " ".join(f"{k}={np.mean([r[k] for r in res]):.4f}" for k in keys)
    print(f"{ds} {len(res)} pairs {json.dumps(opts)} {json.dumps(prep)} {agg} "
          f"wall={time.perf_counter() - t0:.1f}s")
    Path("out").mkdir(exist_ok=True)
    Path(f"out/ablate_{ds}.json").write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main(sys.argv[1:])
