#!/usr/bin/env python
"""Per-pair match time of the staged search against the full one (warm, one process).

    python scripts/staged_time.py [TARGETS] [N]

TARGETS: comma-separated TOSCA 5k target shapes (default michael7,cat9,horse6,dog2); the
first N (default 16) test pairs into them are matched, after one warm-up pass that computes
each target's self-symmetry, with ``staged=False`` (the full search of 8 source features)
and with the staged search whose first stage has 1, 2 and 3 seeding features (the default:
3, ``pipeline._FIRST_STAGE_SEEDS``). One torch thread. Prints the mean time per pair
(``match`` + the dense map) and how many maps the first stage gave. Needs ../shared/data.
"""

from __future__ import annotations

import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")


def main(argv: list[str]) -> int:
    import numpy as np
    import torch

    import torchheat
    from torchheat import datasets
    from torchheat.matching import pipeline

    torch.set_num_threads(1)
    names = (argv[0] if argv else "michael7,cat9,horse6,dog2").split(",")
    n = int(argv[1]) if len(argv) > 1 else 16
    pc = datasets.tosca_remeshed_5k(pairs="test")
    idx = [i for i in range(len(pc)) if pc[i].target.name in names][:n]
    prepared: dict = {}

    def prep(shape):
        if shape.name not in prepared:
            prepared[shape.name] = torchheat.prepare(shape)
        return prepared[shape.name]

    for i in idx:  # warm-up: preparation and every target's self-symmetry
        torchheat.match(prep(pc[i].source), prep(pc[i].target), staged=False).map  # noqa: B018
    default = pipeline._FIRST_STAGE_SEEDS
    try:
        for name, seeds, kw in [("full search", default, {"staged": False}),
                                *[(f"staged, {k} seeds", k, {}) for k in (1, 2, 3)]]:
            pipeline._FIRST_STAGE_SEEDS = seeds
            times, kept = [], 0
            for i in idx:
                t0 = time.perf_counter()
                corr = torchheat.match(prep(pc[i].source), prep(pc[i].target), **kw)
                corr.map  # noqa: B018 - the dense map is computed on first access
                times.append(time.perf_counter() - t0)
                kept += corr.info["search"] == "first stage"
            print(f"{name:18s} {np.mean(times):.3f} s per pair, first stage kept on "
                  f"{kept}/{len(idx)}", flush=True)
    finally:
        pipeline._FIRST_STAGE_SEEDS = default
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
