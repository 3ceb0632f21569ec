#!/usr/bin/env python
"""torchheat against pyFM's README pipeline, side by side on the same pairs and metric.

    python scripts/compare_pyfm.py [--set tosca12|scape6|tosca|scape|CONFIG.yaml] [--points 300]
                                   [--process [--runs N]] [--fine K]
                                   [--out out/compare_pyfm.json] [--shard I/N]
                                   [--records R.jsonl]
    python scripts/compare_pyfm.py --summarize R1.jsonl [R2.jsonl ...]

pyFM (``pip install pyfmaps``; an optional dependency of this script only, never imported by
the package) runs the pipeline of its README (v1.3.1): ``TriMesh.load(path, area_normalize=
True, center=True)``, ``preprocess(descr_type="WKS", subsample_step=2)``, ``fit(K=30,
w_descr=1, w_lap=0.1, w_dcomm=1, w_orient=1)`` (the orientation-preserving term), then
``zoomout_refine(nit=16, step=5)`` (30 -> 110 eigenfunctions) and ``get_p2p``. pyFM's
``p2p_21`` maps mesh2's vertices to mesh1, so mesh1 is our target and mesh2 our source.
torchheat runs ``prepare`` + ``match`` with default options (``--fine K``: ``match(fine_k=K)``,
the command line's ``--fine K``). Both in this process, one thread (BLAS and torch), back to
back per pair.

Metric (the same for both): Princeton error ε(x) = d_N(f(x), f*(x)) / sqrt(area N) on
``--points`` evenly spaced ground-truth rows per pair (``torchheat.evaluate.geodesic_errors``,
heat-method geodesics), direct, and flip-aware on TOSCA (the whole map judged against the
direct or the symmetric ground truth, whichever has the lower mean error); "consistent": the
direct errors on the rows whose ground truth agrees with its neighbours'
(``torchheat.evaluate.gt_disagreement`` at most 0.1; TOSCA's ``.vts`` files contradict
themselves on 0.5 % of rows).

``--process`` also times each tool as a whole process on the first pair (``torchheat match``
CLI against a ``python -c`` running pyFM's pipeline), back to back, ``--runs N`` times
alternating (medians): with one thread each, and with each tool's defaults (thread variables
unset, all cores).

Sets: a batch config's path (its dataset and pairs, e.g. ``configs/scape50.yaml``),
``tosca12`` = two test pairs per class (the first two of each class in test_pairs.txt:
16 pairs; the name is that of the issue's 12-pair measurement), ``scape6`` = SCAPE pairs
(0,1), (4,6), (8,9), (3,13), (5,15), (10,19); ``tosca`` = all 284 test pairs, ``scape`` =
the 40 pairs of configs/scape.yaml.

Long sets (all 284 TOSCA pairs: about 10 s per pair here for both tools and the evaluation)
run in shards side by side, one process per core: ``--shard I/N`` takes pairs ``I, I + N,
...``; ``--records R.jsonl`` appends each pair's record as it is done (one line, flushed) and,
run again, skips the pairs already there (resume). ``--summarize`` prints the summary of one
or more record files (the shards together).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

_THREAD_VARS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
for _var in _THREAD_VARS:  # one thread for both tools (before numpy is imported)
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

SCAPE6 = [(0, 1), (4, 6), (8, 9), (3, 13), (5, 15), (10, 19)]

PYFM_SNIPPET = """
import sys
from pyFM.mesh import TriMesh
from pyFM.functional import FunctionalMapping
import numpy as np
m1 = TriMesh.load(sys.argv[2], area_normalize=True, center=True)
m2 = TriMesh.load(sys.argv[1], area_normalize=True, center=True)
model = FunctionalMapping(m1, m2)
model.preprocess(descr_type="WKS", subsample_step=2)
model.fit(K=30, w_descr=1e0, w_lap=1e-1, w_dcomm=1e0, w_orient=1e0)
fm = model.zoomout_refine(nit=16, step=5)
np.savetxt(sys.argv[3], model.get_p2p(fm), fmt="%d")
"""


def pyfm_map(source_path: str, target_path: str) -> np.ndarray:
    """pyFM's README pipeline; returns the target vertex of every source vertex."""
    from pyFM.functional import FunctionalMapping
    from pyFM.mesh import TriMesh

    m1 = TriMesh.load(target_path, area_normalize=True, center=True)
    m2 = TriMesh.load(source_path, area_normalize=True, center=True)
    model = FunctionalMapping(m1, m2)
    model.preprocess(descr_type="WKS", subsample_step=2)
    model.fit(K=30, w_descr=1e0, w_lap=1e-1, w_dcomm=1e0, w_orient=1e0)
    fm = model.zoomout_refine(nit=16, step=5)
    return np.asarray(model.get_p2p(fm), dtype=np.int64)


