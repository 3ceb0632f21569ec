#!/usr/bin/env python
"""Benchmarks of batch evaluation on Dask distributed (BENCHMARKS.md, "Dask").

    python scripts/bench_dask.py throughput [--config configs/tosca5k_timing.yaml] [--limit 24]
    python scripts/bench_dask.py overhead   [--tasks 2000]
    python scripts/bench_dask.py dataloader [--limit 24]
    python scripts/bench_dask.py report OUTPUT

``throughput``: the same pairs by ``torchheat evaluate`` with ``--workers 2`` (process pool),
``--dask local:2`` (eigenbases moved by Dask) and ``--dask local:2`` with a fresh disk cache
(eigenbases through the cache), each a whole command (interpreter, cluster start, all pairs),
one after the other. ``overhead``: Dask's cost per task (no-op tasks, with and without a
dependency), moving one shape's eigenbasis between workers against reading it from the disk
cache, the client's cost per record (JSON line + fsync) and per record held in memory.
``dataloader``: a ``DataLoader`` loop feeding ``torchheat.match(pair)`` from the cache against
the batch evaluation of the same pairs (in-process, same threads). Output: markdown tables.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

warnings.filterwarnings("ignore", message="Sparse")


def _records(out: Path) -> list[dict]:
    return [json.loads(s) for s in (out / "results.jsonl").read_text().splitlines()]


def _eigensolves(recs: list[dict]) -> int:
    metas = {m["id"]: m for r in recs for m in r.get("shapes", ())}
    return sum(r.get("eigensolves", 0) for r in recs) + sum(m["computed"] for m in metas.values())


def bench_throughput(args: argparse.Namespace) -> None:
    import resource

    import yaml

    tmp = Path(tempfile.mkdtemp(prefix="bench_dask_"))
    base = dict(os.environ, PYTHONPATH=str(ROOT))
    noprof = dict(base, DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED="False")
    runs = {"pool": ("--workers 2 (process pool)", ["--workers", "2"], None, base),
            "dask": ("--dask local:2 (eigenbases moved by Dask)", ["--dask", "local:2"], None,
                     base),
            "cache": ("--dask local:2 (eigenbases through the disk cache)",
                      ["--dask", "local:2"], "cache", base),
            "noprof": ("--dask local:2, Dask's worker profiler off", ["--dask", "local:2"],
                       None, noprof)}
    order = args.runs.split(",")
    rows = []
    for rep in range(args.repeat):
        for which in order[rep % len(order):] + order[:rep % len(order)]:  # rotate the order
            label, flags, cache, env = runs[which]
            out = tmp / f"run{len(rows)}"
            cfg = out.with_suffix(".yaml")
            raw = yaml.safe_load(Path(args.config).read_text())
            raw.update(output=str(out), pictures=0, limit=args.limit)
            if cache:
                raw["cache"] = str(tmp / f"cache{len(rows)}")  # fresh: shapes solved once
            cfg.write_text(yaml.safe_dump(raw))
            ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "torchheat.cli", "evaluate", str(cfg),
                            "--no-progress", *flags], cwd=ROOT, env=env, check=True,
                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            wall = time.perf_counter() - t0
            ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
            recs = _records(out)
            per = np.mean([r["time_prepare"] + r["time_match"] for r in recs])
            ev = np.mean([r["time_eval"] for r in recs])
            rows.append((label, len(recs), f"{wall:.1f}", f"{len(recs) / wall * 60:.1f}",
                         f"{cpu:.0f}", f"{cpu / len(recs):.2f}", f"{cpu / wall:.2f}",
                         f"{per:.2f}", f"{ev:.2f}", _eigensolves(recs)))
            print(rows[-1], flush=True)
    print("\n| run | pairs | wall s | pairs / min | CPU s (all processes) | CPU s / pair | "
          "cores used | prepare+match s / pair | eval s / pair | eigensolves |\n"
          "|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print("| " + " | ".join(str(x) for x in r) + " |")
    shutil.rmtree(tmp, ignore_errors=True)


def _noop(x):
    return x


def _pair_of(*args):
    return 0


def _shape_like(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {"eigenvectors": rng.standard_normal((5000, 100)), "hks": rng.standard_normal(
        (5000, 10)), "mass": rng.random(5000), "eigenvalues": np.sort(rng.random(100))}


def bench_overhead(args: argparse.Namespace) -> None:
    from distributed import get_task_stream, wait

    from torchheat import batch, datasets
    from torchheat.executors import DaskExecutor

    rows = []
    with DaskExecutor("local:2") as ex:
        c = ex.client
        wait(c.map(_noop, range(50), pure=False))  # warm up
        t0 = time.perf_counter()
        wait(c.map(_noop, range(args.tasks), pure=False))
        dt = time.perf_counter() - t0
        rows.append(("no-op tasks, client.map", f"{1e3 * dt / args.tasks:.2f} ms / task",
                     f"{args.tasks / dt:.0f} tasks / s"))
        t0 = time.perf_counter()
        n = 0
        for batch_ in ex.map_shared(_pair_of, list(range(args.tasks)),
                                    lambda i: (i % 20, (i * 7 + 1) % 20), _noop,
                                    {i: i for i in range(20)}):
            n += len(batch_)
        dt = time.perf_counter() - t0
        rows.append(("pair-like tasks with 2 shared inputs, map_shared (window 16)",
                     f"{1e3 * dt / n:.2f} ms / task", f"{n / dt:.0f} tasks / s"))
        # one shape's eigenbasis (5000 x 100 float64 + HKS + mass: 4.5 MB) moved worker to
        # worker, against reading the same arrays from a cache entry
        w = sorted(ex.workers)
        futs = [c.submit(_shape_like, i, workers=[w[0]], pure=False) for i in range(10)]
        wait(futs)
        with get_task_stream(client=c) as ts:
            wait([c.submit(_pair_of, f, f, workers=[w[1]], pure=False) for f in futs])
        moves = [s["stop"] - s["start"] for t in ts.data for s in t["startstops"]
                 if s["action"] == "transfer"]
        if moves:
            rows.append(("one shape's eigenbasis (4.5 MB) moved between workers",
                         f"{1e3 * np.mean(moves):.1f} ms", f"{len(moves)} transfers"))
    pc = datasets.tosca_remeshed_5k(pairs="test", classes=["cat"],
                                    preprocess=datasets.Preprocess(),
                                    cache_dir=tempfile.mkdtemp(prefix="bench_cache_"))
    pc.shapes.fill_cache()
    t0 = time.perf_counter()
    for _ in range(3):
        for i in range(len(pc.shapes)):
            pc.shapes.is_cached(i)
            pc.shapes[i]
    dt = (time.perf_counter() - t0) / (3 * len(pc.shapes))
    rows.append(("one shape from the disk cache (hash, check, mesh + npz read; page cache)",
                 f"{1e3 * dt:.1f} ms", "per shape"))
    t0 = time.perf_counter()
    for _ in range(3):
        for i in range(len(pc.shapes)):
            from torchheat.mesh import load_mesh

            load_mesh(pc.shapes.paths[i])
    dt = (time.perf_counter() - t0) / (3 * len(pc.shapes))
    rows.append(("the mesh alone (what a pair task reads when Dask moves the eigenbasis)",
                 f"{1e3 * dt:.1f} ms", "per shape"))
    # the client: a record to its line in results.jsonl, and held in memory
    rec = batch.load_results(ROOT / "out" / "bench828" / "run" / "results.jsonl")[:1]
    if rec:
        import tracemalloc

        d = tempfile.mkdtemp()
        path = Path(d) / "r.jsonl"
        t0 = time.perf_counter()
        for _ in range(200):
            batch._append_lines(path, rec)
        dt = (time.perf_counter() - t0) / 200
        t0 = time.perf_counter()
        for _ in range(20):
            batch._append_lines(path, rec * 20)
        dt20 = (time.perf_counter() - t0) / 400
        line = len(path.read_bytes().splitlines()[0])
        tracemalloc.start()
        held = [json.loads(json.dumps(rec[0])) for _ in range(1000)]
        size = tracemalloc.get_traced_memory()[0] / len(held)
        tracemalloc.stop()
        rows.append(("client: one record appended (JSON + write + fsync)",
                     f"{1e3 * dt:.2f} ms", f"{1e3 * dt20:.2f} ms in batches of 20"))
        rows.append(("client: one record", f"{line} bytes on disk",
                     f"{size / 1024:.1f} KiB in memory"))
    print("\n| what | cost | note |\n|---|---|---|")
    for r in rows:
        print("| " + " | ".join(r) + " |")


def bench_dataloader(args: argparse.Namespace) -> None:
    import torch
    from torch.utils.data import DataLoader

    import torchheat
    from torchheat import batch
    from torchheat.datasets import Preprocess, collate_list, tosca_remeshed_5k, worker_init

    cache = tempfile.mkdtemp(prefix="bench_cache_")
    pairs = tosca_remeshed_5k(pairs="test", preprocess=Preprocess(), cache_dir=cache)
    subset = torch.utils.data.Subset(pairs, range(args.limit))
    names = {pairs.shapes.names[i] for p in pairs.pairs[:args.limit] for i in p}
    t0 = time.perf_counter()
    for n in names:
        pairs.shapes[n]
    print(f"filled the cache for {len(names)} shapes: {time.perf_counter() - t0:.1f} s")
    # the README loops: match(pair); and with each target prepared once (its self-symmetry,
    # behind the mirror hypothesis, is then computed once per target, as batch does); and the
    # batch evaluation of the same pairs (in-process, evaluation on 50 points). Each variant
    # twice, in rotated order (the machine's load drifts).
    variants = ["match(pair)", "match(prepared source, prepared target)", "batch"]

    def prepared(memo: dict, shape):  # as in the README
        if shape.name not in memo:
            memo[shape.name] = torchheat.prepare(shape)
        return memo[shape.name]

    walls: dict[str, list] = {v: [] for v in variants}
    per: dict[str, list] = {v: [] for v in variants}
    for rep in range(args.repeat):
        for variant in variants[rep % 3:] + variants[:rep % 3]:
            t0 = time.perf_counter()
            if variant == "batch":
                out = Path(tempfile.mkdtemp()) / "batch"
                batch.clear_caches()
                recs = batch.run({"name": "dl", "dataset": "tosca_remeshed_5k",
                                  "dataset_args": {"pairs": "test"}, "limit": args.limit,
                                  "eval_points": 50, "pictures": 0, "cache": cache,
                                  "output": str(out)}, progress=False)
                assert sum(r["eigensolves"] for r in recs) == 0
                per[variant] += [r["time_prepare"] + r["time_match"] for r in recs]
            else:
                loader = DataLoader(subset, batch_size=1, num_workers=1,
                                    collate_fn=collate_list, worker_init_fn=worker_init)
                sources: dict = {}
                targets: dict = {}
                for (pair,) in loader:
                    t1 = time.perf_counter()
                    if variant == "match(pair)":
                        corr = torchheat.match(pair)
                    else:  # the README loop: each shape prepared once per role
                        src = prepared(sources, pair.source)
                        corr = torchheat.match(src, prepared(targets, pair.target))
                    corr.map  # noqa: B018 - the dense map is computed on first access
                    per[variant].append(time.perf_counter() - t1)
            walls[variant].append((time.perf_counter() - t0) / args.limit)
            print(variant, f"{walls[variant][-1]:.2f} s / pair", flush=True)
    print(f"\n{args.limit} TOSCA 5k test pairs, eigenpairs from the disk cache, "
          f"{torch.get_num_threads()} torch threads\n")
    print("| | s / pair (match) | wall s / pair, each round |\n|---|---|---|")
    for v in variants:
        name = "batch evaluation (prepare + match; eval on 50 points)" if v == "batch" \
            else f"DataLoader loop, {v}"
        print(f"| {name} | {np.mean(per[v]):.2f} | "
              + ", ".join(f"{w:.2f}" for w in walls[v]) + " |")


def bench_report(args: argparse.Namespace) -> None:
    """Work counts and times of a finished run, from its results.jsonl."""
    recs = _records(Path(args.output))
    metas = {m["id"]: m for r in recs for m in r.get("shapes", ())}
    shapes = {m["name"] for m in metas.values()}
    solved = [m for m in metas.values() if m["computed"]]
    cold = [r for r in recs if r["time_eval"] > 1.0]
    hosts: dict[str, int] = {}
    for r in recs:
        hosts[r.get("host", "?")] = hosts.get(r.get("host", "?"), 0) + 1
    tgt: dict[str, int] = {}
    for r in cold:
        tgt[r["target"]] = tgt.get(r["target"], 0) + 1
    print(f"pairs {len(recs)}, shapes {len(shapes)}, eigensolves: {len(solved)} in shape tasks "
          f"(mean {np.mean([m['seconds'] for m in solved]):.2f} s each) + "
          f"{sum(r.get('eigensolves', 0) for r in recs)} in pair tasks")
    for key in ("time_prepare", "time_match", "time_eval"):
        v = np.array([r[key] for r in recs])
        print(f"{key}: mean {v.mean():.2f} s, median {np.median(v):.2f} s, total {v.sum():.0f} s")
    print(f"evaluations with a cold target (> 1 s): {len(cold)}, mean "
          f"{np.mean([r['time_eval'] for r in cold]) if cold else 0:.1f} s; per target: "
          f"{np.mean(list(tgt.values())) if tgt else 0:.2f} (max {max(tgt.values(), default=0)})")
    print(f"pairs per worker process: {sorted(hosts.values())}")
    u = np.mean([r["direct"]["under_0.25"] for r in recs])
    f = np.mean([r["flip"]["under_0.25"] for r in recs if r.get("flip")])
    print(f"accuracy: {100 * u:.1f} % under 0.25 ({100 * f:.1f} % flip-aware), mean error "
          f"{np.mean([r['direct']['mean'] for r in recs]):.4f}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    t = sub.add_parser("throughput")
    t.add_argument("--config", default=str(ROOT / "configs" / "tosca5k_timing.yaml"))
    t.add_argument("--limit", type=int, default=24)
    t.add_argument("--repeat", type=int, default=1)
    t.add_argument("--runs", default="pool,dask,cache", help="of pool, dask, cache, noprof")
    o = sub.add_parser("overhead")
    o.add_argument("--tasks", type=int, default=2000)
    d = sub.add_parser("dataloader")
    d.add_argument("--limit", type=int, default=24)
    d.add_argument("--repeat", type=int, default=2)
    r = sub.add_parser("report")
    r.add_argument("output", help="a run's output folder")
    args = ap.parse_args(argv)
    {"throughput": bench_throughput, "overhead": bench_overhead,
     "dataloader": bench_dataloader, "report": bench_report}[args.what](args)


if __name__ == "__main__":
    main()
