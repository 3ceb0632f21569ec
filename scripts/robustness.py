#!/usr/bin/env python
"""Robustness of the default matcher to what real files differ in: resolution and noise.

Pairs: the first two test pairs of each TOSCA class (``test_pairs.txt``); errors are
Euclidean on the target / sqrt(area of the target), over every ground-truth point, so that
all rows of a table use one metric.

``resolution``: pose A at 5k vertices (``tosca_remeshed_5k``) against pose B at full
resolution (``tosca_hires``, 4k-53k vertices, other triangles), and B's full resolution
against A's 5k, beside the 5k -> 5k pair. Ground truth: a 5k vertex of A is the nearest
vertex of A's full-resolution mesh (same pose; the remeshed vertices lie on it), and the
full-resolution poses of a class share their vertex numbering. Pairs without both
full-resolution files are skipped (michael, and some poses of others).

``noise``: B's vertices moved by Gaussian noise of RMS ``level`` x its bbox diagonal
(isotropic, the same faces), errors measured on the clean B; also the quality and suspect
flags of each map.

Usage::

    python scripts/robustness.py resolution [--classes cat,dog]
    python scripts/robustness.py noise --levels 0,0.002,0.005,0.01 [--classes ...]

Prints one line per pair and a summary per setting (share under 0.25, mean error).
"""

from __future__ import annotations

import argparse
import math
import time
import warnings

import numpy as np
import torch
from scipy.spatial import cKDTree

import torchheat
from torchheat.datasets import data_root


def _pairs(root, classes: set[str] | None, per_class: int, need_hires: bool
           ) -> list[tuple[str, str]]:
    out, seen = [], {}
    for line in (root / "tosca_remeshed_5k" / "test_pairs.txt").read_text().splitlines():
        if not line.strip():
            continue
        a, b = line.split()
        c = "".join(ch for ch in a if ch.isalpha())
        if classes is not None and c not in classes:
            continue
        if need_hires and not all((root / "tosca_hires" / f"{s}.off").exists() for s in (a, b)):
            continue
        if seen.get(c, 0) < per_class:
            seen[c] = seen.get(c, 0) + 1
            out.append((a, b))
    return out


class _Shapes:
    """Meshes and prepared shapes, each loaded once."""

    def __init__(self) -> None:
        self.meshes: dict = {}
        self.prepared: dict = {}

    def mesh(self, path) -> torchheat.Mesh:
        if path not in self.meshes:
            self.meshes[path] = torchheat.load_mesh(path, largest_component=True)
        return self.meshes[path]

    def prep(self, path) -> torchheat.PreparedShape:
        if path not in self.prepared:
            self.prepared[path] = torchheat.prepare(self.mesh(path))
        return self.prepared[path]


def _vts(root, name: str) -> np.ndarray:
    return np.loadtxt(root / "tosca_remeshed_5k" / "vtx_5k" / "corres" / f"{name}.vts",
                      dtype=np.int64) - 1


def _file_index(mesh: torchheat.Mesh) -> np.ndarray:
    """File index of every vertex of ``mesh`` (they differ after largest_component)."""
    vm = mesh.vertex_map
    return np.arange(mesh.n_vertices) if vm is None else vm.numpy()


def _errors(Vt: np.ndarray, images: np.ndarray, truth: np.ndarray, area: float) -> np.ndarray:
    return np.linalg.norm(Vt[images] - Vt[truth], axis=1) / math.sqrt(area)


def _row(e: np.ndarray) -> str:
    return f"{100 * np.mean(e < 0.25):5.1f} % / {e.mean():.4f}"