def rows(n_gt: int, points: int) -> np.ndarray:
    """``points`` evenly spaced ground-truth rows (all when fewer), the rows a batch config's
    ``eval_points`` takes (``torchheat.batch.task``: rounded, not truncated; on a victoria pair
    the two 300-row sets read mean 0.0273 and 0.0460 of one map, all 5000 rows 0.0340)."""
    return np.unique(np.linspace(0, n_gt - 1, min(points, n_gt)).round().astype(np.int64))


def princeton(target, pred: np.ndarray, gt: np.ndarray, gt_sym: np.ndarray | None,
              solver=None) -> dict:
    """Direct and flip-aware Princeton errors of predicted target vertices ``pred`` against
    ``gt`` (and ``gt_sym``): ``{"direct": errors, "flip": errors or None}``; the flip-aware
    errors are those of the ground truth with the lower mean error (the whole map)."""
    from torchheat.evaluate import GeodesicSolver, geodesic_errors

    solver = solver or GeodesicSolver(target)
    e = geodesic_errors(target, pred, gt, solver=solver)
    out = {"direct": e, "flip": None}
    if gt_sym is not None:
        es = geodesic_errors(target, pred, gt_sym, solver=solver)
        out["flip"] = e if e.mean() <= es.mean() else es
    return out


def _summary(e: np.ndarray | None) -> dict | None:
    if e is None:
        return None
    return {"mean": float(e.mean()), "under_0.25": float((e < 0.25).mean()),
            "under_0.05": float((e < 0.05).mean())}


def pairs_of(name: str):
    from torchheat import datasets

    if name.endswith((".yaml", ".yml")):  # a batch config's dataset and pairs (its match
        # options are not used: both tools run their defaults)
        from torchheat.batch import load_pairs

        return load_pairs(name)
    if name == "scape6":
        return datasets.scape(pairs=SCAPE6)
    if name == "scape":
        return datasets.scape()
    pc = datasets.tosca_remeshed_5k()
    if name == "tosca":
        return pc
    seen: dict[str, int] = {}
    keep = []
    for i in range(len(pc)):
        cls = pc[i].cls
        if seen.get(cls, 0) < 2:
            seen[cls] = seen.get(cls, 0) + 1
            keep.append((pc.shapes.names[pc.pairs[i][0]], pc.shapes.names[pc.pairs[i][1]]))
    return datasets.tosca_remeshed_5k(pairs=keep)


def _path(shape) -> str:
    return str(shape.path)


