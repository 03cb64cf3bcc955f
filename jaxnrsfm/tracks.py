"""The tracking matrix: layout, missing entries and validation.

A sequence of ``m`` frames and ``n`` tracked points is a matrix ``W`` of shape
``(2m, n)``: rows ``2i`` and ``2i + 1`` hold the ``u`` and ``v`` image coordinates of
frame ``i`` (the interleaved layout of the paper and of the Akhter data). A boolean
mask ``visible`` of shape ``(m, n)`` says which (frame, point) entries were observed;
NaN in ``W`` also means missing.

Validation happens here, in NumPy, before anything is traced or compiled, so that a
user gets a ``ValueError`` naming the problem instead of a NaN-filled result. Checks
that need values (non-finite entries, empty frames) run only when the arrays are
concrete; under ``jax.vmap``/``jax.jit`` only the shape checks can run, and a trial that
goes wrong is reported in its status instead.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float


def to_frames(W: Float[Array, "2m n"]) -> Float[Array, "m 2 n"]:
    """Reshape the interleaved ``(2m, n)`` tracking matrix to ``(m, 2, n)``."""
    return W.reshape(W.shape[0] // 2, 2, W.shape[1])


def from_frames(X: Float[Array, "m 2 n"]) -> Float[Array, "2m n"]:
    """Inverse of `to_frames`."""
    return X.reshape(2 * X.shape[0], X.shape[2])


def row_mask(visible: Bool[Array, "m n"]) -> Bool[Array, "2m n"]:
    """Expand a per-(frame, point) mask to the rows of ``W`` (both coordinates)."""
    return jnp.repeat(visible, 2, axis=0)


def centred_spread(W: Float[Array, "2m n"], visible: Bool[Array, "m n"]) -> Float[Array, ""]:
    """The RMS per coordinate of the observed tracks about each frame's visible centroid:
    the in-plane extent of the object, the yardstick of the plausibility checks."""
    frames = jnp.where(visible[:, None, :], to_frames(W), 0.0)
    centroid = frames.sum(axis=2, keepdims=True) / jnp.maximum(visible.sum(axis=1), 1)[:, None, None]
    centred = jnp.where(visible[:, None, :], frames - centroid, 0.0)
    return jnp.sqrt(jnp.sum(centred**2) / jnp.maximum(2 * visible.sum(), 1))


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def prepare_tracks(
    W: ArrayLike,
    visible: ArrayLike | None = None,
    *,
    rank: int | None = None,
    rank_name: str | None = None,
) -> tuple[Float[Array, "2m n"], Bool[Array, "m n"]]:
    """Validate a tracking matrix and return it with missing entries zero-filled.

    **Arguments:**

    - `W`: tracks, shape ``(2m, n)``, NaN where missing.
    - `visible`: optional boolean mask ``(m, n)``; ``None`` means every entry that is
      not NaN.
    - `rank`: the rank the caller will fit; checked against what the data allows
      (``rank <= min(2m, n)``, and every frame needs at least ``rank`` visible points
      and every point at least ``ceil(rank / 2)`` visible frames, or its factor is not
      determined).
    - `rank_name`: how error messages name the rank (say, ``"k=4 (rank 13)"``).

    **Returns:** ``(W0, visible)`` where ``W0`` has zeros at missing entries (so that no
    NaN ever enters a computation) and ``visible`` is the effective boolean mask.

    **Raises:** ``ValueError`` for a wrong shape, an odd number of rows, a non-finite
    value at an observed entry, a frame or point with no (or too few) observed
    entries, or a rank larger than the data allows.
    """
    if not hasattr(W, "shape"):
        W = np.asarray(W)
    if W.ndim != 2:
        raise ValueError(f"tracks W must be a 2-D array of shape (2m, n); got shape {W.shape}")
    rows, n = W.shape
    if rows % 2:
        raise ValueError(f"tracks W must have an even number of rows (u and v of each frame); got {rows}")
    m = rows // 2
    if m == 0 or n == 0:
        raise ValueError(f"tracks W is empty: shape {W.shape}")
    if visible is not None:
        if not hasattr(visible, "shape"):
            visible = np.asarray(visible)
        if visible.shape != (m, n):
            raise ValueError(
                f"visible must have shape (m, n) = ({m}, {n}) for W of shape {W.shape}; got {visible.shape}"
            )
    if rank is not None:
        rank_name = rank_name or f"rank {rank}"
        if rank < 1:
            raise ValueError(f"rank must be at least 1; got {rank}")
        if rank > min(rows, n):
            raise ValueError(
                f"{rank_name} is larger than the data allows: W is {rows}x{n}, so the "
                f"rank is at most min(2m, n) = {min(rows, n)}"
            )

    dtype = W.dtype if jnp.issubdtype(W.dtype, jnp.floating) else jnp.result_type(float)
    if _is_concrete(W) and (visible is None or _is_concrete(visible)):
        visible = _check_values(np.asarray(W), None if visible is None else np.asarray(visible))
        if rank is not None:
            _check_counts(visible, rank, rank_name)
        W = np.where(np.repeat(visible, 2, axis=0), np.asarray(W), 0.0)
        return jnp.asarray(W, dtype=dtype), jnp.asarray(visible)

    # Traced input: only what the shapes tell can be checked; NaN still means missing.
    W = jnp.asarray(W, dtype=dtype)
    finite = jnp.isfinite(to_frames(W)).all(axis=1)
    visible = finite if visible is None else jnp.asarray(visible, dtype=bool) & finite
    return jnp.where(row_mask(visible), W, 0.0), visible


def _check_values(W: np.ndarray, visible: np.ndarray | None) -> np.ndarray:
    frames = W.reshape(W.shape[0] // 2, 2, W.shape[1])
    nan = np.isnan(frames)
    if np.any(nan.any(axis=1) != nan.all(axis=1)):
        i, j = np.argwhere(nan.any(axis=1) != nan.all(axis=1))[0]
        raise ValueError(
            f"entry (frame {i}, point {j}) has one coordinate NaN and the other not; "
            "mark both coordinates of a missing entry as NaN"
        )
    if visible is None:
        visible = ~nan.all(axis=1)
    else:
        visible = visible.astype(bool)
    bad = visible & ~np.isfinite(frames).all(axis=1)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise ValueError(
            f"tracks W has {int(bad.sum())} non-finite value(s) at observed entries, "
            f"first at frame {i}, point {j}; mark missing entries with NaN or in `visible`"
        )
    return visible


def _check_counts(visible: np.ndarray, rank: int, rank_name: str) -> None:
    per_frame = visible.sum(axis=1)
    per_point = visible.sum(axis=0)
    if (per_frame == 0).any():
        raise ValueError(f"frame(s) {np.flatnonzero(per_frame == 0).tolist()} have no visible points")
    if (per_point == 0).any():
        raise ValueError(f"point(s) {np.flatnonzero(per_point == 0).tolist()} are never visible")
    # Frame i's two motion rows need `rank` equations from its visible points; point j's
    # structure column needs `rank` equations, two per visible frame.
    if (per_frame < rank).any():
        i = int(np.argmin(per_frame))
        raise ValueError(
            f"frame {i} has {int(per_frame[i])} visible points, fewer than the {rank} that "
            f"{rank_name} needs to determine its motion"
        )
    if (2 * per_point < rank).any():
        j = int(np.argmin(per_point))
        raise ValueError(
            f"point {j} is visible in {int(per_point[j])} frame(s), fewer than the "
            f"{-(-rank // 2)} that {rank_name} needs to determine its structure"
        )
