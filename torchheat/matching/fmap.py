"""Functional maps from descriptors, with an orientation-preserving term: a map that needs no
landmark, used as one more hypothesis for :mod:`.pipeline`'s ZoomOut choice.

The heat-kernel hypotheses of :mod:`.pipeline` all start from one point; on humans every one of
them can be a half-turn about the body axis (left/right and front/back swapped together, an
orientation-preserving near-isometry) or a clean reflection, and then no choice among them is
right. A functional map fitted to *all* points at once (Ovsjanikov et al., SIGGRAPH 2012) with
the orientation-preserving operators of Ren, Poulenard, Liu, Melzi, Wonka, Ovsjanikov
(*Continuous and Orientation-preserving Correspondences via Functional Maps*, SIGGRAPH Asia
2018) does not depend on a landmark: the descriptor terms tie the map to the wave kernel
signature (Aubry et al. 2011) and the orientation term rejects reflections. ZoomOut refines it
like the other hypotheses, and the pipeline's residual + orientation score decides.

Convention (as in :mod:`.zoomout`): for a point map ``T: M -> N`` the functional map ``C``
(``k x k``) pulls target functions back, ``Phi_M C ~ Phi_N[T]``: target coefficients in, source
coefficients out. The energy, a convex quadratic in ``C``, minimised exactly (its normal
equations; pyFM runs L-BFGS on it, which stops short of the minimum)::

    E(C) = w_d |C B - A|^2 / tau_d                        descriptors preserved
         + w_l sum_ij mask_ij C_ij^2 / tau_l               commutes with the Laplacians
         + w_c sum_q |C D^N_q - D^M_q C|^2 / tau_c          commutes with descriptor products
         + w_o sum_q |C O^N_q - O^M_q C|^2 / tau_o          commutes with orientation operators

``A``, ``B``: descriptors in the bases (``k x p``); ``D_q``: multiplication by descriptor ``q``;
``O_q``: ``g -> <n x grad f_q, grad g>`` (the orientation operator of descriptor ``q``);
``mask``: the resolvent mask of Ren et al. (SGP 2019, bounded in ``k``); ``tau``: each term's
size at a generic map (so the weights are relative), as in pyFM.

Cost (``k = 30``, ``p = 50`` descriptors, one thread): per shape, once (cached on the shape),
the operators, ``O(p F k^2)`` for ``F`` faces: ~0.2 s for 5k vertices, ~0.5 s for 12.5k; per
pair the ``k^2 x k^2`` normal equations, ``O(p k^4 + k^6)``: ~0.1 s.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg
import torch

from ..heat import threads
from .prepared import PreparedShape, _memoised

__all__ = ["wave_kernel_signature", "orientation_operators", "shape_operators",
           "descriptor_operators", "descriptor_functional_map", "landmark_functional_map"]


def wave_kernel_signature(evals: torch.Tensor, evecs: torch.Tensor, energies: np.ndarray,
                          sigma: float, normalize: bool = True) -> torch.Tensor:
    """Wave kernel signature (Aubry, Schlickewei, Cremers 2011), scaled per energy.

    ``WKS(x, e) = sum_i phi_i(x)^2 g_e(lambda_i) / sum_i g_e(lambda_i)`` with ``g_e(lambda) =
    exp(-(e - log lambda)^2 / (2 sigma^2))``; the constant mode (``lambda ~ 0``) is left out.
    ``normalize=False`` drops the denominator: the local density of states, which agrees on a
    piece and on the whole it was cut from (same units) where the denominators do not (the
    piece has fewer eigenvalues in every band).

    Parameters
    ----------
    evals : torch.Tensor, shape (k,)
        Laplace–Beltrami eigenvalues, ascending.
    evecs : torch.Tensor, shape (n, k)
        Mass-orthonormal eigenfunctions.
    energies : numpy.ndarray, shape (E,)
        Log-energies ``e``.
    sigma : float
        Width of the band-pass filters in log-energy.
    normalize : bool
        Divide by ``sum_i g_e(lambda_i)`` (default).

    Returns
    -------
    torch.Tensor, float64, shape (n, E)

    Examples
    --------
    >>> ev = torch.tensor([0.0, 1.0, 4.0], dtype=torch.float64)
    >>> phi = torch.eye(3, dtype=torch.float64)
    >>> w = wave_kernel_signature(ev, phi, np.log([1.0, 4.0]), 0.1)
    >>> [round(float(v), 3) for v in w[1]]  # vertex 1 carries the eigenfunction of 1.0
    [1.0, 0.0]
    """
    lam = evals.detach().to(torch.float64).cpu()
    phi = evecs.detach().to(torch.float64).cpu()
    keep = lam > 1e-8 * lam.abs().max()
    lam, phi = lam[keep], phi[:, keep]
    e = torch.as_tensor(np.asarray(energies, dtype=np.float64))
    g = torch.exp(-(e[:, None] - torch.log(lam)[None, :]) ** 2 / (2 * sigma**2))  # (E, k)
    if not normalize:
        return (phi * phi) @ g.T
    return (phi * phi) @ g.T / g.sum(1).clamp_min(1e-300)[None, :]


def _unit_area(shape: PreparedShape) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices scaled to unit area, faces, vertex masses of the eigenbasis (unit area)."""
    V, F = shape.mesh.numpy()
    V = np.asarray(V, dtype=np.float64) / np.sqrt(shape.mesh.area())
    return V, F, shape.hk.vertex_mass.numpy()


