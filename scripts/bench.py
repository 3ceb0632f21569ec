#!/usr/bin/env python
"""Benchmarks of torchheat against the scipy code a user would otherwise write.

    python scripts/bench.py heat  [--mesh PATH] [--sources 64] [--threads N]
    python scripts/bench.py fmap  [--source PATH --target PATH] [--k 30]
    python scripts/bench.py match [--source PATH --target PATH]
    python scripts/bench.py partial [--source PIECE --target WHOLE]
    python scripts/bench.py fine  [--source PATH --target PATH] [--k 200]
    python scripts/bench.py gtcheck [--pairs victoria17:victoria2,...]
    python scripts/bench.py threads [--source PATH --target PATH] [--candidates 16]

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
    bumps = 1 + 0.02 * rng.standard_normal((len(m.vertices), 1))
    V = m.vertices * np.array([1.0, 0.7, 0.5]) * bumps
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


def scipy_reference_match(V1, F1, V2, F2, k: int = 300, n_times: int = 10):
    """The plain scipy pipeline a user would write: truncated spectrum + cKDTree.

    Same algorithm as ``match(method="paper")``: cotan/lumped operators, k eigenpairs
    (shift-invert eigsh), t-scaled HKM + HKS at the paper's times, HKS-maxima features,
    every target feature scored with a cKDTree (L-infinity), dense map by cKDTree.
    Returns (map, timings).
    """
    from scipy.spatial import cKDTree

    from torchheat.eigen import cotmatrix_scipy as _cotmatrix_scipy
    from torchheat.eigen import massmatrix_scipy as _massmatrix_scipy

    tm: dict[str, float] = {}
    t0 = time.perf_counter()
    shapes = []
    for V, F in ((V1, F1), (V2, F2)):
        W = _cotmatrix_scipy(V, F)
        M = _massmatrix_scipy(V, F, "lumped")
        M = M / M.sum()
        lam, phi = eigsh(W, k=k, M=M, sigma=-0.01, which="LM")
        shapes.append((lam, phi, W))
    tm["operators + eigsh"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    times = np.logspace(-3, np.log10(2.0), n_times)
    feats = []
    hks_ = []
    for (lam, phi, W), V in zip(shapes, (V1, V2), strict=True):
        h = (phi**2) @ np.exp(-np.outer(lam, times)) * times
        sig = (phi**2) @ np.exp(-0.05 * lam)
        A = (W != 0).astype(float)
        A2 = ((A @ A) != 0)
        A2.setdiag(False)
        A2 = A2.tocoo()
        loser = np.zeros(len(V), bool)
        loser[A2.row[sig[A2.col] > sig[A2.row]]] = True
        f = np.flatnonzero(~loser)
        feats.append(f[np.argsort(-sig[f])][:50])
        hks_.append(h)
    tm["HKS + features"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    (l1, p1, _), (l2, p2, _) = shapes
    p = feats[0][0]
    D1 = np.hstack([(p1 * p1[p]) @ np.exp(-np.outer(l1, times)) * times, hks_[0]])
    scores = []
    for q in feats[1]:
        D2 = np.hstack([(p2 * p2[q]) @ np.exp(-np.outer(l2, times)) * times, hks_[1]])
        d, _ = cKDTree(D2).query(D1, p=np.inf)
        scores.append(np.mean(d**2))
    q = feats[1][int(np.argmin(scores))]
    tm["score all candidates"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    D2 = np.hstack([(p2 * p2[q]) @ np.exp(-np.outer(l2, times)) * times, hks_[1]])
    _, fmap = cKDTree(D2).query(D1, p=np.inf)
    tm["dense map"] = time.perf_counter() - t0
    tm["total"] = sum(tm.values())
    return fmap, tm


def permuted_copy(mesh: Mesh, seed: int = 1) -> tuple[Mesh, np.ndarray]:
    """A randomly permuted, rigidly moved copy; returns it and gt (source i -> target gt[i])."""
    V, F = mesh.numpy()
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(V))  # new vertex j is old perm[j]
    inv = np.argsort(perm)
    Q, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    return Mesh(V[perm] @ Q.T + 1.0, inv[F], name=mesh.name + "-permuted"), inv


def bench_match(args) -> None:
    import shutil
    import subprocess
    import tempfile

    from torchheat.matching import dense_map, landmark_scores, prepare

    if args.threads:
        torch.set_num_threads(args.threads)
    print(f"# machine: {machine()}")
    cases = []
    gen = generic_mesh()
    gen2, gt = permuted_copy(gen)
    cases.append(("bumpy ellipsoid 10k vs permuted+rotated copy", gen, gen2, gt))
    if args.source and args.target:
        S, T = load_mesh(args.source), load_mesh(args.target)
        cases.append((f"{Path(args.source).name} -> {Path(args.target).name}", S, T,
                      np.arange(S.n_vertices) if S.n_vertices == T.n_vertices else None))
    for title, S, T, gt in cases:
        print(f"\n## {title}: {S.n_vertices} / {T.n_vertices} vertices")
        rows = []
        t0 = time.perf_counter()
        ps = prepare(S)
        pt = prepare(T)
        t_prep = time.perf_counter() - t0
        rows.append(("prepare both (operators, eigenbasis k=100, HKS, features)",
                     f"{t_prep:.3f}"))
        p = int(ps.features[0])
        pt.hk = pt.hk.with_times(ps.hk.times)
        for eng in ("kdtree", "cdist"):
            t0 = time.perf_counter()
            sc = landmark_scores(ps, pt, p, pt.features, engine=eng)
            rows.append((f"score all {pt.features.numel()} candidates, engine={eng}",
                         f"{time.perf_counter() - t0:.3f}"))
        q = int(pt.features[int(torch.argmin(sc))])
        t0 = time.perf_counter()
        fmap, _ = dense_map(ps, pt, [(p, q)])
        rows.append(("dense map (one landmark, kdtree)", f"{time.perf_counter() - t0:.3f}"))
        t0 = time.perf_counter()
        torchheat.match(ps, pt, method="paper", landmarks=2)
        rows.append(("paper pipeline with greedy 2nd landmark, end to end (prepared)",
                     f"{time.perf_counter() - t0:.3f}"))
        t0 = time.perf_counter()
        c = torchheat.match(ps, pt)
        rows.append(("default pipeline (refine), end to end (prepared)",
                     f"{time.perf_counter() - t0:.3f}"))
        t0 = time.perf_counter()
        c = torchheat.match(S, T)
        t_lib = time.perf_counter() - t0
        rows.append(("torchheat.match(mesh, mesh) default, end to end", f"{t_lib:.3f}"))
        exe = shutil.which("torchheat") or str(Path(sys.executable).parent / "torchheat")
        t_cli = None
        if Path(exe).exists():
            with tempfile.TemporaryDirectory() as d:
                fs, ft = Path(d) / "s.off", Path(d) / "t.off"
                import trimesh

                for m, f in ((S, fs), (T, ft)):
                    trimesh.Trimesh(*m.numpy(), process=False).export(f)
                t_proc = {}
                for meth in ("paper", "refine"):
                    t0 = time.perf_counter()
                    subprocess.run([exe, "match", str(fs), str(ft), "-o", str(Path(d) / "m.txt"),
                                    "--method", meth], check=True, capture_output=True)
                    t_proc[meth] = time.perf_counter() - t0
                t0 = time.perf_counter()
                subprocess.run([sys.executable, "-c", "import torchheat.matching"], check=True)
                t_import = time.perf_counter() - t0
                t_cli = t_proc["refine"]
            rows.append(("`python -c 'import torchheat.matching'` (interpreter start, torch "
                         "and torchheat imports, exit)", f"{t_import:.3f}"))
            rows.append(("`torchheat match --method paper` whole process (incl. imports, I/O)",
                         f"{t_proc['paper']:.3f}"))
            rows.append(("`torchheat match` (default) whole process (incl. imports, I/O)",
                         f"{t_cli:.3f}"))
        Vs, Fs = S.numpy()
        Vt, Ft = T.numpy()
        fref, tm = scipy_reference_match(Vs, Fs, Vt, Ft)
        for k_, v in tm.items():
            rows.append((f"scipy reference (k=300 + cKDTree): {k_}", f"{v:.3f}"))
        ref_total = tm["total"]
        rows.append(("speed-up of torchheat.match vs scipy reference",
                     f"{ref_total / t_lib:.1f}x"))
        if t_cli:
            rows.append(("speed-up of `torchheat match` process vs scipy reference: "
                         "paper / default", f"{ref_total / t_proc['paper']:.1f}x / "
                         f"{ref_total / t_cli:.1f}x"))
        if gt is not None:
            ok = float((c.map.numpy() == gt).mean())
            ok_ref = float((fref == gt).mean())
            rows.append(("exact vertices: torchheat default / scipy reference",
                         f"{ok:.3f} / {ok_ref:.3f}"))
        print(table(rows, ("stage", "seconds")))


def energy_and_gradient(terms: tuple, shape: tuple[int, int]):
    """The functional-map energy of ``fmap._solve_quadratic``'s arguments and its analytic
    gradient, for scipy's L-BFGS-B (pyFM's way). With a ``gram`` (7th term) the descriptor
    term is the weighted one, up to its constant."""
    coef, A, B, mask, (Dm, Dn), (Om, On), *rest = terms
    G = rest[0] if rest else None

    def f_and_g(x):
        X = x.reshape(shape)
        r2, r3 = X @ Dn - Dm @ X, X @ On - Om @ X
        if G is None:
            r1 = X @ B - A
            e0, g0 = (r1**2).sum(), r1 @ B.T
        else:
            XB = X @ B
            e0, g0 = (XB * (G @ XB)).sum() - 2 * (XB * A).sum(), (G @ XB - A) @ B.T
        e = coef[0] * e0 + coef[1] * (mask * X * X).sum() + coef[2] * (
            r2**2).sum() + coef[3] * (r3**2).sum()
        g = 2 * (coef[0] * g0 + coef[1] * mask * X + coef[2] * (
            np.einsum("qij,qkj->ik", r2, Dn) - np.einsum("qji,qjk->ik", Dm, r2))
            + coef[3] * (np.einsum("qij,qkj->ik", r3, On) - np.einsum("qji,qjk->ik", Om, r3)))
        return float(e), g.ravel()

    return f_and_g


def exact_and_lbfgs(terms: tuple) -> tuple:
    """Solve the energy exactly (torchheat) and by scipy's L-BFGS-B from ``C = e_0 e_0^T``
    (pyFM's tolerances): ``(C, seconds, x_lbfgs, energy_lbfgs, info, seconds)``."""
    from scipy.optimize import fmin_l_bfgs_b

    from torchheat.matching import fmap

    t0 = time.perf_counter()
    C = fmap._solve_quadratic(*terms)
    t1 = time.perf_counter()
    x0 = np.zeros(C.size)
    x0[0] = 1.0
    t2 = time.perf_counter()
    x, fv, info = fmin_l_bfgs_b(energy_and_gradient(terms, C.shape), x0, factr=1e7, pgtol=1e-5)
    return C, t1 - t0, x, fv, info, time.perf_counter() - t2


def bench_fmap(args) -> None:
    """The descriptor functional map: torchheat's exact quadratic solve against the scipy
    baseline pyFM uses (L-BFGS-B on the same energy, analytic gradient), same terms."""

    from torchheat.matching import fmap

    if args.source and args.target:
        s_mesh, t_mesh = load_mesh(args.source), load_mesh(args.target)
    else:
        s_mesh = generic_mesh()
        t_mesh, _ = permuted_copy(s_mesh)
    if args.threads:
        torch.set_num_threads(args.threads)
    s, t = torchheat.prepare(s_mesh, k=100), torchheat.prepare(t_mesh, k=100)
    t0 = time.perf_counter()
    fmap.shape_operators(s, args.k, 50)
    t1 = time.perf_counter()
    fmap.shape_operators(t, args.k, 50)
    terms = fmap._terms(s, t, args.k, 50, (1.0, 0.1, 1.0, 1.0))
    C, t_exact, x, fv, info, t_lbfgs = exact_and_lbfgs(terms)
    e_exact = fmap._energy(C, *terms)
    rows = [(f"per-shape operators (n = {s.n}, k = {args.k}, 50 WKS), once per shape",
             f"{t1 - t0:.3f}"),
            (f"torchheat: exact solve ({C.size} unknowns), energy {e_exact:.6g}",
             f"{t_exact:.3f}"),
            (f"scipy L-BFGS-B, pyFM's tolerances ({info['nit']} iterations), energy {fv:.6g}",
             f"{t_lbfgs:.3f}"),
            ("max |C_exact - C_lbfgs|", f"{np.abs(x.reshape(C.shape) - C).max():.3g}")]
    print(f"machine: {machine()}")
    print(table(rows, ("descriptor functional map", "seconds")))


def bench_partial(args) -> None:
    """The landmark-free partial functional map (a piece into its whole): torchheat's exact
    solve of the weighted rectangular energy against scipy's L-BFGS-B on the same energy
    (analytic gradient, pyFM's tolerances), same terms."""

    from torchheat.matching import partial

    if args.source and args.target:
        s_mesh, t_mesh = load_mesh(args.source), load_mesh(args.target)
    else:  # the front 60 % of the generic mesh into the whole
        t_mesh = generic_mesh()
        V, F = t_mesh.numpy()
        c = np.quantile(V[:, 0], 0.6)
        s_mesh = Mesh(V, F[(V[F, 0] <= c).all(axis=1)], largest_component=True)
    if args.threads:
        torch.set_num_threads(args.threads)
    s, t = torchheat.prepare(s_mesh, k=100), torchheat.prepare(t_mesh, k=100)
    r = partial.area_ratio(s_mesh, t_mesh)
    t0 = time.perf_counter()
    terms = partial._partial_terms(s, t, r, partial.PARTIAL_DESCR_K, 50, (1.0, 0.1, 1.0, 1.0),
                                   partial.PARTIAL_DESCR_RAMP, None)
    t1 = time.perf_counter()
    C, t_exact, x, fv, info, t_lbfgs = exact_and_lbfgs(terms)
    e_exact = energy_and_gradient(terms, C.shape)(C.ravel())[0]
    rows = [(f"terms: WKS, operators of both shapes (piece n = {s.n}, whole n = {t.n}, "
             f"r = {r:.2f})", f"{t1 - t0:.3f}"),
            (f"torchheat: exact solve ({C.shape[0]} x {C.shape[1]} map), energy {e_exact:.6g} "
             "(+ a constant)", f"{t_exact:.3f}"),
            (f"scipy L-BFGS-B, pyFM's tolerances ({info['nit']} iterations), energy {fv:.6g}",
             f"{t_lbfgs:.3f}"),
            ("max |C_exact - C_lbfgs|", f"{np.abs(x.reshape(C.shape) - C).max():.3g}")]
    print(f"machine: {machine()}")
    print(table(rows, ("partial functional map", "seconds")))


def bench_fine(args) -> None:
    """``match(fine_k=K)``'s stages on one pair, and its dense search against the nearest-
    neighbour searches a user would otherwise write (scipy's k-d tree, as pyFM's ``p2p``; a
    float64 brute force), on the same functional map: times and agreement with the float64
    brute force."""
    from scipy.spatial import cKDTree

    from torchheat.matching.nn import (
        _argmin_certified,
        _blocked_argmin,
        _Factors,
        _nn_factors_pruned,
    )
    from torchheat.matching.prepared import _basis, _cluster_centres
    from torchheat.matching.zoomout import CERTIFIED_MAX_PAIRS, fine_map

    if args.source and args.target:
        s_mesh, t_mesh = load_mesh(args.source), load_mesh(args.target)
    else:
        s_mesh = generic_mesh()
        t_mesh = permuted_copy(s_mesh)[0]
    torch.set_num_threads(args.threads)
    s, t = torchheat.prepare(s_mesh), torchheat.prepare(t_mesh)
    corr = torchheat.match(s, t)
    t0 = time.perf_counter()
    _basis(s, args.k), _basis(t, args.k)
    t_eig = time.perf_counter() - t0
    # the chosen map's functional map at the heat kernel's size (of its dense map)
    a = s.hk.vertex_mass
    C0 = s.hk.eigenvectors.T @ (a[:, None] * t.hk.eigenvectors[corr.map])
    t0 = time.perf_counter()
    images, C = fine_map(s, t, C0, args.k)
    t_fine = time.perf_counter() - t0
    X = _basis(s, C.shape[0])
    Y = _basis(t, C.shape[0]) @ C.T
    # the same bases solved whole (the code before the fortieth session; what a user calling
    # eigsh for K modes gets): eigenvalues compared with the extensions of the held ones
    from torchheat.eigen import eigenpairs

    t0 = time.perf_counter()
    whole = [eigenpairs(*shape.hk.laplacian.reduced(), args.k)[0] for shape in (s, t)]
    t_whole = time.perf_counter() - t0
    ext = [shape.hk.eigenpairs(args.k)[0].numpy() for shape in (s, t)]
    gap = max(float(np.abs(a - b).max() / b[-1]) for a, b in zip(ext, whole, strict=True))
    rows = [(f"eigensolves of {args.k} modes, both shapes (n = {s.n}, m = {t.n}): the held "
             f"{s.hk.k} kept, the rest solved", f"{t_eig:.3f}", ""),
            (f"  all {args.k} solved again (ARPACK shift-invert); eigenvalues apart (rel.)",
             f"{t_whole:.3f}", f"{gap:.1e}")]
    rows.append((f"fine_map {C0.shape[0]} -> {C.shape[0]} modes (ZoomOut + dense map)",
                 f"{t_fine:.3f}", ""))
    t0 = time.perf_counter()
    ref = _blocked_argmin(X, Y, (X * X).sum(1), (Y * Y).sum(1), 256 * 2**20)[1]
    t_ref = time.perf_counter() - t0
    t0 = time.perf_counter()
    cert = _argmin_certified(X, Y)
    t_cert = time.perf_counter() - t0
    t0 = time.perf_counter()
    kd = torch.from_numpy(cKDTree(Y.numpy()).query(X.numpy(), workers=args.threads)[1])
    t_kd = time.perf_counter() - t0
    # the dense map's exact pruned search (large meshes), on the same map and bases
    centres = _cluster_centres(t)
    t0 = time.perf_counter()
    pr = _nn_factors_pruned(_Factors(X, torch.eye(X.shape[1], dtype=X.dtype)), None,
                            _Factors(_basis(t, C.shape[0]), C.T), centres)[1]
    t_pr = time.perf_counter() - t0
    k = C.shape[0]
    for name, tt, got in (
            (f"dense map in {k} modes: torchheat, float32 certified exact (up to "
             f"{CERTIFIED_MAX_PAIRS / 1e6:.0f}M pairs)", t_cert, cert),
            ("  torchheat, float64 cluster-pruned (the dense map's search beyond)", t_pr, pr),
            ("  torch float64 brute force (reference)", t_ref, ref),
            ("  scipy cKDTree(Y).query(X) (as pyFM's p2p)", t_kd, kd)):
        rows.append((name, f"{tt:.3f}", f"{float((got == ref).double().mean()):.4f}"))
    print(f"machine: {machine()}")
    print(table(rows, ("fine maps", "seconds", "same as float64 (or apart)")))


def _gt_disagreement_loop(F, n, gt_src, gt_tgt, rows, field, sqrt_area):
    """The baseline a user would write for ``evaluate.gt_disagreement``: a Python loop over
    the checked rows, their 1-ring neighbours and the neighbours' rows (torchheat's code up
    to the twenty-fifth session)."""
    import scipy.sparse as sp

    E = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    A = sp.coo_matrix((np.ones(len(E)), (E[:, 0], E[:, 1])), shape=(n, n)).tocsr()
    A = ((A + A.T) > 0).tocsr()
    order = np.argsort(gt_src, kind="stable")
    starts = np.searchsorted(gt_src[order], np.arange(n + 1))
    out = np.full(len(rows), np.nan)
    by_source: dict[int, list[int]] = {}
    for i, k in enumerate(rows.tolist()):
        by_source.setdefault(int(gt_tgt[k]), []).append(i)
    for s, idx in by_source.items():
        d = np.asarray(field(s))
        for i in idx:
            x = gt_src[rows[i]]
            best = [d[gt_tgt[order[starts[v]:starts[v + 1]]]].min()
                    for v in A.indices[A.indptr[x]:A.indptr[x + 1]].tolist()
                    if starts[v + 1] > starts[v]]
            if best:
                out[i] = float(np.median(best)) / sqrt_area
    return out


def bench_gtcheck(args) -> None:
    """``evaluate.gt_disagreement`` on every ground-truth row of TOSCA pairs against the plain
    loop, on the same (precomputed) geodesic fields: times and equality."""
    from torchheat.datasets import tosca_remeshed_5k
    from torchheat.evaluate import GeodesicSolver, _gt_disagreement

    pairs = [p.split(":") for p in args.pairs.split(",")]
    data = tosca_remeshed_5k(pairs=pairs, root=args.root)
    rows = []
    for i in range(len(data)):
        pair = data[i]
        Vs, Fs = pair.source.mesh.numpy()
        gs, gt = np.asarray(pair.gt_src), np.asarray(pair.gt_tgt)
        solver = GeodesicSolver(pair.target.mesh)
        fields = {int(s): solver.distances(np.array([s]))[0] for s in np.unique(gt)}
        sa = float(np.sqrt(solver.area))
        F = np.asarray(Fs, dtype=np.int64)
        every = np.arange(len(gs))
        got = {}
        for name, fn in (("torchheat", _gt_disagreement), ("loop", _gt_disagreement_loop)):
            best = float("inf")
            for _ in range(args.repeat):
                t0 = time.perf_counter()
                got[name] = fn(F, len(Vs), gs, gt, every, fields.__getitem__, sa)
                best = min(best, time.perf_counter() - t0)
            got[name + "_s"] = best
        same = np.array_equal(got["torchheat"], got["loop"], equal_nan=True)
        rows.append((pair.name, len(gs), f"{got['torchheat_s']:.4f}", f"{got['loop_s']:.4f}",
                     f"{got['loop_s'] / got['torchheat_s']:.1f}x", "yes" if same else "NO"))
    print(f"machine: {machine()}")
    print(table(rows, ("pair", "rows", "torchheat s", "loop s", "speed-up", "identical")))


_WORKERS_SNIPPET = """
import sys, time
t0 = time.perf_counter()
from torchheat.eigen import EigenWorkers
from torchheat.meshio import read_arrays
arrays = [read_arrays(p) for p in sys.argv[3:]]
t1 = time.perf_counter()
with EigenWorkers(arrays, k=100, processes=int(sys.argv[1]), nice=int(sys.argv[2])) as bg:
    import torch  # what the command line does while its workers solve
    got = [bg.get(i) for i in range(len(arrays))]
assert all(g is not None for g in got) or int(sys.argv[1]) == 0
print(time.perf_counter() - t1)
"""


def bench_threads(args) -> None:
    """What two torch threads buy ``match``: its ZoomOut candidates one after the other on
    one thread, one after the other with each GEMM split over the threads (before the
    twenty-eighth session), and side by side on one thread each (``background.run_each``,
    since); and the command line's eigensolve workers while the parent imports torch, at the
    parent's priority and at nice 10, against solving in the process after the import (the
    code a user would write: ``--workers 0``). Each worker setting runs in a fresh
    interpreter (``import torch`` is timed once per process)."""
    import os
    import subprocess

    from torchheat.heat import blas_threads, threads
    from torchheat.matching.background import run_each
    from torchheat.matching.prepared import _fps
    from torchheat.matching.zoomout import zoomout

    if args.source and args.target:
        s_mesh, t_mesh = load_mesh(args.source), load_mesh(args.target)
        paths = [args.source, args.target]
    else:
        s_mesh = generic_mesh()
        t_mesh = permuted_copy(s_mesh)[0]
        paths = []
    s, t = torchheat.prepare(s_mesh), torchheat.prepare(t_mesh)
    corr = torchheat.match(s, t)
    phi_s, phi_t = s.hk.eigenvectors, t.hk.eigenvectors
    rows, targets = _fps(s, 500), _fps(t, 2000)
    seed_rows = rows[:48]
    g = torch.Generator().manual_seed(0)
    seeds = []
    for i in range(args.candidates):  # the chosen map's sample images, i of them moved
        im = corr.map[seed_rows].clone()
        moved = torch.randperm(48, generator=g)[:i]
        im[moved] = targets[torch.randint(0, targets.numel(), (moved.numel(),), generator=g)]
        seeds.append(im)

    def one(im):
        return zoomout(phi_s, phi_t, seed_rows, im, rows, k_start=16, k_end=100, step=8,
                       targets=targets)

    out_rows = []
    with blas_threads(1):
        with threads(1):
            t0 = time.perf_counter()
            ref = [one(im) for im in seeds]
            t_one = time.perf_counter() - t0
        with threads(2):
            t0 = time.perf_counter()
            split = [one(im) for im in seeds]
            t_split = time.perf_counter() - t0
            got: dict[int, object] = {}
            t0 = time.perf_counter()
            run_each([lambda i=i, im=im: got.__setitem__(i, one(im))
                      for i, im in enumerate(seeds)], 2)
            t_side = time.perf_counter() - t0
    side = [got[i] for i in range(len(seeds))]

    def same(res) -> str:
        n = sum(a.residual == b.residual and torch.equal(a.images, b.images)
                for a, b in zip(ref, res, strict=True))
        return f"{n}/{len(ref)}"

    name = f"{args.candidates} ZoomOuts (500 rows, 2000 targets, 16 -> 100 modes)"
    out_rows.append((f"{name}: one thread", f"{t_one:.3f}", same(ref)))
    out_rows.append(("  two threads, each GEMM split over them", f"{t_split:.3f}", same(split)))
    out_rows.append(("  two threads, side by side on one thread each (run_each)", f"{t_side:.3f}",
                     same(side)))
    if not paths:  # the workers read files: write the pair (vertex order kept)
        import tempfile

        import trimesh

        tmp = Path(tempfile.mkdtemp())
        for m, nm in ((s_mesh, "a.off"), (t_mesh, "b.off")):
            trimesh.Trimesh(*m.numpy(), process=False).export(tmp / nm)
            paths.append(str(tmp / nm))
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1])
    for w, nice, what in ((0, 0, "in the process, after import torch (--workers 0)"),
                          (2, 0, "2 workers at the parent's priority (before)"),
                          (2, 10, "2 workers at nice 10 (since)"),
                          (1, 10, "1 worker, both meshes, at nice 10")):
        times = []
        for _ in range(args.repeat):
            if w == 0:
                code = ("import sys, time; t0 = time.perf_counter(); import torch; "
                        "from torchheat.eigen import cotan_eigenpairs; "
                        "from torchheat.meshio import read_arrays; "
                        "[cotan_eigenpairs(*read_arrays(p), 100) for p in sys.argv[3:]]; "
                        "print(time.perf_counter() - t0)")
            else:
                code = _WORKERS_SNIPPET
            res = subprocess.run([sys.executable, "-c", code, str(w), str(nice), *paths],
                                 env=env, capture_output=True, text=True, check=True)
            times.append(float(res.stdout.split()[-1]))
        out_rows.append((f"import torch and both eigensolves: {what}",
                         f"{min(times):.3f}-{max(times):.3f}", ""))
    print(f"machine: {machine()}; pair: {s.n} / {t.n} vertices")
    print(table(out_rows, ("stage", "seconds", "same bits as one thread")))


