"""Error measures: reprojection errors, the statistical floor, e3D and outlier detection.

All are pure functions of arrays (jit- and vmap-friendly). ``e3d``, ``align_shapes``,
``rms_error``, ``mean_reprojection_error`` and ``outlier_precision_recall`` are
jit-compiled: called op by op, ``e3d`` and ``rms_error`` dispatched 27 small programs
on a first call, each compiled on its own. A "reprojection error" of an
entry is the Euclidean length of its 2-vector residual ``|e_ij|`` (the paper's eq. 16);
"RMS" errors are per coordinate, the convention of the low-rank factorization
literature and of the statistical floor.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .tracks import to_frames


def length(x: Float[Array, "..."], axis: int) -> Float[Array, "..."]:
    """Euclidean length along ``axis``, with gradient 0 (not NaN) at a zero vector: a
    noise-free fit has exactly zero residuals (double ``where``)."""
    sq = jnp.sum(x**2, axis=axis)
    return jnp.where(sq > 0, jnp.sqrt(jnp.where(sq > 0, sq, 1.0)), 0.0)


def entry_errors(W: Float[Array, "2m n"], W_hat: Float[Array, "2m n"]) -> Float[Array, "m n"]:
    """``|e_ij|``, the length of each entry's 2-vector residual."""
    return length(to_frames(W) - to_frames(W_hat), axis=1)


@jax.jit
def mean_reprojection_error(
    W: Float[Array, "2m n"], W_hat: Float[Array, "2m n"], mask: Bool[Array, "m n"]
) -> Float[Array, ""]:
    """Mean of ``|e_ij|`` over the entries in ``mask`` (NaN in ``W`` elsewhere is ignored)."""
    e = jnp.where(mask, entry_errors(jnp.where(jnp.isnan(W), 0.0, W), W_hat), 0.0)
    return e.sum() / mask.sum()


@jax.jit
def rms_error(W: Float[Array, "2m n"], W_hat: Float[Array, "2m n"], mask: Bool[Array, "m n"]) -> Float[Array, ""]:
    """Root mean square coordinate residual over the entries in ``mask``."""
    e = jnp.where(mask, entry_errors(jnp.where(jnp.isnan(W), 0.0, W), W_hat), 0.0)
    return jnp.sqrt(jnp.sum(e**2) / (2 * mask.sum()))


def statistical_floor(noise, m: int, n: int, rank: int):
    """Expected RMS deviation from the noise-free matrix of a rank-``rank`` least-squares
    fit of a ``2m x n`` matrix with i.i.d. Gaussian noise of standard deviation ``noise``:
    ``noise * sqrt(rank (2m + n - rank) / (2 m n))`` (the parameter count over the data
    count)."""
    return noise * jnp.sqrt(rank * (2 * m + n - rank) / (2 * m * n))


def _normalize(shapes, scale):
    X = shapes / scale
    return X - X.mean(axis=2, keepdims=True)


@jax.jit
def align_shapes(shapes: Float[Array, "m 3 n"], true_shapes: Float[Array, "m 3 n"]) -> Float[Array, "m 3 n"]:
    """``shapes`` centred per frame and turned by the ONE orthogonal 3x3 matrix
    (reflection allowed) that best fits them to the centred ``true_shapes``."""
    X, Y = _normalize(shapes, 1.0), _normalize(true_shapes, 1.0)
    U, _, Vt = jnp.linalg.svd(jnp.einsum("ian,ibn->ab", Y, X))
    return jnp.einsum("ab,ibn->ian", U @ Vt, X)  # argmin_Q sum_i |Q X_i - Y_i|


@jax.jit
def e3d(shapes: Float[Array, "m 3 n"], true_shapes: Float[Array, "m 3 n"]) -> Float[Array, ""]:
    """Akhter et al.'s 3-D error, exactly as defined in ``shared/data/README.md``.

    Both shapes are divided by the mean over the ``3m`` rows of the row-wise standard
    deviation (over points, population) of the ground truth; every frame is centred;
    ONE orthogonal 3x3 alignment (reflection allowed) is fitted for the whole sequence;
    the result is the per-point Euclidean distance averaged over all points and frames.
    """
    scale = jnp.mean(jnp.std(true_shapes, axis=2))
    X = align_shapes(shapes / scale, true_shapes / scale)
    return jnp.mean(length(X - _normalize(true_shapes, scale), axis=1))


@jax.jit
def outlier_precision_recall(
    detected: Bool[Array, "m n"], true: Bool[Array, "m n"], mask: Bool[Array, "m n"] | None = None
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """Precision and recall of ``detected`` outliers against the ``true`` ones, counted
    over ``mask`` (default: all entries). With nothing detected precision is 1; with
    nothing to find recall is 1."""
    if mask is not None:
        detected, true = detected & mask, true & mask
    hits = jnp.sum(detected & true)
    precision = jnp.where(detected.sum() > 0, hits / jnp.maximum(detected.sum(), 1), 1.0)
    recall = jnp.where(true.sum() > 0, hits / jnp.maximum(true.sum(), 1), 1.0)
    return precision, recall