def resolution(root, pairs: list[tuple[str, str]]) -> None:
    d5, dh = root / "tosca_remeshed_5k" / "vtx_5k", root / "tosca_hires"
    S = _Shapes()
    rows = {"5k -> 5k": [], "5k -> full": [], "full -> 5k": []}
    for a, b in pairs:
        A5, B5 = S.prep(d5 / f"{a}.off"), S.prep(d5 / f"{b}.off")
        AH, BH = S.prep(dh / f"{a}.off"), S.prep(dh / f"{b}.off")
        # 5k -> 5k, the .vts ground truth
        V5 = B5.mesh.numpy()[0]
        e55 = _errors(V5, torchheat.match(A5, B5).map.numpy()[_vts(root, a)], _vts(root, b),
                      B5.mesh.area())
        # 5k -> full: A5 vertex -> nearest A full vertex -> the same file index on B full
        _, near = cKDTree(AH.mesh.numpy()[0]).query(A5.mesh.numpy()[0])
        pos = np.full(BH.mesh.n_input_vertices, -1)
        pos[_file_index(BH.mesh)] = np.arange(BH.n)
        truth = pos[_file_index(AH.mesh)[near]]
        ok = truth >= 0
        t0 = time.perf_counter()
        m = torchheat.match(A5, BH).map.numpy()
        t_up = time.perf_counter() - t0
        e5h = _errors(BH.mesh.numpy()[0], m[ok], truth[ok], BH.mesh.area())
        # full -> 5k: A full vertex -> the same file index on B full -> nearest B5 vertex
        posb = np.full(BH.mesh.n_input_vertices, -1)
        posb[_file_index(BH.mesh)] = np.arange(BH.n)
        j = posb[_file_index(AH.mesh)]
        ok = j >= 0
        _, truth = cKDTree(V5).query(BH.mesh.numpy()[0][j[ok]])
        t0 = time.perf_counter()
        m = torchheat.match(AH, B5).map.numpy()
        t_down = time.perf_counter() - t0
        eh5 = _errors(V5, m[ok], truth, B5.mesh.area())
        for k, e in zip(rows, (e55, e5h, eh5), strict=True):
            rows[k].append(e)
        print(f"{a} -> {b} (full: {AH.n} / {BH.n} vertices): 5k -> 5k {_row(e55)}; "
              f"5k -> full {_row(e5h)} ({t_up:.1f} s); full -> 5k {_row(eh5)} "
              f"({t_down:.1f} s)", flush=True)
    _summary(rows)


def noise(root, pairs: list[tuple[str, str]], levels: list[float], seed: int) -> None:
    d5 = root / "tosca_remeshed_5k" / "vtx_5k"
    S = _Shapes()
    rng = np.random.default_rng(seed)
    rows: dict[str, list] = {f"noise {lv:g}": [] for lv in levels}
    flags: dict[str, list] = {k: [] for k in rows}
    for a, b in pairs:
        A, clean = S.prep(d5 / f"{a}.off"), S.mesh(d5 / f"{b}.off")
        V, F = clean.numpy()
        ga, gb = _vts(root, a), _vts(root, b)
        line = []
        for lv, key in zip(levels, rows, strict=True):
            W = V + rng.normal(scale=lv * clean.bbox_diagonal() / math.sqrt(3), size=V.shape)
            B = S.prep(d5 / f"{b}.off") if lv == 0 else torchheat.prepare(
                torchheat.Mesh(W, F, name=f"{b} + noise {lv:g}"))
            c = torchheat.match(A, B)
            e = _errors(V, c.map.numpy()[ga], gb, clean.area())  # on the clean target
            rows[key].append(e)
            flags[key].append((c.quality.quality, c.suspect))
            line.append(f"{lv:g}: {_row(e)} q {c.quality.quality:.2f}"
                        + (" SUSPECT" if c.suspect else ""))
        print(f"{a} -> {b}: " + " | ".join(line), flush=True)
    _summary(rows, flags)


def _summary(rows: dict[str, list], flags: dict[str, list] | None = None) -> None:
    print("\n| setting | pairs | % < 0.25 (mean of pairs) | mean error | quality | suspect |")
    print("|---|---|---|---|---|---|")
    for k, es in rows.items():
        share = np.mean([np.mean(e < 0.25) for e in es])
        mean = np.mean([e.mean() for e in es])
        q = s = "—"
        if flags is not None:
            q = f"{np.mean([f[0] for f in flags[k]]):.2f}"
            s = str(sum(bool(f[1]) for f in flags[k]))
        print(f"| {k} | {len(es)} | {100 * share:.2f} | {mean:.4f} | {q} | {s} |")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("what", choices=("resolution", "noise"))
    ap.add_argument("--classes", default=None, help="comma-separated TOSCA classes (default: all)")
    ap.add_argument("--per-class", type=int, default=2, help="test pairs per class (default 2)")
    ap.add_argument("--levels", default="0,0.002,0.005,0.01",
                    help="noise RMS as fractions of the bbox diagonal (noise)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    warnings.simplefilter("ignore", torchheat.MeshWarning)
    root = data_root()
    classes = None if args.classes is None else set(args.classes.split(","))
    pairs = _pairs(root, classes, args.per_class, need_hires=args.what == "resolution")
    if args.what == "resolution":
        resolution(root, pairs)
    else:
        noise(root, pairs, [float(x) for x in args.levels.split(",")], args.seed)


if __name__ == "__main__":
    main()
