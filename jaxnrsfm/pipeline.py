"""The user entry point: tracks in, Euclidean reconstruction out.

``reconstruct`` validates the tracks (before anything is compiled), then runs one
jit-compiled pure pipeline: factorization -> metric upgrade -> per-frame structure and
motion. One sequence per call; a batch is ``jax.vmap`` of the same call.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .factorize import factorize_prepared
from .status import Status
from .tracks import from_frames, prepare_tracks
from .upgrade import metric_upgrade, split_translation

METHODS = ("direct",)
"""Reconstruction strategies available to :func:`reconstruct`."""
FORMS = ("augmented", "registered")
"""Factorization forms: rank ``3k + 1`` without registration, or rank ``3k`` registered."""


class Reconstruction(eqx.Module):
    """The result of :func:`reconstruct` for one sequence (or a batch, under vmap)."""

    W_hat: Float[Array, "2m n"]
    """The fitted tracks ``M S`` (+ translations): the affine low-rank reprojection. The
    metric upgrade is a change of basis and leaves it unchanged."""
    inliers: Bool[Array, "m n"]
    """Observed entries the method kept as inliers."""
    shapes: Float[Array, "m 3 n"]
    """Per-frame Euclidean 3-D shapes, centred."""
    rotations: Float[Array, "m 3 3"]
    """Camera rotations; frame ``i`` projects with ``rotations[i, :2]``."""
    weights: Float[Array, "m k"]
    """Deformation weights."""
    bases: Float[Array, "k 3 n"]
    """Shape bases."""
    translations: Float[Array, "m 2"]
    """Image translation of each frame (the projection of its shape's centroid)."""
    M: Float[Array, "2m r"]
    """Affine motion matrix of the factorization (``r = 3k + 1`` or ``3k``)."""
    S: Float[Array, "r n"]
    """Affine structure matrix of the factorization."""
    cost: Float[Array, ""]
    """Sum of squared residuals of ``W_hat`` over the inliers."""
    metric_residual: Float[Array, ""]
    """Relative misfit of the upgraded motion to the Bregler form (0 when exact)."""
    steps: Int[Array, ""]
    """Iterations of the factorization solver (0 for a plain SVD)."""
    status: Status
    """Outcome; ``status == Status.success`` when all went well."""

    def reproject(self) -> Float[Array, "2m n"]:
        """The Euclidean model's tracks ``R_i[:2] S_i + t_i``. Equal to ``W_hat`` for exact
        data; with noise it also carries the Bregler model's stricter structure."""
        proj = jnp.einsum("iab,ibn->ian", self.rotations[:, :2], self.shapes)
        return from_frames(proj + self.translations[:, :, None])


@eqx.filter_jit
def reconstruct_prepared(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    k: int,
    method: str = "direct",
    form: str = "augmented",
    complete: bool = False,
    max_steps: int = 500,
    rtol: float = 1e-10,
) -> Reconstruction:
    """:func:`reconstruct` on tracks already checked by :func:`prepare_tracks` (zero-filled,
    with their effective mask): the pure, jit-compiled pipeline that a batch vmaps."""
    augmented = form == "augmented"
    fac = factorize_prepared(
        W,
        visible,
        rank=3 * k + augmented,
        register=not augmented,
        complete=complete,
        max_steps=max_steps,
        rtol=rtol,
    )
    if augmented:
        M, S, t, _ = split_translation(fac.M, fac.S)
    else:
        M, S, t = fac.M, fac.S, fac.translations
    eu = metric_upgrade(M, S, t, k)
    finite = jnp.all(jnp.isfinite(fac.W_hat)) & jnp.all(jnp.isfinite(eu.shapes))
    status = Status.where(fac.converged, Status.success, Status.not_converged)
    status = Status.where(finite, status, Status.nonfinite)
    return Reconstruction(
        fac.W_hat,
        visible,
        eu.shapes,
        eu.rotations,
        eu.weights,
        eu.bases,
        eu.translations,
        fac.M,
        fac.S,
        fac.cost,
        eu.metric_residual,
        fac.steps,
        status,
    )


def reconstruct(
    W: ArrayLike,
    visible: ArrayLike | None = None,
    *,
    k: int,
    method: Literal["direct"] = "direct",
    form: Literal["augmented", "registered"] = "augmented",
    max_steps: int = 500,
    rtol: float = 1e-10,
) -> Reconstruction:
    """Reconstruct a nonrigid object from its tracks.

    **Arguments:**

    - `W`: tracks ``(2m, n)``; rows ``2i, 2i+1`` are u, v of frame ``i``; NaN = missing.
    - `visible`: optional ``(m, n)`` mask of observed entries.
    - `k`: number of shape bases (1 = rigid).
    - `method`: ``"direct"`` fits every observed entry by least squares (no outlier
      handling).
    - `form`: ``"augmented"`` (the paper's rank-(3k+1) factorization, eq. 12, no
      registration; the default) or ``"registered"`` (rank 3k after centring each frame
      on its visible centroid, eq. 8).
    - `max_steps`, `rtol`: budget of the missing-data solver.

    **Returns:** a :class:`Reconstruction`.

    **Raises:** ``ValueError`` (before any compilation) for malformed tracks, an unknown
    method or form, or a ``k`` too large for the data.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if form not in FORMS:
        raise ValueError(f"unknown form {form!r}; choose one of {', '.join(FORMS)}")
    if not isinstance(k, int) or isinstance(k, bool) or k < 1:
        raise ValueError(f"k (the number of shape bases) must be a positive integer; got {k!r}")
    rank = 3 * k + (form == "augmented")
    W0, vis = prepare_tracks(W, visible, rank=rank, rank_name=f"k={k} ({form} rank {rank})")
    complete = not isinstance(vis, jax.core.Tracer) and bool(vis.all())
    return reconstruct_prepared(
        W0, vis, k=k, method=method, form=form, complete=complete, max_steps=max_steps, rtol=rtol
    )
