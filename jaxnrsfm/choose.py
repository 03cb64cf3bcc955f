"""Choosing the number of shape bases ``k`` from the tracks alone (never from ground truth).

Rule: register every frame to its centroid and take the singular values ``s`` of the
``2m x n`` registered tracking matrix; the rank-``3k`` approximation leaves the relative
residual ``rho_k = sqrt(sum_{j >= 3k} s_j^2 / sum_j s_j^2)`` (eq. 14 of the paper: the
truncated SVD is the least-squares optimum). Choose the smallest ``k`` with
``rho_k <= tolerance``.

Why a relative tolerance and not a noise estimate: on motion capture the tracks are exact
projections and the spectrum decays smoothly (the "noise" is the part of the deformation
that no small ``k`` explains), so noise-level estimators read that decay as signal. Gavish
and Donoho's optimal hard threshold (noise from the median singular value) gives rank 18
(k = 6) on drink, pickup, yoga and stretch and 31 (k = 11) on dance. The default tolerance
of 1% of the tracks' energy (RMS) asks the 3k-dimensional motion space to explain 99% of the
image motion. On the Akhter sequences it gives k = 3 (drink), 4 (pickup, yoga), 5 (stretch,
dance). With image noise of standard deviation ``sigma`` the natural tolerance is the
statistical floor of `jaxnrsfm.statistical_floor` relative to the tracks' RMS.

**Outliers** (``robust=True``, what `jaxnrsfm.reconstruct` uses when it is not told
``k``): a few gross errors carry more energy than the tail of the deformation, and the
spectrum of the tracks themselves then asks for every basis (``k = 12``, the cap, on each
Akhter sequence with 10% outliers of 2.5--12.5% of the tracks' extent). The spectrum is
instead taken of the low-rank part ``L`` of a robust principal component analysis,
``min ||L||_* + lambda sum_ij |E_ij|`` subject to ``W = L + E`` on the observed entries
(principal component pursuit, Candès, Li, Ma & Wright 2011; ``E_ij`` the 2-vector error of
an entry, ``lambda = 1 / sqrt(max(2m, n))``; solved by the inexact augmented Lagrangian
method of Lin, Chen & Ma 2010). The nuclear norm shrinks ``L``, so the rule picks a
smaller ``k`` than on the raw tracks (2, 3, 3, 3, 4 on drink, pickup, yoga, stretch,
dance), and the same with 10% outliers (dance: 3). The robust rule returns the smaller of
the two choices: outliers only inflate the raw spectrum's tail, and where principal
component pursuit does not recover an exactly low-rank matrix (a noise-free 40-frame,
30-point Bregler sequence with k = 3: it chose 4) the raw spectrum is the right one.
On the paper's cube (sigma = 2, with or without 10% outliers) the robust rule gives the
true k = 4, the raw one 12 (the cube's deformation modes are weak against the noise).
"""

import numpy as np
from jaxtyping import ArrayLike

from .threads import single_threaded_lapack
from .tracks import prepare_tracks

RPCA_STEPS = 300
"""Iterations of the robust PCA (its penalty grows by 1.5 a step: converged long before)."""


def robust_low_rank(W: np.ndarray, visible: np.ndarray, *, steps: int = RPCA_STEPS) -> np.ndarray:
    """The low-rank part ``L`` of principal component pursuit on the observed entries (see
    the module docstring), with each entry's 2-vector error penalised as a group.
    Unobserved entries are free: ``L`` there is a completion."""
    mask = np.repeat(visible, 2, axis=0)
    W = np.where(mask, W, 0.0)
    lam = 1.0 / np.sqrt(max(W.shape))
    mu = 1.25 / max(np.linalg.norm(W, 2), np.finfo(float).tiny)
    E, Y = np.zeros_like(W), np.zeros_like(W)
    with single_threaded_lapack(host=True):  # 300 SVDs of a thin matrix: see jaxnrsfm.threads
        for _ in range(steps):
            U, s, Vt = np.linalg.svd(W - E + Y / mu, full_matrices=False)
            L = (U * np.maximum(s - 1 / mu, 0.0)) @ Vt
            X = W - L + Y / mu
            length = np.sqrt(X[0::2] ** 2 + X[1::2] ** 2)
            shrink = np.maximum(1 - (lam / mu) / np.maximum(length, np.finfo(float).tiny), 0.0)
            E = np.where(mask, X * np.repeat(shrink, 2, axis=0), X)
            Y = Y + mu * np.where(mask, W - L - E, 0.0)
            mu = min(1.5 * mu, 1e10)
    return L


def residual_spectrum(
    W: ArrayLike, visible: ArrayLike | None = None, *, k_max: int = 12, robust: bool = False
) -> np.ndarray:
    """``rho_k`` for ``k = 1..k_max``: the relative RMS residual of the best rank-``3k``
    approximation of the registered tracks (``robust``: of their robust low-rank part,
    `robust_low_rank`). Otherwise missing entries are filled with their frame's
    visible centroid (zero after registration) — adequate for a few missing entries only."""
    W0, vis = prepare_tracks(W, visible)
    W0, vis = np.asarray(W0, np.float64), np.asarray(vis)
    if robust:
        W0, vis = robust_low_rank(W0, vis), np.ones_like(vis)
    vis = np.repeat(vis, 2, axis=0)
    centroid = (W0 * vis).sum(axis=1, keepdims=True) / np.maximum(vis.sum(axis=1, keepdims=True), 1)
    Wc = np.where(vis, W0 - centroid, 0.0)
    s2 = np.linalg.svd(Wc, compute_uv=False) ** 2
    tail = np.concatenate([np.cumsum(s2[::-1])[::-1], [0.0]])
    ks = np.arange(1, k_max + 1)
    return np.sqrt(tail[np.minimum(3 * ks, len(s2))] / s2.sum())


def choose_k(
    W: ArrayLike, visible: ArrayLike | None = None, *, tolerance: float = 0.01, k_max: int = 12, robust: bool = False
) -> int:
    """The smallest ``k`` whose rank-``3k`` fit of the registered tracks leaves a relative
    RMS residual at most ``tolerance`` (see the module docstring); ``k_max`` if none does.

    **Arguments:**

    - `W`: tracks ``(2m, n)``, NaN where missing.
    - `visible`: optional ``(m, n)`` mask.
    - `tolerance`: the residual RMS allowed, relative to the registered tracks' RMS.
    - `k_max`: largest ``k`` considered (also capped by the matrix size).
    - `robust`: also take the spectrum of the tracks' robust low-rank part, which
      outliers do not inflate, and return the smaller choice (module docstring).
    """
    if not 0 < tolerance < 1:
        raise ValueError(f"tolerance must be in (0, 1); got {tolerance}")
    W_shape = np.shape(W)
    k_max = max(1, min(k_max, min(W_shape[0], W_shape[1]) // 3))
    choices = [_smallest(residual_spectrum(W, visible, k_max=k_max), tolerance, k_max)]
    if robust:
        choices.append(_smallest(residual_spectrum(W, visible, k_max=k_max, robust=True), tolerance, k_max))
    return min(choices)


def _smallest(rho: np.ndarray, tolerance: float, k_max: int) -> int:
    below = np.nonzero(rho <= tolerance)[0]
    return int(below[0]) + 1 if below.size else k_max