def process_times(src: str, tgt: str, tmp: Path, fine: int | None = None,
                  runs: int = 1) -> dict:
    """Whole-process wall times of both tools on one pair, back to back, ``runs`` times
    alternating (medians; this host's single runs move by 10-20 %).

    Two settings: ``one thread`` (``torchheat match --threads 1`` and pyFM, both with one BLAS
    thread: this script's environment), and ``defaults`` (both as a user runs them: the three
    thread variables unset, ``torchheat match`` with its default threads).
    """
    import statistics

    root = str(Path(__file__).resolve().parents[1])
    one = dict(os.environ, PYTHONPATH=root)
    dflt = {k: v for k, v in one.items() if k not in _THREAD_VARS}
    extra = [] if fine is None else ["--fine", str(fine)]
    th = [sys.executable, "-c", "from torchheat.cli import run; run()", "match", src, tgt,
          "-o", str(tmp / "th.txt"), *extra]
    pf = [sys.executable, "-c", PYFM_SNIPPET, src, tgt, str(tmp / "pyfm.txt")]
    cases = {"torchheat_process_s": (th + ["--threads", "1"], one),
             "pyfm_process_s": (pf, one),
             "torchheat_process_default_s": (th, dflt),
             "pyfm_process_default_s": (pf, dflt)}
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(max(1, int(runs))):
        for key, (cmd, env) in cases.items():
            t0 = time.perf_counter()
            subprocess.run(cmd, check=True, env=env, capture_output=True)
            times[key].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def main(argv: list[str]) -> None:
    import torch

    import torchheat
    from torchheat.evaluate import GT_DISAGREEMENT, GeodesicSolver, gt_disagreement

    torch.set_num_threads(1)
    name, points, proc, outf, fine, runs = "tosca12", 300, False, None, None, 1
    shard, nshards, records = 0, 1, None
    if argv[:1] == ["--summarize"]:
        summarize([json.loads(line) for f in argv[1:] for line in Path(f).read_text().splitlines()
                   if line.strip()])
        return
    it = iter(argv)
    for a in it:
        if a == "--shard":
            spec = next(it, "")
            try:
                shard, nshards = (int(v) for v in spec.split("/"))
            except ValueError:
                raise SystemExit(f"--shard {spec!r}: give I/N, e.g. --shard 0/2") from None
            if not 0 <= shard < nshards:
                raise SystemExit(f"--shard {shard}/{nshards}: I must be in 0 .. N-1")
        elif a == "--records":
            records = Path(next(it))
        elif a == "--set":
            name = next(it)
        elif a == "--points":
            points = int(next(it))
        elif a == "--process":
            proc = True
        elif a == "--out":
            outf = next(it)
        elif a == "--fine":
            fine = int(next(it))
        elif a == "--runs":
            runs = int(next(it))
        else:
            raise SystemExit(__doc__)
    pc = pairs_of(name)
    res: list[dict] = []
    done: set[str] = set()
    if records is not None and records.exists():  # resume: the pairs already recorded
        res = [json.loads(line) for line in records.read_text().splitlines() if line.strip()]
        done = {r["name"] for r in res}
    print(f"load average at start: {os.getloadavg()}", flush=True)
    for i in range(shard, len(pc), nshards):
        pr = pc[i]
        if pr.name in done:
            continue
        S, T = pr.source.mesh, pr.target.mesh
        gs, gt = pr.gt_src.numpy(), pr.gt_tgt.numpy()
        sel = rows(len(gs), points)
        gsym = None if pr.gt_sym_tgt is None else pr.gt_sym_tgt.numpy()[sel]
        t0 = time.perf_counter()
        corr = torchheat.match(torchheat.prepare(S), torchheat.prepare(T), fine_k=fine)
        f_th = corr.map.numpy()
        t1 = time.perf_counter()
        f_pf = pyfm_map(_path(pr.source), _path(pr.target))
        t2 = time.perf_counter()
        solver = GeodesicSolver(T)
        # rows whose ground truth contradicts its neighbours' (no continuous map is right there)
        consistent = ~(gt_disagreement(S, T, gs, gt, rows=sel, solver=solver) > GT_DISAGREEMENT)
        rec = {"name": pr.name, "cls": pr.cls, "points": int(sel.size),
               "gt_contradicted": float(1 - consistent.mean()),
               "torchheat_s": t1 - t0, "pyfm_s": t2 - t1}
        for tool, f in (("torchheat", f_th), ("pyfm", f_pf)):
            e = princeton(T, f[gs[sel]], gt[sel], gsym, solver)
            rec[tool] = {"direct": _summary(e["direct"]), "flip": _summary(e["flip"]),
                         "consistent": _summary(e["direct"][consistent])
                         if consistent.any() else None}
        if proc and i == 0:
            rec.update(process_times(_path(pr.source), _path(pr.target),
                                     Path(outf or "out/compare_pyfm.json").parent, fine, runs))
        res.append(rec)
        if records is not None:
            records.parent.mkdir(parents=True, exist_ok=True)
            with records.open("a") as fh:  # one whole line per pair: a cut run loses one
                fh.write(json.dumps(rec) + "\n")
        print(f"{pr.name:22s} torchheat {rec['torchheat']['direct']['under_0.25']:.3f} "
              f"({rec['torchheat']['direct']['mean']:.4f}, {rec['torchheat_s']:.2f} s)  "
              f"pyFM {rec['pyfm']['direct']['under_0.25']:.3f} "
              f"({rec['pyfm']['direct']['mean']:.4f}, {rec['pyfm_s']:.2f} s)", flush=True)
    print(f"load average at end: {os.getloadavg()}")
    summarize(res, runs)
    if outf:
        Path(outf).parent.mkdir(parents=True, exist_ok=True)
        Path(outf).write_text(json.dumps(res, indent=1))


