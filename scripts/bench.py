#!/usr/bin/env python
"""Benchmarks of torchheat against the scipy code a user would otherwise write.

    python scripts/bench.py heat  [--mesh PATH] [--sources 64] [--threads N]
    python scripts/bench.py match [--source PATH --target PATH]

Every row is measured in the same run on the same input; errors are relative L2 errors per
(source, time) against scipy's ``expm_multiply``, maximised over sources and times.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import torch
from scipy.sparse.linalg import eigsh, expm_multiply

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torchheat  # noqa: E402
from torchheat import HeatKernel, Mesh, laplacian, load_mesh  # noqa: E402

warnings.filterwarnings("ignore", message="Sparse")


def generic_mesh(subdivisions: int = 5, seed: int = 0) -> Mesh:
    """~10k-vertex ellipsoid with random bumps (no symmetry, irregular triangles)."""
    import trimesh

    m = trimesh.creation.icosphere(subdivisions)
    rng = np.random.default_rng(seed)
    V = m.vertices * np.array([1.0, 0.7, 0.5]) * (1 + 0.02 * rng.standard_normal((len(m.vertices), 1)))
    return Mesh(V, m.faces, name=f"bumpy-ellipsoid-{len(V)}")


def machine() -> str:
    try:
        cpu = next(
            line.split(":", 1)[1].strip()
            for line in open("/proc/cpuinfo")
            if line.startswith("model name")
        )
    except (OSError, StopIteration):
        cpu = platform.processor() or "unknown CPU"
    return f"{cpu}, {torch.get_num_threads()} torch threads, torch {torch.__version__}"


def table(rows: list[tuple], header: tuple) -> str:
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    line = "| " + " | ".join(str(h).ljust(w) for h, w in zip(header, widths, strict=True)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    body = [
        "| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths, strict=True)) + " |"
        for r in rows
    ]
    return "\n".join([line, sep, *body])


def bench_heat(args) -> None:
    mesh = load_mesh(args.mesh) if args.mesh else generic_mesh()
    if args.threads:
        torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    src = rng.choice(mesh.n_vertices, args.sources, replace=False)
    times = torchheat.default_times().numpy()
    print(f"# heat benchmark: {mesh.name}, n = {mesh.n_vertices}, {len(src)} sources x "
          f"{len(times)} times, rtol 1e-6")
    print(f"# machine: {machine()}")

    # reference: scipy expm_multiply on a subset of sources (all times)
    lap = laplacian(mesh)
    a = lap.mass_scipy.diagonal()
    L = (sp.diags(1.0 / a) @ lap.stiffness_scipy).tocsc()
    sub = src[: args.ref_sources]
    E = np.zeros((mesh.n_vertices, len(sub)))
    E[sub, np.arange(len(sub))] = 1.0 / a[sub]
    t0 = time.perf_counter()
    ref = np.stack([expm_multiply(-t * L, E) for t in times], axis=2)  # [n, b, J]
    t_ref = (time.perf_counter() - t0) * len(src) / len(sub)
    ref = ref.transpose(1, 0, 2)  # [b, n, J]

    def err(C: np.ndarray) -> tuple[float, float]:
        e = np.linalg.norm(C[: len(sub)] - ref, axis=1) / np.linalg.norm(ref, axis=1)
        return float(e.max()), float(e[:, 0].max())

    rows = []
    for label, kw in (
        ("torchheat hybrid (default)", {}),
        ("torchheat Chebyshev only", {"method": "chebyshev"}),
        ("torchheat hybrid float32", {"dtype": torch.float32, "rtol": 1e-4}),
    ):
        best = None
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                hk = HeatKernel(mesh, **kw)
            t1 = time.perf_counter()
            C = hk.columns(src)
            t2 = time.perf_counter()
            if best is None or t2 - t0 < best[0]:
                best = (t2 - t0, t1 - t0, t2 - t1)
        e_all, e_small = err(C.double().numpy())
        rows.append((label, f"{best[0]:.3f}", f"{best[1]:.3f}", f"{best[2]:.3f}",
                     f"{e_all:.1e}", f"{e_small:.1e}", f"{t_ref / best[0]:.0f}x"))

    # truncated spectrum k = 100, the usual shortcut
    t0 = time.perf_counter()
    W, M = lap.stiffness_scipy, lap.mass_scipy
    lam, phi = eigsh(W, k=100, M=M, sigma=-0.01, which="LM")
    t1 = time.perf_counter()
    C = np.einsum("nk,bk,kj->bnj", phi, phi[src], np.exp(-np.outer(lam, times)))
    t2 = time.perf_counter()
    e_all, e_small = err(C)
    rows.append(("scipy truncated spectrum k=100", f"{t2 - t0:.3f}", f"{t1 - t0:.3f}",
                 f"{t2 - t1:.3f}", f"{e_all:.1e}", f"{e_small:.1e}", f"{t_ref / (t2 - t0):.0f}x"))
    rows.append((f"scipy expm_multiply (timed on {len(sub)} sources, x{len(src) / len(sub):.0f})",
                 f"{t_ref:.1f}", "-", f"{t_ref:.1f}", "reference", "reference", "1x"))
    print(table(rows, ("method", "total s", "set-up s", f"{len(src)} columns s",
                       "max rel err", "err at t=0.001", "vs expm_multiply")))


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    h = sub.add_parser("heat", help="heat-kernel columns: torchheat vs scipy")
    h.add_argument("--mesh", help="mesh file (default: a ~10k-vertex bumpy ellipsoid)")
    h.add_argument("--sources", type=int, default=64)
    h.add_argument("--ref-sources", type=int, default=2,
                   help="sources timed with expm_multiply (extrapolated to --sources)")
    h.add_argument("--threads", type=int, default=None)
    h.add_argument("--repeat", type=int, default=3)
    args = p.parse_args(argv)
    if args.cmd == "heat":
        bench_heat(args)


if __name__ == "__main__":
    main()
