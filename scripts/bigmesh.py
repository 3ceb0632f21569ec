#!/usr/bin/env python
"""Big meshes: time and peak memory of ``torchheat match`` on subdivided KIDS pairs.

    python scripts/bigmesh.py --sizes 60k,120k,239k,300k [--workers default,0] [--geodesic 200]
    python scripts/bigmesh.py --sizes 300k --keep /tmp/big   # also keep the OFF files

Builds, at run time and into a temporary directory (the KIDS meshes are for academic use and
are never written into the repository), a pair of meshes of the requested size from
``kids/0001.null.0.off`` and ``kids/0001.isometry.1.off`` (59 727 vertices each, same
connectivity) by midpoint subdivision applied identically to both, then runs ``torchheat
match`` on it as a subprocess with default options and reports:

* wall time of the process, and the per-stage timings the command prints;
* peak memory of the whole process tree (the command and its forked eigensolve workers):
  the largest sum of the tree's resident sets (``VmRSS``) and of its proportional set sizes
  (``Pss``, shared copy-on-write pages counted once), sampled every 0.1 s from ``/proc``,
  and ``ru_maxrss`` of ``wait4`` (the largest single process of the tree, what ``/usr/bin/time
  -v`` prints); the peak of the tree's RSS within each stage (stages located from the printed
  timings; approximate to the sampling interval);
* accuracy against the ground truth (the identity, see below): Euclidean error of every
  vertex's image divided by sqrt(area) of the target (a lower bound of the geodesic error),
  and on ``--geodesic`` random vertices the geodesic error (heat method,
  :class:`torchheat.evaluate.GeodesicSolver`): the fraction under 0.25 and the mean.

How the sizes are reached. One level of 1:4 midpoint subdivision (every edge split at its
midpoint, every triangle into four) takes the 59 727 vertices to 59 727 + #edges = 238 703.
A size between two full levels is reached by splitting only some edges of the next level:
the ``n_target - n`` edges with the smallest coordinate along the null pose's longest
bounding-box axis (one end of the body becomes twice as fine, a realistic graded mesh);
each triangle is then split by how many of its edges are split (1: into two, 2: into three,
the quad cut along its shorter diagonal in the null pose, 3: into four), which keeps the mesh
conforming. Every decision is taken on the null pose and applied to both meshes, and the
new vertices are numbered by edge (sorted vertex pairs) on both, so vertex ``i`` of one
corresponds to vertex ``i`` of the other: the ground truth stays the identity.

Results go to stdout (a table) and, with ``--json``, to a file.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TORCHHEAT_DATA", ROOT.parent / "shared" / "data"))
if not (DATA / "kids").is_dir():
    DATA = Path("/work/shared/data")
KIDS = ("kids/0001.null.0.off", "kids/0001.isometry.1.off")


# ------------------------------------------------------------------------------------------
# subdivision
# ------------------------------------------------------------------------------------------
def edges(F: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique edges ``E [e, 2]`` (``lo < hi``, sorted by ``(lo, hi)``) and, per face, the
    index of its edge ``j`` = ``(F[:, j], F[:, (j + 1) % 3])``, shape ``[f, 3]``."""
    a = F[:, [0, 1, 2]].reshape(-1)
    b = F[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    keys, inv = np.unique(lo.astype(np.int64) * n + hi, return_inverse=True)
    E = np.stack([keys // n, keys % n], axis=1)
    return E, inv.reshape(-1, 3)


def subdivide(Vs: list[np.ndarray], F: np.ndarray, marked: np.ndarray | None = None,
              ref: int = 0) -> tuple[list[np.ndarray], np.ndarray]:
    """Split the ``marked`` edges (boolean over :func:`edges`; None: all) at their midpoints
    in every mesh of ``Vs`` (same connectivity ``F``), and each face by its split edges.

    New vertices are appended in edge order. A face with 1 split edge becomes 2 triangles, 2
    split edges 3 (its quad cut along the shorter diagonal in ``Vs[ref]``), 3 split edges 4
    (1:4); orientation is kept. Returns the new vertex arrays and faces.
    """
    n = Vs[0].shape[0]
    E, fe = edges(F, n)
    if marked is None:
        marked = np.ones(len(E), dtype=bool)
    new_id = np.full(len(E), -1, dtype=np.int64)
    new_id[marked] = n + np.arange(int(marked.sum()))
    out_V = [np.concatenate([V, 0.5 * (V[E[marked, 0]] + V[E[marked, 1]])]) for V in Vs]
    mk = marked[fe]  # [f, 3]: edge j of the face is split
    cnt = mk.sum(axis=1)
    mids = new_id[fe]  # [f, 3]: midpoint of edge j (or -1)
    out_F = [F[cnt == 0]]
    # rotate so that: 1 split edge -> it is edge 0; 2 split edges -> the unsplit one is edge 2
    r = np.zeros(len(F), dtype=np.int64)
    r[cnt == 1] = np.argmax(mk[cnt == 1], axis=1)
    r[cnt == 2] = (np.argmin(mk[cnt == 2], axis=1) + 1) % 3
    rows = np.arange(len(F))[:, None]
    cols = (np.arange(3)[None, :] + r[:, None]) % 3
    v, m = F[rows, cols], mids[rows, cols]
    s = cnt == 1  # v0 m0 v1 | v2
    out_F.append(np.stack([v[s, 0], m[s, 0], v[s, 2]], axis=1))
    out_F.append(np.stack([m[s, 0], v[s, 1], v[s, 2]], axis=1))
    s = np.flatnonzero(cnt == 2)  # corner (m0, v1, m1), then the quad v0 m0 m1 v2
    out_F.append(np.stack([m[s, 0], v[s, 1], m[s, 1]], axis=1))
    R = out_V[ref]
    d_v0m1 = np.linalg.norm(R[v[s, 0]] - R[m[s, 1]], axis=1)
    d_m0v2 = np.linalg.norm(R[m[s, 0]] - R[v[s, 2]], axis=1)
    a = s[d_v0m1 <= d_m0v2]  # diagonal v0-m1
    out_F.append(np.stack([v[a, 0], m[a, 0], m[a, 1]], axis=1))
    out_F.append(np.stack([v[a, 0], m[a, 1], v[a, 2]], axis=1))
    b = s[d_v0m1 > d_m0v2]  # diagonal m0-v2
    out_F.append(np.stack([v[b, 0], m[b, 0], v[b, 2]], axis=1))
    out_F.append(np.stack([m[b, 0], m[b, 1], v[b, 2]], axis=1))
    s = cnt == 3
    out_F.append(np.stack([v[s, 0], m[s, 0], m[s, 2]], axis=1))
    out_F.append(np.stack([v[s, 1], m[s, 1], m[s, 0]], axis=1))
    out_F.append(np.stack([v[s, 2], m[s, 2], m[s, 1]], axis=1))
    out_F.append(np.stack([m[s, 0], m[s, 1], m[s, 2]], axis=1))
    return out_V, np.concatenate(out_F).astype(np.int64)


def grow(Vs: list[np.ndarray], F: np.ndarray, n_target: int, ref: int = 0
         ) -> tuple[list[np.ndarray], np.ndarray]:
    """Subdivide ``Vs`` (same connectivity) until they have exactly ``n_target`` vertices:
    full 1:4 levels, then the ``n_target - n`` edges with the smallest coordinate of their
    farther end along ``Vs[ref]``'s longest bounding-box axis."""
    while True:
        n = Vs[0].shape[0]
        if n >= n_target:
            if n > n_target:
                raise ValueError(f"cannot shrink a {n}-vertex mesh to {n_target}")
            return Vs, F
        E, _ = edges(F, n)
        if n + len(E) <= n_target:
            Vs, F = subdivide(Vs, F, None, ref)
            continue
        R = Vs[ref]
        axis = int(np.argmax(R.max(axis=0) - R.min(axis=0)))
        key = np.maximum(R[E[:, 0], axis], R[E[:, 1], axis])
        marked = np.zeros(len(E), dtype=bool)
        marked[np.argsort(key, kind="stable")[: n_target - n]] = True
        Vs, F = subdivide(Vs, F, marked, ref)


def write_off(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    """Plain ASCII OFF (``%.9g`` coordinates)."""
    with open(path, "w", encoding="ascii") as fh:
        fh.write(f"OFF\n{len(V)} {len(F)} 0\n")
        np.savetxt(fh, V, fmt="%.9g")
        np.savetxt(fh, np.hstack([np.full((len(F), 1), 3), F]), fmt="%d")


def build_pair(n_target: int, out_dir: Path) -> tuple[Path, Path, dict]:
    """Write the subdivided KIDS pair of ``n_target`` vertices to ``out_dir``."""
    sys.path.insert(0, str(ROOT))
    from torchheat.meshio import read_arrays

    V0, F0 = read_arrays(DATA / KIDS[0])
    V1, F1 = read_arrays(DATA / KIDS[1])
    if not np.array_equal(F0, F1):
        raise SystemExit("the two KIDS meshes do not share their connectivity")
    (W0, W1), F = grow([V0, V1], F0.astype(np.int64), n_target)
    paths = []
    for name, V in (("null", W0), ("iso", W1)):
        p = out_dir / f"kids_{name}_{len(V)}.off"
        write_off(p, V, F)
        paths.append(p)
    return paths[0], paths[1], {"vertices": int(len(W0)), "faces": int(len(F))}


# ------------------------------------------------------------------------------------------
# measuring a process tree
# ------------------------------------------------------------------------------------------
def _children_map() -> dict[int, list[int]]:
    kids: dict[int, list[int]] = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat", "rb") as fh:
                stat = fh.read()
        except OSError:
            continue
        ppid = int(stat[stat.rindex(b")") + 2 :].split()[1])
        kids.setdefault(ppid, []).append(int(d))
    return kids


def _tree(root: int) -> list[int]:
    kids = _children_map()
    out, todo = [], [root]
    while todo:
        p = todo.pop()
        out.append(p)
        todo.extend(kids.get(p, []))
    return out


def _kib(path: str, field_name: str) -> int:
    try:
        with open(path, encoding="ascii") as fh:
            for line in fh:
                if line.startswith(field_name):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


@dataclass
class Sampler:
    """Samples the RSS and PSS sums of a process tree every ``interval`` seconds."""

    root: int
    interval: float = 0.1
    samples: list[tuple[float, int, int, int]] = field(default_factory=list)  # t, rss, pss, n
    _stop: threading.Event = field(default_factory=threading.Event)

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            pids = _tree(self.root)
            rss = sum(_kib(f"/proc/{p}/status", "VmRSS:") for p in pids)
            pss = sum(_kib(f"/proc/{p}/smaps_rollup", "Pss:") for p in pids)
            if rss:
                self.samples.append((time.time(), rss, pss, len(pids)))
            self._stop.wait(self.interval)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


# the command's entry point with this checkout first on the path (``python -c`` puts the
# working directory first, which may hold another checkout)
_LAUNCH = ("import sys, time; print('T0', repr(time.time()), flush=True); "
           f"sys.path.insert(0, {str(ROOT)!r}); "
           "from torchheat.cli import run; sys.argv[0] = 'torchheat'; run()")


def run_match(src: Path, tgt: Path, out: Path, workers: str | None,
              extra: list[str] | None = None) -> dict:
    """Run ``torchheat match src tgt -o out`` and measure it (see the module docstring)."""
    cmd = [sys.executable, "-c", _LAUNCH, "match", str(src), str(tgt), "-o", str(out)]
    if workers is not None:
        cmd += ["--workers", workers]
    cmd += list(extra or [])
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    log = tempfile.TemporaryFile(mode="w+")
    t0 = time.time()
    proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, env=env,
                            cwd=tempfile.gettempdir())
    sampler = Sampler(proc.pid)
    sampler.start()
    _, status, ru = os.wait4(proc.pid, 0)
    wall = time.time() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    sampler.stop()
    log.seek(0)
    text = log.read()
    if proc.returncode != 0:
        raise RuntimeError(f"torchheat match failed ({proc.returncode}):\n{text}")
    m = re.search(r"^T0 (\S+)$", text, re.M)
    t_launch = float(m.group(1)) if m else t0
    tm = re.search(r"^timings: (.*)$", text, re.M)
    stages: dict[str, float] = {}
    if tm:
        for part in tm.group(1).split(", "):
            name, sec = part.rsplit(" ", 2)[0], float(part.rsplit(" ", 2)[1])
            stages[name] = sec
    # stage windows on the sampler's clock: sequential stages in printed order ("match
    # total" overlaps the ones before it and is skipped)
    bounds, t = [("start-up (interpreter, cli import)", t0, t_launch + 0.05)], t_launch + 0.05
    for name, sec in stages.items():
        if name == "match total":
            continue
        bounds.append((name, t, t + sec))
        t += sec
    bounds.append(("write + exit", t, t0 + wall + 1))
    stage_peak = {}
    for name, a, b in bounds:
        inside = [s[1] for s in sampler.samples if a <= s[0] < b]
        stage_peak[name] = max(inside) / 2**20 if inside else float("nan")  # GiB
    peak_rss = max((s[1] for s in sampler.samples), default=0) / 2**20
    peak_pss = max((s[2] for s in sampler.samples), default=0) / 2**20
    return {"wall_s": wall, "stages_s": stages, "stage_peak_rss_gib": stage_peak,
            "peak_tree_rss_gib": peak_rss, "peak_tree_pss_gib": peak_pss,
            "ru_maxrss_gib": ru.ru_maxrss / 2**20, "cpu_s": ru.ru_utime + ru.ru_stime,
            "max_processes": max((s[3] for s in sampler.samples), default=0),
            "log": text}


def read_map(path: Path) -> np.ndarray:
    return np.loadtxt(path, dtype=np.int64).reshape(-1)


def accuracy(tgt: Path, fmap: np.ndarray, n_geodesic: int, seed: int = 0) -> dict:
    """Errors of ``fmap`` against the identity, divided by sqrt(area) of the target."""
    sys.path.insert(0, str(ROOT))
    from torchheat.meshio import read_arrays

    W, F = read_arrays(tgt)
    area = 0.5 * np.linalg.norm(np.cross(W[F[:, 1]] - W[F[:, 0]], W[F[:, 2]] - W[F[:, 0]]),
                                axis=1).sum()
    e = np.linalg.norm(W[fmap] - W, axis=1) / math.sqrt(area)
    out = {"exact": float(np.mean(fmap == np.arange(len(W)))),
           "euclid_under_0.25": float(np.mean(e <= 0.25)), "euclid_mean": float(e.mean())}
    if n_geodesic > 0:
        from torchheat.evaluate import GeodesicSolver

        idx = np.random.default_rng(seed).choice(len(W), size=min(n_geodesic, len(W)),
                                                 replace=False)
        t = time.perf_counter()
        solver = GeodesicSolver((W, F))
        g = solver.pairwise(idx, fmap[idx]) / math.sqrt(solver.area)
        out.update({"geodesic_samples": int(idx.size), "geodesic_under_0.25":
                    float(np.mean(g <= 0.25)), "geodesic_mean": float(g.mean()),
                    "geodesic_s": time.perf_counter() - t})
    return out


def parse_size(s: str) -> int:
    s = s.strip().lower()
    return int(float(s[:-1]) * 1000) if s.endswith("k") else int(s)


def machine() -> str:
    cpu = "unknown CPU"
    with open("/proc/cpuinfo", encoding="ascii", errors="replace") as fh:
        for line in fh:
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    mem = _kib("/proc/meminfo", "MemTotal:") / 2**20
    return f"{cpu}, {os.cpu_count()} CPUs, {mem:.1f} GiB"


def loadavg() -> str:
    with open("/proc/loadavg", encoding="ascii") as fh:
        return " ".join(fh.read().split()[:3])


def fit_exponent(ns: list[int], ys: list[float]) -> float:
    """Slope of log y against log n (least squares)."""
    return float(np.polyfit(np.log(ns), np.log(ys), 1)[0])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", default="60k,120k,239k,300k",
                    help="comma-separated vertex counts (k = 1000), each >= 59727")
    ap.add_argument("--workers", default="default",
                    help="comma-separated --workers values for torchheat match ('default': "
                         "the option left out)")
    ap.add_argument("--geodesic", type=int, default=200,
                    help="random vertices whose geodesic error is measured (0: none)")
    ap.add_argument("--extra", default="", help="further options for torchheat match")
    ap.add_argument("--keep", default=None, help="keep the meshes and maps in this directory")
    ap.add_argument("--json", default=None, help="append the results (JSON lines) here")
    args = ap.parse_args(argv)
    sizes = [parse_size(s) for s in args.sizes.split(",") if s.strip()]
    workers = [None if w == "default" else w for w in args.workers.split(",")]
    print(f"machine: {machine()}; python {sys.version.split()[0]}", flush=True)
    results = []
    with tempfile.TemporaryDirectory(prefix="bigmesh-") as tmp:
        out_dir = Path(args.keep) if args.keep else Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        for n in sizes:
            t = time.perf_counter()
            src, tgt, info = build_pair(n, out_dir)
            print(f"\n== {info['vertices']} vertices, {info['faces']} faces (built in "
                  f"{time.perf_counter() - t:.1f} s) ==", flush=True)
            for w in workers:
                load0 = loadavg()
                mp = out_dir / f"map_{info['vertices']}_{w or 'default'}.txt"
                r = run_match(src, tgt, mp, w, args.extra.split())
                r.update(info, workers=w or "default", load_before=load0, load_after=loadavg())
                r["accuracy"] = accuracy(tgt, read_map(mp), args.geodesic)
                log = r.pop("log")
                results.append(r)
                print(f"-- workers={r['workers']}: wall {r['wall_s']:.1f} s, cpu "
                      f"{r['cpu_s']:.1f} s, peak tree RSS {r['peak_tree_rss_gib']:.2f} GiB "
                      f"(PSS {r['peak_tree_pss_gib']:.2f}, largest process "
                      f"{r['ru_maxrss_gib']:.2f}), load {load0} -> {r['load_after']}")
                for name, sec in r["stages_s"].items():
                    pk = r["stage_peak_rss_gib"].get(name, float("nan"))
                    print(f"   {name:<45} {sec:8.2f} s   peak RSS {pk:6.2f} GiB")
                print(f"   accuracy: {json.dumps(r['accuracy'])}")
                print("   " + "\n   ".join(line for line in log.splitlines()
                                         if line.startswith(("landmarks", "orientation"))))
                sys.stdout.flush()
                if args.json:
                    with open(args.json, "a", encoding="utf-8") as fh:
                        fh.write(json.dumps(r) + "\n")
    for w in workers:
        rs = [r for r in results if r["workers"] == (w or "default")]
        if len(rs) >= 2:
            ns = [r["vertices"] for r in rs]
            print(f"\ngrowth (workers={w or 'default'}, {ns[0]}..{ns[-1]} vertices): time ~ "
                  f"n^{fit_exponent(ns, [r['wall_s'] for r in rs]):.2f}, peak tree RSS ~ "
                  f"n^{fit_exponent(ns, [r['peak_tree_rss_gib'] for r in rs]):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
