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
statistical floor of :func:`jaxnrsfm.statistical_floor` relative to the tracks' RMS.
"""

import numpy as np
from jaxtyping import ArrayLike

from .tracks import prepare_tracks


def residual_spectrum(W: ArrayLike, visible: ArrayLike | None = None, *, k_max: int = 12) -> np.ndarray:
    """``rho_k`` for ``k = 1..k_max``: the relative RMS residual of the best rank-``3k``
    approximation of the registered tracks. Missing entries are filled with their frame's
    visible centroid (zero after registration) — adequate for a few missing entries only."""
    W0, vis = prepare_tracks(W, visible)
    W0, vis = np.asarray(W0, np.float64), np.repeat(np.asarray(vis), 2, axis=0)
    centroid = (W0 * vis).sum(axis=1, keepdims=True) / np.maximum(vis.sum(axis=1, keepdims=True), 1)
    Wc = np.where(vis, W0 - centroid, 0.0)
    s2 = np.linalg.svd(Wc, compute_uv=False) ** 2
    tail = np.concatenate([np.cumsum(s2[::-1])[::-1], [0.0]])
    ks = np.arange(1, k_max + 1)
    return np.sqrt(tail[np.minimum(3 * ks, len(s2))] / s2.sum())


def choose_k(W: ArrayLike, visible: ArrayLike | None = None, *, tolerance: float = 0.01, k_max: int = 12) -> int:
    """The smallest ``k`` whose rank-``3k`` fit of the registered tracks leaves a relative
    RMS residual at most ``tolerance`` (see the module docstring); ``k_max`` if none does.

    **Arguments:**

    - `W`: tracks ``(2m, n)``, NaN where missing.
    - `visible`: optional ``(m, n)`` mask.
    - `tolerance`: the residual RMS allowed, relative to the registered tracks' RMS.
    - `k_max`: largest ``k`` considered (also capped by the matrix size).
    """
    if not 0 < tolerance < 1:
        raise ValueError(f"tolerance must be in (0, 1); got {tolerance}")
    W_shape = np.shape(W)
    k_max = max(1, min(k_max, min(W_shape[0], W_shape[1]) // 3))
    rho = residual_spectrum(W, visible, k_max=k_max)
    below = np.nonzero(rho <= tolerance)[0]
    return int(below[0]) + 1 if below.size else k_max