def _pair_args(sub_parser: argparse.ArgumentParser,
               source: str = "source mesh (default: the generic mesh)",
               target: str = "target mesh (default: a permuted copy)") -> None:
    """A sub-command's ``--source`` / ``--target`` mesh files."""
    sub_parser.add_argument("--source", help=source)
    sub_parser.add_argument("--target", help=target)


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
    m = sub.add_parser("match", help="matching stages: torchheat vs a plain scipy pipeline")
    _pair_args(m, "source mesh (adds a real pair to the generic one)", "target mesh")
    m.add_argument("--threads", type=int, default=None)
    f = sub.add_parser("fmap", help="descriptor functional map: exact solve vs scipy L-BFGS-B")
    _pair_args(f)
    f.add_argument("--k", type=int, default=30)
    f.add_argument("--threads", type=int, default=1)
    q = sub.add_parser("partial", help="partial functional map: exact solve vs scipy L-BFGS-B")
    _pair_args(q, "the piece (default: 60 %% of the generic mesh)",
               "the whole (default: the generic mesh)")
    q.add_argument("--threads", type=int, default=1)
    fi = sub.add_parser("fine", help="fine maps (match(fine_k=K)): stages, dense search vs "
                                     "scipy's k-d tree")
    _pair_args(fi)
    fi.add_argument("--k", type=int, default=200)
    fi.add_argument("--threads", type=int, default=1)
    g = sub.add_parser("gtcheck", help="ground-truth disagreement: vectorised vs a Python loop")
    g.add_argument("--pairs", default="victoria17:victoria2,cat0:cat1,michael11:michael2",
                   help="TOSCA remeshed 5k pairs, source:target,...")
    g.add_argument("--root", help="data root (default: $TORCHHEAT_DATA or ../shared/data)")
    g.add_argument("--repeat", type=int, default=3)
    th = sub.add_parser("threads", help="two torch threads: ZoomOut candidates side by side; "
                                        "eigensolve workers during import torch")
    _pair_args(th)
    th.add_argument("--candidates", type=int, default=16)
    th.add_argument("--repeat", type=int, default=3)
    args = p.parse_args(argv)
    if args.cmd == "threads":
        bench_threads(args)
        return
    if args.cmd == "gtcheck":
        bench_gtcheck(args)
        return
    if args.cmd == "fine":
        bench_fine(args)
        return
    if args.cmd == "heat":
        bench_heat(args)
    elif args.cmd == "fmap":
        bench_fmap(args)
    elif args.cmd == "partial":
        bench_partial(args)
    else:
        bench_match(args)


if __name__ == "__main__":
    main()