def summarize(res: list[dict], runs: int = 1) -> None:
    """Print both tools' direct, flip-aware and consistent-row figures over the records."""
    print(f"{len(res)} pairs")
    for tool in ("torchheat", "pyfm"):
        for kind in ("direct", "flip", "consistent"):
            vals = [r[tool][kind] for r in res if r[tool][kind] is not None]
            if vals:
                print(f"{tool:9s} {kind:6s} n={len(vals)} % < 0.25 "
                      f"{100 * np.mean([v['under_0.25'] for v in vals]):.1f}  mean "
                      f"{np.mean([v['mean'] for v in vals]):.4f}  % < 0.05 "
                      f"{100 * np.mean([v['under_0.05'] for v in vals]):.1f}  min "
                      f"{100 * min(v['under_0.25'] for v in vals):.1f}")
        print(f"{tool:9s} time per pair (in process) "
              f"{np.mean([r[tool + '_s'] for r in res]):.2f} s; pairs under 90 %: "
              f"{sum(r[tool]['direct']['under_0.25'] < 0.9 for r in res)}")
    # by class, and head to head on the pairs both tools get right (>= 99 % under 0.25)
    for cls in sorted({r["cls"] for r in res}):
        rc = [r for r in res if r["cls"] == cls]
        print(f"  {cls:9s} n={len(rc):3d} " + "  ".join(
            f"{tool} {100 * np.mean([r[tool]['direct']['under_0.25'] for r in rc]):5.1f} % "
            f"{np.mean([r[tool]['direct']['mean'] for r in rc]):.4f}"
            for tool in ("torchheat", "pyfm")))
    both = [r for r in res if min(r[t]["direct"]["under_0.25"] for t in ("torchheat", "pyfm"))
            >= 0.99]
    if both:
        th, pf = (np.array([r[t]["direct"]["mean"] for r in both]) for t in ("torchheat", "pyfm"))
        print(f"both right (>= 99 %): {len(both)} pairs, mean eps torchheat {th.mean():.4f}, "
              f"pyFM {pf.mean():.4f}; torchheat finer on {int((th < pf).sum())}")
    if res and "pyfm_process_s" in res[0]:
        r0 = res[0]
        print(f"whole process, first pair (median of {runs}): one thread: torchheat "
              f"{r0['torchheat_process_s']:.2f} s, pyFM {r0['pyfm_process_s']:.2f} s; defaults: "
              f"torchheat {r0['torchheat_process_default_s']:.2f} s, pyFM "
              f"{r0['pyfm_process_default_s']:.2f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
