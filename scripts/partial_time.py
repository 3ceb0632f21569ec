#!/usr/bin/env python
"""Per-pair time of partial matches on SHREC'16 pieces, warm, in one process.

    python scripts/partial_time.py [KIND] [N]

KIND: ``holes`` (default) or ``cuts``; the first N // 6 pieces of each class (default N = 12)
are matched into their whole with ``partial=True`` (prepare + match, as the batch evaluation
times them; one torch thread, one BLAS thread), after one warm-up piece per class that
prepares each whole and computes its self-symmetry, as a batch worker keeps them. Prints
each piece's stage timings and the mean per pair. Alternate two code versions run by run
(this host's speed drifts by 10-20 % over minutes). Needs ../shared/data.
"""

from __future__ import annotations

import os
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")


def main(argv: list[str]) -> int:
    import torch

    from torchheat.batch import evaluate_pair
    from torchheat.datasets import shrec16_partial

    kind = argv[0] if argv else "holes"
    n = int(argv[1]) if len(argv) > 1 else 12
    torch.set_num_threads(1)
    pieces = shrec16_partial(kind=kind)
    items = [pieces[i] for i in range(len(pieces))]
    by_class: dict[str, list[int]] = {}
    for i, it in enumerate(items):
        by_class.setdefault(it.cls, []).append(i)
    per = max(1, n // len(by_class))
    warm = [v[-1] for v in by_class.values()]
    test = [i for v in by_class.values() for i in v[:per]]
    for i in warm:
        evaluate_pair(items[i], {"partial": True}, eval_points=10)
    t0 = time.perf_counter()
    total = 0.0
    for i in test:
        r = evaluate_pair(items[i], {"partial": True}, eval_points=10)
        total += r["time_prepare"] + r["time_match"]
        stages = ", ".join(f"{k} {v:.2f}" for k, v in r["timings"].items())
        print(f"{r['name']}: prepare {r['time_prepare']:.2f} s, match {r['time_match']:.2f} s"
              f" ({stages})")
    print(f"{len(test)} {kind} pieces: prepare + match {total / len(test):.2f} s per pair "
          f"(wall {time.perf_counter() - t0:.1f} s with a 10-point evaluation)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
