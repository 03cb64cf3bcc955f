"""The robust pipeline written the way a researcher would without this library: NumPy and
SciPy, one trial at a time, no compilation. It is the yardstick of ``speed.py`` and
follows ``jaxnrsfm`` step for step on complete tracks (``method="wang"``):

1. rank-4 SVD; rejection passes at ranks 4, 6, ..., 3k+1 with Cauchy weights and a
   falling threshold, each a weighted alternating least-squares fit to rtol 1e-4 (batched
   ``numpy.linalg.solve`` over the columns and rows, QR to keep ``M`` orthonormal);
2. the inliers by the residual model (a Student-t / uniform mixture fitted by EM for
   each degree of freedom, the scale floored at the tracks' precision), per-frame x
   per-point weights, anchored outliers, a final weighted fit;
3. the translation split, the rotation triple by Gauss-Newton from eight starts
   (``scipy.optimize.least_squares``, Levenberg-Marquardt), all triples and weights
   from the ``9k x 9k`` eigenproblem, the dominant combination, the shapes with each
   frame's reflection sign from a rigid fit of the back-projected tracks.

Left out: the canonical gauge of the output (a rotation of the world frame and a sign
per basis, free of cost and of effect on ``W_hat`` or e3D). Neither side pays for the
library's Newton polish of the final fit (``jaxnrsfm.implicit.attach``): it runs only
where a result is differentiated.
"""

import numpy as np
from scipy.optimize import least_squares
from scipy.special import expit

RAYLEIGH_MEDIAN = np.sqrt(2 * np.log(2.0))


def entry_errors(W, fit):
    d = (W - fit).reshape(-1, 2, W.shape[1])
    return np.sqrt((d**2).sum(axis=1))


def robust_scale(errors, mask, floor):
    return max(np.median(errors[mask]) / RAYLEIGH_MEDIAN, floor)


def log_inlier_density(a, sigma, nu):
    z = (a / sigma) ** 2
    tail = -z / 2 if np.isinf(nu) else -(nu + 2) / 2 * np.log1p(z / nu)
    return np.log(np.maximum(a, 1e-300)) - 2 * np.log(sigma) + tail


def residual_threshold(errors, visible, floor, nus=(3, 4, 6, 10, 20, 50, np.inf), steps=10000):
    """The residual model of ``jaxnrsfm.residuals``: per nu, EM on (eps, sigma) to its limit
    (a step that moves them by less than sqrt(eps) relative; the library adds Newton steps,
    which the cube does not need); the nu of highest likelihood; the boundary where the
    inlier component stops being the likelier."""
    a = errors[visible]
    A = max(a.max(), floor)
    sigma0 = robust_scale(errors, visible, floor)
    eps0 = np.clip(np.mean(a > 6 * sigma0), 1e-3, 0.5)
    best = None
    for nu in nus:
        sigma, eps = sigma0, eps0
        for _ in range(steps):
            log_in = np.log1p(-eps) + log_inlier_density(a, sigma, nu)
            log_out = np.log(eps) - np.log(A)
            r = expit(log_in - log_out)
            u = 1.0 if np.isinf(nu) else (nu + 2) / (nu + (a / sigma) ** 2)
            new = max(np.sqrt(np.sum(r * u * a**2) / max(2 * r.sum(), 1.0)), floor), np.clip(1 - r.mean(), 1e-6, 0.5)
            if np.allclose(new, (sigma, eps), rtol=np.sqrt(np.finfo(float).eps), atol=0):
                break
            sigma, eps = new
        ll = np.sum(np.logaddexp(log_in, log_out))
        if best is None or ll > best[0]:
            best = (ll, sigma, eps, nu)
    _, sigma, eps, nu = best
    mode = sigma * (1.0 if np.isinf(nu) else np.sqrt(nu / (nu + 1)))
    target = np.log(eps) - np.log(A) - np.log1p(-eps)
    lo, hi = mode, 2 * max(A, mode)
    for _ in range(60):
        mid = np.sqrt(lo * hi)
        lo, hi = (mid, hi) if log_inlier_density(mid, sigma, nu) >= target else (lo, mid)
    return max(lo, 3.0 * sigma), sigma


def svd_factors(A, rank):
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    root = np.sqrt(s[:rank])
    return U[:, :rank] * root, root[:, None] * Vt[:rank]


