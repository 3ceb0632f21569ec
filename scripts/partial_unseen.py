#!/usr/bin/env python
"""Out-of-sample partial check on TOSCA 5k classes absent from the SHREC'16 training set
(victoria, wolf): a piece of pose A — twelve holes punched (the two-rings of farthest-point
vertices), or everything below the 60 % height quantile — matched into pose B with
``match(..., partial=True)``; errors against TOSCA's ground truth, Euclidean / sqrt(area of B).

Usage: ``python scripts/partial_unseen.py OUT.jsonl victoria0-victoria1,wolf0-wolf1,...``
(one JSON line per piece: pair, kind, area share, share under 0.25 and 0.05, mean, way kept).
"""

from __future__ import annotations

import json
import math
import sys
import warnings

import numpy as np
import torch

import torchheat
from torchheat import Mesh
from torchheat.datasets import tosca_remeshed_5k
from torchheat.descriptors import farthest_point_sampling


def kring(F: np.ndarray, seeds: list[int], k: int) -> np.ndarray:
    """The vertices within ``k`` edges of ``seeds``."""
    s = set(seeds)
    for _ in range(k):
        s |= set(np.unique(F[np.isin(F, list(s)).any(axis=1)]).tolist())
    return np.array(sorted(s))


def pieces(V: np.ndarray, F: np.ndarray) -> dict[str, Mesh]:
    """The holed and the cut piece of a mesh (largest components; ``vertex_map`` into it)."""
    ring = kring(F, farthest_point_sampling(V, 12).numpy().tolist(), 2)
    c = np.quantile(V[:, 1], 0.6)
    return {"holes": Mesh(V, F[~np.isin(F, ring).any(axis=1)], name="holed",
                          largest_component=True),
            "cut": Mesh(V, F[(V[F, 1] <= c).all(axis=1)], name="cut", largest_component=True)}


def main(out_path: str, names: list[str]) -> None:
    warnings.filterwarnings("ignore")
    torch.set_num_threads(1)
    pc = tosca_remeshed_5k(pairs="test")
    with open(out_path, "a") as out:
        for name in names:
            pr = pc[pc.names.index(name)]
            V, F = pr.source.mesh.numpy()
            W, G = pr.target.mesh.numpy()
            gt = np.full(len(V), -1)
            gt[pr.gt_src.numpy()] = pr.gt_tgt.numpy()
            whole = Mesh(W, G, name="B")
            sc = math.sqrt(whole.area())
            for kind, P in pieces(V, F).items():
                corr = torchheat.match(P, whole, partial=True)
                g = gt[P.vertex_map.numpy()]
                ok = g >= 0
                e = np.linalg.norm(W[corr.map.numpy()[ok]] - W[g[ok]], axis=1) / sc
                rec = {"name": name, "kind": kind, "r": P.area() / pr.source.mesh.area(),
                       "acc": float((e < 0.25).mean()), "mean": float(e.mean()),
                       "acc05": float((e < 0.05).mean()),
                       "scale": corr.info["partial"]["scale"]}
                print(json.dumps(rec), flush=True)
                out.write(json.dumps(rec) + "\n")
                out.flush()


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2].split(","))