def _face_frames(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unit face normals (F, 3), face areas (F,), hat-function gradients (F, 3 corners, 3)."""
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    cr = np.cross(e1, e2)
    dbl = np.linalg.norm(cr, axis=1)
    n = cr / np.maximum(dbl, 1e-300)[:, None]
    # grad B_c = n x (opposite edge, counter-clockwise) / (2 area)
    opp = np.stack([V[F[:, 2]] - V[F[:, 1]], V[F[:, 0]] - V[F[:, 2]],
                    V[F[:, 1]] - V[F[:, 0]]], axis=1)
    gB = np.cross(n[:, None, :], opp) / np.maximum(dbl, 1e-300)[:, None, None]
    return n, dbl / 2.0, gB


_FACE_CHUNK = 128  # faces per block of orientation_operators (a (128, p, k) block: ~1.5 MB)
# Faces whose gradients orientation_operators builds at once (elementwise, so the same bits
# as chunk by chunk; 4096 x 3 x 100 float64: ~10 MB): 128-face gradient blocks spent a fifth
# of its time in small-tensor overhead (thirty-fourth session, BENCHMARKS.md). A multiple of
# _FACE_CHUNK, so that the products are summed over the same chunks of faces as before.
_GRADIENT_BLOCK = 4096


def orientation_operators(V: np.ndarray, F: np.ndarray, phi: np.ndarray, descr: np.ndarray
                          ) -> np.ndarray:
    """The orientation operators ``g -> <n x grad f_q, grad g>`` of descriptors ``f_q`` in a
    basis: ``O_q[i, j] = int phi_i <n x grad f_q, grad phi_j> dA`` (piecewise-linear
    functions, face-wise gradients, ``phi_i`` averaged over each face).

    Parameters
    ----------
    V : numpy.ndarray, shape (n, 3)
    F : numpy.ndarray, int, shape (m, 3)
    phi : numpy.ndarray, shape (n, k)
        Basis functions.
    descr : numpy.ndarray, shape (n, p)
        Descriptors ``f_q``.

    Returns
    -------
    numpy.ndarray, shape (p, k, k)

    Examples
    --------
    >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]]); F = np.array([[0, 1, 2]])
    >>> x, y = V[:, :1], V[:, 1:2]
    >>> float(orientation_operators(V, F, np.ones((3, 1)), x)[0, 0, 0])  # grad of a constant
    0.0
    >>> float(orientation_operators(V, F, np.hstack([np.ones((3, 1)), y]), x)[0, 0, 1])
    0.5
    """
    n, area, gB = _face_frames(V, F)
    m, k, p = F.shape[0], phi.shape[1], descr.shape[1]
    avg = torch.from_numpy(phi[F].mean(1) * area[:, None])  # (m, k)
    Ft = torch.from_numpy(np.ascontiguousarray(F, dtype=np.int64))
    ph = torch.from_numpy(np.ascontiguousarray(phi, dtype=np.float64))
    de = torch.from_numpy(np.ascontiguousarray(descr, dtype=np.float64))
    gBt, nt = torch.from_numpy(gB), torch.from_numpy(n)
    out = torch.zeros((k, p * k), dtype=torch.float64)
    for A in range(0, m, _GRADIENT_BLOCK):
        B = min(m, A + _GRADIENT_BLOCK)
        f, g = Ft[A:B], gBt[A:B]
        # face-wise gradients of the basis and the descriptors: (block, 3, k), (block, 3, p)
        gp, gd = ((g[:, 0, :, None] * X[f[:, 0]][:, None, :]
                   + g[:, 1, :, None] * X[f[:, 1]][:, None, :]
                   + g[:, 2, :, None] * X[f[:, 2]][:, None, :]) for X in (ph, de))
        # n x grad f_q, component by component (block, p)
        nf = nt[A:B, :, None]
        r0 = nf[:, 1] * gd[:, 2] - nf[:, 2] * gd[:, 1]
        r1 = nf[:, 2] * gd[:, 0] - nf[:, 0] * gd[:, 2]
        r2 = nf[:, 0] * gd[:, 1] - nf[:, 1] * gd[:, 0]
        # w[f] = rot[f] @ grad_phi[f], an inner dimension of 3: three broadcast products
        # (twice as fast as torch.bmm's batch of tiny products; equal to 1e-14), in chunks
        # kept in cache; w is (chunk, p, k)
        for a in range(0, B - A, _FACE_CHUNK):
            b = min(B - A, a + _FACE_CHUNK)
            w = r0[a:b, :, None] * gp[a:b, None, 0, :]
            w.addcmul_(r1[a:b, :, None], gp[a:b, None, 1, :])
            w.addcmul_(r2[a:b, :, None], gp[a:b, None, 2, :])
            out += avg[A + a : A + b].T @ w.reshape(b - a, p * k)
    return out.reshape(k, p, k).permute(1, 0, 2).numpy()


def _resolvent_mask(lam_s: np.ndarray, lam_t: np.ndarray, gamma: float = 0.5) -> np.ndarray:
    """Ren et al. (SGP 2019): ``|R(lambda_i) - R(mu_j)|^2`` with ``R(x) = 1 / (x^gamma - i)``
    on spectra scaled by their common maximum; rows: source, columns: target."""
    scale = max(np.abs(lam_s).max(), np.abs(lam_t).max())
    a, b = (np.abs(lam_s) / scale) ** gamma, (np.abs(lam_t) / scale) ** gamma
    re_a, re_b = a / (a * a + 1), b / (b * b + 1)
    im_a, im_b = 1 / (a * a + 1), 1 / (b * b + 1)
    return (re_a[:, None] - re_b[None, :]) ** 2 + (im_a[:, None] - im_b[None, :]) ** 2


def _effective_p(*red: np.ndarray) -> float:
    vals = []
    for Fm in red:
        G = Fm[1:].T @ Fm[1:]
        den = float((G * G).sum())
        vals.append(float(np.trace(G)) ** 2 / den if den > 0 else 1.0)
    return max(float(np.mean(vals)), 1e-12)


def descriptor_functional_map(src: PreparedShape, tgt: PreparedShape, k: int = 30,
                              n_descr: int = 50, weights: tuple[float, float, float, float] = (
                                  1.0, 0.1, 1.0, 1.0), reversing: bool = False,
                              memo: dict | None = None) -> torch.Tensor:
    """A ``k x k`` functional map of two shapes from their wave kernel signatures, with the
    orientation-preserving term; no landmark (see the module docstring for the energy).

    Parameters
    ----------
    src, tgt : PreparedShape
        Shapes with at least ``k`` eigenpairs (``src.hk.eigenvectors``; more eigenpairs give
        the WKS a finer spectrum).
    k : int
        Size of the map.
    n_descr : int
        WKS energies (log-spaced between the shapes' first and last eigenvalues).
    weights : (w_descr, w_lap, w_dcomm, w_orient)
        Relative weights (pyFM's README pipeline: 1, 0.1, 1, 1).
    reversing : bool
        Ask for an orientation-reversing map instead (``C O_N = -O_M C``): a shape's intrinsic
        symmetry when ``src is tgt``.
    memo : dict, optional
        The caller's memo for this pair of shapes: the energy's Hessians are kept there for
        other maps of the same pair (:func:`landmark_functional_map`).

    Returns
    -------
    torch.Tensor, float64, shape (k, k)
        ``C`` with ``Phi_M C ~ Phi_N[T]`` (see :mod:`.zoomout`); its point map is
        :func:`~torchheat.matching.zoomout.spectral_map`.

    Notes
    -----
    Accuracy: a coarse map (a few percent of the diameter on near-isometric shapes), meant as a
    ZoomOut seed; a shape with an intrinsic symmetry that also preserves orientation (a
    half-turn) gives such maps an ambiguity the energy cannot resolve.

    Examples
    --------
    >>> import trimesh, torchheat
    >>> m = trimesh.creation.icosphere(3)
    >>> s = torchheat.prepare(torchheat.Mesh(m.vertices, m.faces), k=40)
    >>> C = descriptor_functional_map(s, s, k=10)
    >>> tuple(C.shape)
    (10, 10)
    """
    terms = _terms(src, tgt, k, n_descr, weights)
    if reversing:
        (Om, On) = terms[5]
        terms = (*terms[:5], (Om, -On))
    hess = _pair_hessians(memo, (terms[1].shape[0], n_descr, reversing), terms[4], terms[5])
    return torch.from_numpy(_solve_quadratic(*terms, hessians=hess))


#: Times (unit-area shapes) of the heat kernels around the point pairs of
#: :func:`landmark_functional_map`: diffusion lengths ``sqrt(4 t)`` of 0.28-0.63 sqrt(area),
#: longer than a body's thickness (a front/back flip is not encoded) and shorter than its
#: limbs' separation (a left/right swap is)
LANDMARK_TIMES = (0.02, 0.05, 0.1)


def landmark_functional_map(src: PreparedShape, tgt: PreparedShape, src_points: torch.Tensor,
                            tgt_points: torch.Tensor, k: int = 30,
                            times: tuple[float, ...] = LANDMARK_TIMES, n_descr: int = 50,
                            weights: tuple[float, float, float, float] = (1.0, 0.1, 1.0, 1.0),
                            memo: dict | None = None) -> torch.Tensor:
    """An orientation-preserving ``k x k`` functional map that keeps a coarse correspondence.

    The energy of :func:`descriptor_functional_map` (wave kernel signatures, Laplacian and
    descriptor commutativity, the orientation-preserving term) with more descriptors: the heat
    kernels ``k_t(p_i, .)`` of the source points and ``k_t(q_i, .)`` of their images, at
    large times (:data:`LANDMARK_TIMES`). They tie the map to where the point pairs say the
    parts of the shape go, but are too smooth to say which way a part faces; the orientation
    term decides that. A map that is right part by part but reflected (a body mapped front to
    back: orientation-reversing, yet every point lands within a body's thickness of its true
    image) is turned into the direct map; a map with the orientation already right is kept
    and made consistent where it was locally reflected.

    Parameters
    ----------
    src, tgt : PreparedShape
        Shapes with at least ``k`` eigenpairs.
    src_points, tgt_points : torch.Tensor, int64, shape (L,)
        Point pairs ``(p_i, q_i)`` of the coarse correspondence (a few tens, spread out:
        farthest-point samples and their images).
    k : int
        Size of the map.
    times : tuple of float
        Heat-kernel times of the point descriptors (unit area).
    n_descr : int
        WKS energies (see :func:`descriptor_functional_map`).
    weights : (w_descr, w_lap, w_dcomm, w_orient)
        Relative weights of the terms (pyFM's README pipeline: 1, 0.1, 1, 1).
    memo : dict, optional
        The caller's memo for this pair of shapes (see :func:`descriptor_functional_map`):
        the energy's Hessians are computed once for every map of the pair.

    Returns
    -------
    torch.Tensor, float64, shape (k, k)
        ``C`` with ``Phi_M C ~ Phi_N[T]`` (see :mod:`.zoomout`).

    Raises
    ------
    ValueError
        No point pairs, lists of different lengths, or a vertex index outside its shape.

    Notes
    -----
    Cost: that of :func:`descriptor_functional_map` (the shapes' operators are cached) plus
    ``O(L |times| k)`` for the point descriptors: ~0.02 s for ``k = 30`` (one thread) when
    ``memo`` holds the pair's Hessians, ~0.04 s otherwise.

    Examples
    --------
    >>> import trimesh, torchheat
    >>> m = trimesh.creation.icosphere(3)
    >>> s = torchheat.prepare(torchheat.Mesh(m.vertices * [1.0, 0.8, 0.6], m.faces), k=40)
    >>> p = torch.tensor([0, 100, 200, 300, 400, 500])
    >>> C = landmark_functional_map(s, s, p, p, k=10)
    >>> bool(torch.allclose(C, torch.eye(10, dtype=torch.float64), atol=0.05))  # the identity
    True
    """
    sp = torch.as_tensor(src_points, dtype=torch.int64).reshape(-1)
    tp = torch.as_tensor(tgt_points, dtype=torch.int64).reshape(-1)
    if sp.numel() == 0 or sp.numel() != tp.numel():
        raise ValueError(f"landmark_functional_map needs point pairs: {sp.numel()} source and "
                         f"{tp.numel()} target points given")
    for name, pts, n in (("source", sp, src.n), ("target", tp, tgt.n)):
        if int(pts.min()) < 0 or int(pts.max()) >= n:
            raise ValueError(f"{name} point index out of range: {int(pts.min())}.."
                             f"{int(pts.max())} for a shape of {n} vertices")
    lam_s_all = src.hk.eigenvalues.double()
    lam_t_all = tgt.hk.eigenvalues.double()
    k = int(min(k, lam_s_all.numel(), lam_t_all.numel()))
    A_w, Dm, Om = shape_operators(src, k, n_descr)
    B_w, Dn, On = shape_operators(tgt, k, n_descr)
    t = torch.as_tensor(times, dtype=torch.float64)
    phi_s = src.hk.eigenvectors.double()[sp, :k]  # (L, k)
    phi_t = tgt.hk.eigenvectors.double()[tp, :k]
    # coefficients of k_t(p, .) = sum_i exp(-lam_i t) phi_i(p) phi_i(.): (k, L |times|)
    A_h = (phi_s[:, None, :] * torch.exp(-lam_s_all[None, :k] * t[:, None])[None]).reshape(-1, k)
    B_h = (phi_t[:, None, :] * torch.exp(-lam_t_all[None, :k] * t[:, None])[None]).reshape(-1, k)
    norm = A_h.norm(dim=1).clamp_min(1e-300)[:, None]  # each pair at the source's unit norm
    A = np.hstack([A_w, (A_h / norm).T.numpy()])
    B = np.hstack([B_w, (B_h / norm).T.numpy()])
    mask = _resolvent_mask(lam_s_all[:k].numpy(), lam_t_all[:k].numpy())
    coef = _coefficients(A, B, mask, (Dm, Dn), (Om, On), weights)
    hess = _pair_hessians(memo, (k, n_descr, False), (Dm, Dn), (Om, On))
    return torch.from_numpy(_solve_quadratic(coef, A, B, mask, (Dm, Dn), (Om, On),
                                             hessians=hess))


def shape_operators(shape: PreparedShape, k: int, n_descr: int
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One shape's part of the energy: its WKS in the basis, the multiplication and the
    orientation operators of its descriptors; computed once per shape and size (cached on the
    shape: a shape in many pairs pays once).

    The WKS filter bank is the shape's own (``n_descr`` log-energies between its first and
    last non-zero eigenvalue, as pyFM does): it depends on the shape alone, and two
    near-isometric unit-area shapes have nearly the same spectrum.

    Parameters
    ----------
    shape : PreparedShape
    k : int
        Basis size (at most the shape's eigenpairs).
    n_descr : int

    Returns
    -------
    red : numpy.ndarray, shape (k, n_descr)
        The unit-norm descriptors' coefficients.
    mult, orient : numpy.ndarray, shape (n_descr, k, k)
        ``phi_i^T A diag(d_q) phi_j`` and :func:`orientation_operators`.

    Examples
    --------
    >>> import trimesh, torchheat
    >>> m = trimesh.creation.icosphere(3)
    >>> s = torchheat.prepare(torchheat.Mesh(m.vertices, m.faces), k=40)
    >>> [a.shape for a in shape_operators(s, 10, 8)]
    [(10, 8), (8, 10, 10), (8, 10, 10)]
    """
    cache = shape.caches.fmap_operators
    lam = shape.hk.eigenvalues.double().numpy()
    key = (int(k), int(n_descr), lam.size)
    if key in cache:
        return cache[key]
    phi_all = shape.hk.eigenvectors.double()
    pos = lam[lam > 1e-8 * np.abs(lam).max()]
    e_min, e_max = np.log(pos.min()), np.log(pos.max())
    sigma = 7.0 * (e_max - e_min) / max(2 * n_descr, 1)
    energies = np.linspace(e_min + 2 * sigma, e_max - 2 * sigma, n_descr)
    V, F, mass = _unit_area(shape)
    with threads(1):  # the same bits whichever thread fills the cache first (matching.select)
        d = wave_kernel_signature(torch.from_numpy(lam), phi_all, energies, sigma).numpy()
    d = d / np.sqrt((mass[:, None] * d * d).sum(0)).clip(1e-300)[None, :]
    cache[key] = descriptor_operators(V, F, mass, phi_all[:, :k].numpy(), d)
    return cache[key]


def descriptor_operators(V: np.ndarray, F: np.ndarray, mass: np.ndarray, phi: np.ndarray,
                         d: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Descriptors ``d`` in a basis ``phi``: their coefficients, multiplication operators and
    orientation operators (the shape's part of the energy, see :func:`shape_operators`).

    Parameters
    ----------
    V : numpy.ndarray, shape (n, 3)
    F : numpy.ndarray, int, shape (m, 3)
    mass : numpy.ndarray, shape (n,)
        Lumped vertex masses (the basis is mass-orthonormal).
    phi : numpy.ndarray, shape (n, k)
    d : numpy.ndarray, shape (n, p)

    Returns
    -------
    red : numpy.ndarray, shape (k, p)
        ``phi^T A d``.
    mult, orient : numpy.ndarray, shape (p, k, k)
        ``phi_i^T A diag(d_q) phi_j`` and :func:`orientation_operators`.

    Examples
    --------
    >>> V = np.array([[0., 0, 0], [1, 0, 0], [0, 1, 0]]); F = np.array([[0, 1, 2]])
    >>> red, mult, orient = descriptor_operators(V, F, np.ones(3), np.eye(3)[:, :2],
    ...                                          V[:, :1])
    >>> red.ravel().tolist(), mult[0].tolist()
    ([0.0, 1.0], [[0.0, 0.0], [0.0, 1.0]])
    """
    phi = np.ascontiguousarray(phi, dtype=np.float64)
    k = phi.shape[1]
    red = (phi.T * mass[None, :]) @ d  # (k, p): coefficients in the basis
    dm = d * mass[:, None]
    mult = np.empty((d.shape[1], k, k))  # products with d_q: phi_i^T A diag(d_q) phi_j
    for i in range(k):  # k GEMMs with an (n, p) temporary (one (n, k, k) array: 4x slower)
        mult[:, i, :] = (dm * phi[:, i : i + 1]).T @ phi
    return red, mult, orientation_operators(V, F, phi, d)


def _terms(src: PreparedShape, tgt: PreparedShape, k: int, n_descr: int,
           weights: tuple[float, float, float, float]
           ) -> tuple[list[float], np.ndarray, np.ndarray, np.ndarray,
                      tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """Weights and matrices of the energy: ``(coef, A, B, mask, (D_M, D_N), (O_M, O_N))``."""
    lam_s_all = src.hk.eigenvalues.double().numpy()
    lam_t_all = tgt.hk.eigenvalues.double().numpy()
    k = int(min(k, lam_s_all.size, lam_t_all.size))
    A, Dm, Om = shape_operators(src, k, n_descr)
    B, Dn, On = shape_operators(tgt, k, n_descr)
    mask = _resolvent_mask(lam_s_all[:k], lam_t_all[:k])
    coef = _coefficients(A, B, mask, (Dm, Dn), (Om, On), weights)
    return coef, A, B, mask, (Dm, Dn), (Om, On)


def _coefficients(A: np.ndarray, B: np.ndarray, mask: np.ndarray,
                  dcomm: tuple[np.ndarray, np.ndarray], orient: tuple[np.ndarray, np.ndarray],
                  weights: tuple[float, ...]) -> list[float]:
    """``w_i / tau_i``: each term's weight over its size at a generic ``a x b`` map (pyFM's
    normalisation, so that the weights are relative)."""
    a, b = mask.shape
    p_eff = _effective_p(A, B)

    def oplist_tau(o1: np.ndarray, o2: np.ndarray, skew: bool) -> float:
        pos_ = b * (o1 * o1).sum() + a * (o2 * o2).sum()
        tot = pos_ if skew else pos_ - 2 * (np.trace(o1, axis1=1, axis2=2)
                                            * np.trace(o2, axis1=1, axis2=2)).sum()
        return float(tot) * a / (a * a) / p_eff if tot > 1e-12 * pos_ else 1.0

    # (written so that a square map gets the operations of the square-only code, bit for bit)
    tau = (max(a * float((A[1:] ** 2).sum()) / a / p_eff, 1e-300),
           max(a * float(mask.sum()) / (a * a), 1e-300),
           oplist_tau(*dcomm, False), oplist_tau(*orient, True))
    w = np.asarray(weights, dtype=np.float64)
    w = w / w.sum()
    return [float(wi / ti) for wi, ti in zip(w, tau, strict=True)]


def _energy(C: np.ndarray, coef: list[float], A: np.ndarray, B: np.ndarray, mask: np.ndarray,
            dcomm: tuple[np.ndarray, np.ndarray], orient: tuple[np.ndarray, np.ndarray]
            ) -> float:
    """The energy of :func:`descriptor_functional_map` at ``C`` (for tests)."""
    e = coef[0] * ((C @ B - A) ** 2).sum() + coef[1] * (mask * C * C).sum()
    e += coef[2] * ((C @ dcomm[1] - dcomm[0] @ C) ** 2).sum()
    e += coef[3] * ((C @ orient[1] - orient[0] @ C) ** 2).sum()
    return float(e)


def _comm_hessian(Q: np.ndarray, P: np.ndarray) -> np.ndarray:
    """Hessian (``ab x ab``, row-major ``vec`` of an ``a x b`` map) of ``sum_q |C P_q - Q_q C|^2``
    (``Q_q``: ``a x a``, ``P_q``: ``b x b``):
    ``I (x) sum P P^T + sum Q^T Q (x) I - S - S^T``, ``S = sum_q Q_q (x) P_q``."""
    p, a, _ = Q.shape
    b = P.shape[1]
    H = np.kron(np.eye(a), np.einsum("qab,qcb->ac", P, P)) + np.kron(
        np.einsum("qba,qbc->ac", Q, Q), np.eye(b))
    S = (Q.reshape(p, a * a).T @ P.reshape(p, b * b)).reshape(a, a, b, b)  # [i,k,j,l]
    S = S.transpose(0, 2, 1, 3).reshape(a * b, a * b)  # [(i,j),(k,l)] = sum Q[i,k] P[j,l]
    return H - S - S.T


def _pair_hessians(memo: dict | None, key: tuple, dcomm: tuple[np.ndarray, np.ndarray],
                   orient: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The unweighted commutativity Hessians of a pair's operators, memoised in ``memo`` (the
    caller's, one per pair of shapes) under ``key``; ``O(p k^4)`` each (~10 ms at k = 30)."""
    return _memoised(memo, key, lambda: (_comm_hessian(*dcomm), _comm_hessian(*orient)))


def _solve_quadratic(coef: list[float], A: np.ndarray, B: np.ndarray, mask: np.ndarray,
                     dcomm: tuple[np.ndarray, np.ndarray], orient: tuple[np.ndarray, np.ndarray],
                     gram: np.ndarray | None = None,
                     hessians: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """The minimiser of the (convex, quadratic) energy of :func:`descriptor_functional_map`:
    its normal equations, ``ab`` unknowns for an ``a x b`` map, solved by Cholesky (``O(a^3
    b^3)``: ~0.015 s for ``a = b = 30``) instead of by L-BFGS (pyFM), which stops short of it.

    ``gram`` (``a x a``, default the identity) weighs the descriptor term in space:
    ``|C B - A|^2`` becomes ``tr((C B)^T G C B) - 2 tr((C B)^T A)``, i.e. ``sum_x w(x) |Phi_M[x]
    C B - d_M(x)|^2`` with ``G = Phi^T W Phi`` and ``A = Phi^T W d_M`` (``W``: weights times
    masses). ``hessians``: the unweighted Hessians of the two commutativity terms, if already
    computed (:func:`_pair_hessians`)."""
    a = A.shape[0]
    G = np.eye(a) if gram is None else gram
    H = coef[0] * np.kron(G, B @ B.T) + coef[1] * np.diag(mask.ravel())
    if coef[2]:
        H += coef[2] * (_comm_hessian(dcomm[0], dcomm[1]) if hessians is None else hessians[0])
    if coef[3]:
        H += coef[3] * (_comm_hessian(orient[0], orient[1]) if hessians is None
                        else hessians[1])
    g = coef[0] * (A @ B.T).ravel()
    H[np.diag_indices_from(H)] += 1e-12 * np.trace(H) / H.shape[0]  # a null direction
    try:  # symmetric positive definite: Cholesky, half the cost of LU
        return scipy.linalg.cho_solve(scipy.linalg.cho_factor(H, check_finite=False), g,
                                      check_finite=False).reshape(mask.shape)
    except np.linalg.LinAlgError:  # not numerically positive definite
        return np.linalg.solve(H, g).reshape(mask.shape)