def _solve(G, rhs):
    r = G.shape[-1]
    ridge = 1e-12 * np.trace(G, axis1=1, axis2=2)[:, None, None] / r + np.finfo(float).tiny
    return np.linalg.solve(G + ridge * np.eye(r), rhs[..., None])[..., 0]


def masked_als(W, weights, M, max_steps=500, rtol=1e-10):
    # jaxnrsfm.factorize.masked_als: each sweep's new M extrapolated along its change and
    # kept if its fit costs less than the last iterate's, else the plain sweep.
    mask = np.repeat(weights, 2, axis=0)
    floor = np.finfo(float).eps ** 2 * np.sum(mask * W**2)

    def structure(M):
        return _solve(np.einsum("ij,ia,ib->jab", mask, M, M, optimize=True), np.einsum("ij,ia,ij->ja", mask, M, W)).T

    def motion(S):
        return _solve(np.einsum("ij,aj,bj->iab", mask, S, S, optimize=True), np.einsum("ij,aj,ij->ia", mask, S, W))

    def cost(M, S):
        return np.sum(mask * (W - M @ S) ** 2)

    S, previous, beta = structure(M), np.inf, 1.0
    for step in range(max_steps):
        new = motion(S)
        far = new + (beta if step else 0.0) * (new - M)
        S_far = structure(far)
        c_far = cost(far, S_far)
        if step == 0 or c_far < previous:
            M, S, c = far, S_far, c_far
            beta = min(1.5 * beta, 8.0) if step else beta
        else:
            M, S = new, structure(new)
            c = cost(M, S)
            beta = max(0.5 * beta, 0.25)
        M, R = np.linalg.qr(M)
        S = R @ S
        if c <= floor or previous - c <= rtol * c:
            break
        previous = c
    return M, S


def wang(W, visible, rank, passes=3, pass_rtol=1e-4):
    start = min(4, rank)
    ranks = (*range(start, rank, 2), rank)
    ranks += (rank,) * max(0, passes - len(ranks))
    factors = 4.0 * np.geomspace(3.0, 1.0, len(ranks))
    M, S = svd_factors(W, ranks[0])
    floor = np.sqrt(np.finfo(float).eps) * np.sqrt(np.mean(W[np.repeat(visible, 2, axis=0)] ** 2))
    weights, kept = visible.astype(float), visible
    for r, factor in zip(ranks, factors, strict=True):
        if r > M.shape[1]:  # new directions: the weighted residual's leading singular vectors
            U, s, _ = np.linalg.svd(np.repeat(kept, 2, axis=0) * (W - M @ S), full_matrices=False)
            M = np.concatenate([M, U[:, : r - M.shape[1]] * s[: r - M.shape[1]]], axis=1)
            M, S = masked_als(W, weights, M, rtol=pass_rtol)
        errors = entry_errors(W, M @ S)
        bound = factor * robust_scale(errors, kept, floor)
        kept = visible & (errors <= bound)
        weights = np.where(visible, 1 / (1 + (errors / bound) ** 2), 0.0)
        M, S = masked_als(W, weights, M, rtol=pass_rtol)
    errors = entry_errors(W, M @ S)
    threshold, sigma = residual_threshold(errors, visible, floor)
    inliers = visible & (errors <= threshold)
    e = np.where(inliers, errors, 0.0)
    frame = np.sqrt((e**2).sum(1) / np.maximum(inliers.sum(1), 1))
    point = np.sqrt((e**2).sum(0) / np.maximum(inliers.sum(0), 1))
    overall = np.sum(e**2) / max(inliers.sum(), 1)
    weights = np.where(inliers, np.clip(overall / np.maximum(np.outer(frame, point), 1e-300), 0.1, 10.0), 0.0)
    rms = np.sqrt(np.mean(W[np.repeat(visible, 2, axis=0)] ** 2))
    weights = np.where(visible & ~inliers, 1e-4 * max((sigma / rms) ** 2, np.sqrt(np.finfo(float).eps)), weights)
    M, S = masked_als(W, weights, M)
    return M, S, inliers


