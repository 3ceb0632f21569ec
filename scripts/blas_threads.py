#!/usr/bin/env python
"""Matches with numpy's BLAS on one thread (the default inside ``match``) or left alone.

    python scripts/blas_threads.py [--repeats 2]

Four TOSCA 5k pairs (one per class of cat, michael, david, horse), each prepared afresh (so
the target's self-symmetry is computed every time, as on the command line), matched with one
and with two torch threads; "left alone" replaces ``heat.blas_threads`` inside the pipeline by
a no-op, so numpy's OpenBLAS keeps its default threads (one per core). Prints the summed match
time per setting and whether the maps are identical.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torchheat  # noqa: E402
import torchheat.matching.pipeline as pipeline  # noqa: E402
from torchheat.datasets import data_root  # noqa: E402

PAIRS = [("cat0", "cat1"), ("michael4", "michael5"), ("david0", "david1"), ("horse0", "horse5")]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--repeats", type=int, default=2)
    args = p.parse_args(argv)
    from threadpoolctl import threadpool_info

    d = data_root() / "tosca_remeshed_5k" / "vtx_5k"
    meshes = {n: torchheat.load_mesh(d / f"{n}.off") for pair in PAIRS for n in pair}
    blas = [(i["filepath"].rsplit("/", 1)[-1], i["num_threads"]) for i in threadpool_info()
            if i["user_api"] == "blas"]
    print(f"BLAS libraries (threads by default): {blas}")
    limit = pipeline.blas_threads
    maps: dict = {}
    for rep in range(args.repeats):
        for nt in (1, 2):
            for mode in ("one BLAS thread (default)", "BLAS left alone"):
                pipeline.blas_threads = limit if mode.startswith("one") else (
                    lambda n: contextlib.nullcontext())
                total, got = 0.0, []
                for s, t in PAIRS:
                    ps, pt = torchheat.prepare(meshes[s]), torchheat.prepare(meshes[t])
                    t0 = time.perf_counter()
                    corr = torchheat.match(ps, pt, num_threads=nt)
                    got.append(corr.map.numpy())
                    total += time.perf_counter() - t0
                maps.setdefault(nt, []).append(got)
                print(f"run {rep + 1}, {nt} torch thread{'s' if nt > 1 else ''}, {mode}: "
                      f"{total:.2f} s for {len(PAIRS)} matches", flush=True)
    pipeline.blas_threads = limit
    same = all(np.array_equal(a, b) for runs in maps.values() for got in runs
               for a, b in zip(runs[0], got, strict=True))
    print(f"maps identical across settings: {same}")


if __name__ == "__main__":
    main()