def split_translation(M, S):
    v = np.linalg.lstsq(S.T, np.ones(S.shape[1]), rcond=None)[0]
    U = np.linalg.svd(S - S.mean(1, keepdims=True), full_matrices=False)[0][:, : S.shape[0] - 1]
    T = np.concatenate([U.T - np.outer(U.T @ S.mean(1), v), v[None]], axis=0)
    S_t, M_t = T @ S, np.linalg.solve(T.T, M.T).T
    return M_t[:, :-1], S_t[:-1], M_t[:, -1].reshape(-1, 2)


def _rotation_residuals(g, Mn):
    g = g.reshape(-1, 3)
    a, b = Mn[0::2] @ g, Mn[1::2] @ g
    aa, bb, ab = (a * a).sum(1), (b * b).sum(1), (a * b).sum(1)
    return np.concatenate([aa - bb, 2 * ab, [np.sqrt(Mn.shape[0] / 2) * ((aa + bb).mean() / 2 - 1)]])


def polar_rows(A):
    U, _, Vt = np.linalg.svd(A, full_matrices=False)
    return U @ Vt


def rotations_and_trust(Mi, g):
    A = Mi @ g
    R2 = polar_rows(A)
    R = np.concatenate([R2, np.cross(R2[:, 0], R2[:, 1])[:, None]], axis=1)
    scale = (A**2).sum(axis=(1, 2))
    return R, scale / scale.max()


def triples_given_rotations(M, R, k, trust):
    Mi = M.reshape(-1, 2, M.shape[1])
    X = np.einsum("iab,iac->ibc", Mi, R[:, :2]).reshape(len(Mi), -1)
    G = np.kron(np.einsum("i,iab,iac->bc", trust, Mi, Mi), np.eye(3)) - 0.5 * (trust[:, None] * X).T @ X
    vecs = np.linalg.eigh(G)[1][:, :k]
    H = np.concatenate(list(vecs.T.reshape(k, -1, 3)), axis=1)
    return H, 0.5 * X @ vecs


def metric_upgrade(M, S, t, k, starts=8, seed=0):
    mean = S.mean(1)
    S, t = S - mean[:, None], t + (M @ mean).reshape(-1, 2)
    Mi = M.reshape(-1, 2, M.shape[1])
    Mn = M / np.sqrt(np.mean(M**2))
    rng = np.random.default_rng(seed)
    fits = [
        least_squares(_rotation_residuals, rng.standard_normal(3 * M.shape[1]), args=(Mn,), method="lm")
        for _ in range(starts)
    ]
    g = min(fits, key=lambda f: f.cost).x.reshape(-1, 3)
    R, trust = rotations_and_trust(Mi, g)
    H, w = triples_given_rotations(M, R, k, trust)
    c = np.linalg.svd(w, full_matrices=False)[2][0]
    R, trust = rotations_and_trust(Mi, np.einsum("blc,l->bc", H.reshape(-1, k, 3), c))
    H, w = triples_given_rotations(M, R, k, trust)
    B = np.linalg.solve(H, S).reshape(k, 3, -1)
    shapes = np.einsum("il,lan->ian", w, B)
    return frame_signs(R, Mi @ S)[:, None, None] * shapes, t


def frame_signs(R, tracks, sweeps=20):
    # The signs under which one rigid shape explains the back-projected tracks best.
    P2 = R[:, :2]
    Y = np.einsum("iab,ian->ibn", P2, tracks)
    ev, V = np.linalg.eigh(np.einsum("iab,iac->bc", P2, P2))
    seen = ev > 1e-8 * ev[-1]
    inv_sqrt = np.where(seen, 1.0 / np.sqrt(np.where(seen, ev, 1.0)), 0.0)
    Z = np.einsum("ab,ibn->ian", (V * inv_sqrt) @ V.T, Y).reshape(len(R), -1)
    s = np.where(np.linalg.svd(Z, full_matrices=False)[0][:, 0] < 0, -1.0, 1.0)
    for _ in range(sweeps):
        s = np.where(Z @ (Z.T @ s) < 0, -1.0, 1.0)
    return s


def reconstruct(W, visible, k):
    """The robust pipeline on one complete trial: ``W_hat``, the inliers, the shapes."""
    M, S, inliers = wang(W, visible, 3 * k + 1)
    W_hat = M @ S
    M, S, t = split_translation(M, S)
    shapes, t = metric_upgrade(M, S, t, k)
    return W_hat, inliers, shapes
