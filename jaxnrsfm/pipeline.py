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

from . import residuals, robust
from .choose import choose_k
from .factorize import Factorization, factorize_prepared
from .metrics import entry_errors
from .refine import refine_upgrade
from .status import Status
from .tracks import centred_spread, from_frames, prepare_tracks, row_mask, to_frames
from .upgrade import Euclidean, metric_upgrade, split_translation

METHODS = ("direct", "wang", "huynh", "ke_kanade", "huber", "l1", "oracle")
"""Reconstruction strategies available to :func:`reconstruct`."""
FORMS = ("augmented", "registered")
"""Factorization forms: rank ``3k + 1`` without registration, or rank ``3k`` registered."""


class Options(eqx.Module):
    """The methods' tuning knobs (Python scalars: static under jit). The defaults are
    :func:`reconstruct`'s."""

    threshold: float | None = None
    """Outlier threshold, a multiple of the robust residual scale; ``None`` chooses it
    from the data (:mod:`jaxnrsfm.residuals`)."""
    passes: int = 3
    """Minimum number of rejection passes of the robust algorithm (``wang``)."""
    weighted: bool = True
    """Step 5's weighted factorization of the inliers (``wang``)."""
    iterations: int = 10
    """Pseudo-observation iterations (``huynh``)."""
    delta: float = 1.345
    """Huber loss parameter in robust scales (``huber``); an array here is traced, and
    differentiable."""
    max_steps: int = 500
    """Step budget of the missing-data solver."""
    rtol: float = 1e-10
    """Relative cost decrease below which the missing-data solver stops."""
    refine: bool = True
    """Replace the upgrade's shapes by the nuclear-norm shapes given its rotations
    (:func:`jaxnrsfm.refine.refine_upgrade`, Dai et al.'s BMM shape step)."""
    trace_norm: float = 0.0
    """With ``refine``: 0 keeps the upgrade's rotations; > 0 takes them from Dai et al.'s
    trace-norm relaxation with this weight (:func:`jaxnrsfm.refine.trace_norm_triple`)."""
    rotation_rank: int | None = None
    """With ``refine``: 0 keeps the upgrade's rotations; > 0 takes them from the rotation
    constraints on a factorization of that rank (:func:`jaxnrsfm.refine.high_rank_rotations`),
    ``None`` on the directions of the tracks above the noise (its rule)."""


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

    @property
    def camera_shapes(self) -> Float[Array, "... m 3 n"]:
        """The shapes in each frame's camera coordinates, ``R_i S_i``: what a ground truth
        given in the camera frame (a static camera, e.g. Akhter's dance) is compared with."""
        return jnp.einsum("...iab,...ibn->...ian", self.rotations, self.shapes)

    def shapes_in(self, frame: Literal["world", "camera"]) -> Float[Array, "... m 3 n"]:
        """``shapes`` (``"world"``) or :attr:`camera_shapes` (``"camera"``): the shapes in the
        frame a ground truth is given in (``jaxnrsfm.datasets.Tracks.frame``)."""
        if frame not in ("world", "camera"):
            raise ValueError(f"frame must be 'world' or 'camera'; got {frame!r}")
        return self.shapes if frame == "world" else self.camera_shapes

    def reproject(self) -> Float[Array, "2m n"]:
        """The Euclidean model's tracks ``R_i[:2] S_i + t_i``. Equal to ``W_hat`` for exact
        data; with noise it also carries the Bregler model's stricter structure."""
        proj = jnp.einsum("iab,ibn->ian", self.rotations[:, :2], self.shapes)
        return from_frames(proj + self.translations[:, :, None])


def _factorize(W, visible, outliers, *, k, method, form, complete, options: Options) -> Factorization:
    augmented = form == "augmented"
    rank = 3 * k + augmented
    budget = dict(max_steps=options.max_steps, rtol=options.rtol)
    if method == "direct":
        return factorize_prepared(W, visible, rank=rank, register=not augmented, complete=complete, **budget)
    if method == "wang":
        return robust.wang(
            W,
            visible,
            rank=rank,
            complete=complete,
            threshold=options.threshold,
            passes=options.passes,
            weighted=options.weighted,
            **budget,
        )
    if method == "huynh":
        return robust.huynh(W, visible, rank=rank, complete=complete, iterations=options.iterations, **budget)
    if method == "ke_kanade":
        return robust.ke_kanade(W, visible, rank=rank, complete=complete, threshold=options.threshold)
    if method in ("huber", "l1"):
        delta = options.delta if method == "huber" else None
        return robust.huber(
            W, visible, rank=rank, complete=complete, delta=delta, threshold=options.threshold, **budget
        )
    return robust.oracle(W, visible, outliers, rank=rank, **budget)


MAX_REJECTED = 0.375
"""Largest fraction of the observed entries a detecting method may reject and still
report success. Measured with ``wang`` on the cube (sigma 2, two seeds each): with 35%
outliers it rejected 36% and fitted within 15% of the oracle; with 40% it rejected 40%,
found them (precision and recall >= 0.96), and still failed (errors 2.1 and 7.1 against
the oracle's 0.9, from a few points left with too few inliers) while its kept residuals
looked like noise; only this count gives it away."""


MISFIT = 0.12
"""Largest Kolmogorov--Smirnov distance between the kept residuals and the fitted inlier
law (:func:`jaxnrsfm.residuals.misfit`) of a detecting method that reports success."""

SCALE_RATIO = 0.15
"""Largest inlier residual scale (the residual model's ``sigma``), relative to the RMS
spread of the centred tracks, of a detecting method that reports success: beyond it the
low-rank model does not explain the tracks. Measured on the cube (spread ~95 units, seed
1): 0.048 at sigma 5 with 20% outliers, 0.026 at sigma 2 with 40%; with 60% and 70%
outliers, past the breakdown point, the model took the outliers for inliers of scale 27
and 33 (0.28, 0.34) and rejected nothing, its residuals fitting the heavy-tailed inlier
law (Kolmogorov--Smirnov 0.09)."""


DEPTH_RATIO = 10.0
"""Largest ratio of the shapes' RMS depth (along each camera's viewing direction) to
their RMS in-plane extent that :func:`implausible` accepts. The in-plane part of a shape
is what the tracks show; a real object seen from moving cameras is not ten times deeper
than it is wide in every view. (The failure it catches: an upgrade whose ``H^-1``
amplified the misfit into shapes 10^4 times larger than the object, reported as a
success with a metric residual of 2e-8.)"""

REPROJECTION_RATIO = 0.5
"""Largest RMS distance, relative to the tracks' RMS spread, between the Euclidean
model's reprojection and the fitted tracks that :func:`implausible` accepts."""


def implausible(
    rotations: Float[Array, "m 3 3"],
    shapes: Float[Array, "m 3 n"],
    translations: Float[Array, "m 2"],
    W_hat: Float[Array, "2m n"],
) -> Bool[Array, ""]:
    """Whether Euclidean shapes are wildly inconsistent with the fitted tracks ``W_hat``:
    their depth spread is more than ``DEPTH_RATIO`` times their in-plane spread, or their
    reprojection ``R_i[:2] S_i + t_i`` is farther from ``W_hat`` than ``REPROJECTION_RATIO``
    of the tracks' spread. Such a result is never reported as a success."""
    camera = jnp.einsum("iab,ibn->ian", rotations, shapes)
    misfit = jnp.sqrt(jnp.mean((camera[:, :2] + translations[:, :, None] - to_frames(W_hat)) ** 2))
    camera = camera - camera.mean(axis=2, keepdims=True)
    plane = jnp.sqrt(jnp.mean(camera[:, :2] ** 2))
    depth = jnp.sqrt(jnp.mean(camera[:, 2] ** 2))
    spread = centred_spread(W_hat, jnp.ones((W_hat.shape[0] // 2, W_hat.shape[1]), bool))
    tiny = jnp.finfo(W_hat.dtype).tiny
    return (depth > DEPTH_RATIO * jnp.maximum(plane, tiny)) | (misfit > REPROJECTION_RATIO * jnp.maximum(spread, tiny))


BASELINES = ("huynh", "ke_kanade")
"""The paper's baselines. Their fit uses every observed entry (corrected, or under the L1
loss); the inliers they report are :func:`jaxnrsfm.robust.classify`'s, for comparison
only. Their status (:func:`_status`) says whether *their* iteration converged to its own
stopping rule, as their papers define them, and the result is finite and plausible; a
residual-distribution test designed for the robust method says nothing about that."""

DETECTING = ("wang", "huber", "l1")
"""Methods whose status also judges their outlier detection (:func:`_status`): the paper's
robust algorithm and the library's robust losses decide the inliers their fit relies on."""


def _status(W, visible, fac: Factorization, eu: Euclidean, rank: int, method: str) -> Status:
    finite = jnp.all(jnp.isfinite(fac.W_hat)) & jnp.all(jnp.isfinite(eu.shapes))
    status = Status.where(fac.converged, Status.success, Status.not_converged)
    status = Status.where(implausible(eu.rotations, eu.shapes, eu.translations, fac.W_hat), Status.implausible, status)
    # Too few of the entries the fit relies on (the inliers it kept; every observed entry
    # for a baseline) to determine a frame's motion or a point's structure: the fit
    # cannot be trusted.
    used = visible if method in BASELINES else fac.inliers
    starved = jnp.any(used.sum(1) < rank) | jnp.any(2 * used.sum(0) < rank)
    starved |= used.sum() < 0.5 * visible.sum()
    if method in DETECTING:
        # More rejected than the method survives (the median scale breaks down at half),
        # or kept residuals that do not look like noise.
        starved |= used.sum() < (1 - MAX_REJECTED) * visible.sum()
        errors = entry_errors(W, fac.W_hat)
        model = residuals.fit(errors, visible, residuals.scale_floor(W, visible))
        starved |= residuals.misfit(errors, used, model) > MISFIT
        starved |= model.sigma > SCALE_RATIO * centred_spread(W, visible)
    status = Status.where(starved, Status.too_many_outliers, status)
    return Status.where(finite, status, Status.nonfinite)


@eqx.filter_jit
def reconstruct_prepared(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    outliers: Bool[Array, "m n"] | None = None,
    *,
    k: int,
    method: str = "wang",
    form: str = "augmented",
    complete: bool = False,
    options: Options | None = None,
) -> Reconstruction:
    """:func:`reconstruct` on tracks already checked by :func:`prepare_tracks` (zero-filled,
    with their effective mask): the pure, jit-compiled pipeline that a batch vmaps."""
    options = Options() if options is None else options
    fac = _factorize(W, visible, outliers, k=k, method=method, form=form, complete=complete, options=options)
    if form == "augmented":
        M, S, t, _ = split_translation(fac.M, fac.S)
    else:
        M, S, t = fac.M, fac.S, fac.translations
    eu = metric_upgrade(M, S, t, k)
    if options.refine:
        tracks = jnp.where(row_mask(fac.inliers), W, fac.W_hat)
        # Known at trace time to have every entry: no mask, and no refills of the rotations.
        observed = None if complete and method == "direct" else fac.inliers
        eu = refine_upgrade(
            eu, M, tracks, k, observed, trace_norm=options.trace_norm, rotation_rank=options.rotation_rank
        )
    return Reconstruction(
        fac.W_hat,
        fac.inliers,
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
        _status(W, visible, fac, eu, M.shape[1] + (form == "augmented"), method),
    )


def reconstruct(
    W: ArrayLike,
    visible: ArrayLike | None = None,
    *,
    k: int | None = None,
    method: Literal["direct", "wang", "huynh", "ke_kanade", "huber", "l1", "oracle"] = "wang",
    form: Literal["augmented", "registered"] = "augmented",
    outliers: ArrayLike | None = None,
    threshold: float | None = None,
    passes: int = 3,
    weighted: bool = True,
    iterations: int = 10,
    delta: float = 1.345,
    max_steps: int = 500,
    rtol: float = 1e-10,
    refine: bool = True,
    trace_norm: float = 0.0,
    rotation_rank: int | None = None,
) -> Reconstruction:
    """Reconstruct a nonrigid object from its tracks.

    The defaults are the configuration measured best on real tracks
    (``benchmarks/real_sequences.py``): ``k`` chosen from the tracks
    (:func:`jaxnrsfm.choose_k` with ``robust=True``), the paper's robust algorithm
    (``method="wang"``), rotations from the rotation constraints on a high-rank
    factorization of the tracks (every direction above the noise,
    :func:`jaxnrsfm.refine.high_rank_rotations`)
    and the nuclear-norm shapes of Dai et al.'s BMM (``refine=True``). The paper's own
    pipeline -- factorization and metric upgrade, shapes ``H^-1 S`` -- is
    ``refine=False``.

    **Arguments:**

    - `W`: tracks ``(2m, n)``; rows ``2i, 2i+1`` are u, v of frame ``i``; NaN = missing.
    - `visible`: optional ``(m, n)`` mask of observed entries.
    - `k`: number of shape bases (1 = rigid); ``None`` (the default) chooses it from the
      tracks, :func:`jaxnrsfm.choose_k` with ``robust=True`` (needs concrete tracks:
      under ``jit`` or ``vmap`` give ``k``).
    - `method`: ``"wang"`` (the default) is the paper's robust algorithm (section 4.2,
      :func:`jaxnrsfm.robust.wang`); ``"direct"`` fits every observed entry by least
      squares (no outlier handling); ``"huynh"`` is Huynh et al.'s pseudo-observation
      correction; ``"ke_kanade"`` is Ke & Kanade's L1 factorization by alternating
      linear programs; ``"huber"`` and ``"l1"`` minimise the Huber or L1 loss of the
      reprojection residuals with optimistix (:mod:`jaxnrsfm.objective`); ``"oracle"``
      is least squares told the true ``outliers``.
    - `form`: ``"augmented"`` (the paper's rank-(3k+1) factorization, eq. 12, no
      registration; the default) or ``"registered"`` (rank 3k after centring each frame
      on its visible centroid, eq. 8; ``method="direct"`` only).
    - `outliers`: ``(m, n)`` true outlier mask, for ``method="oracle"`` only.
    - `threshold`, `passes`, `weighted`: the robust algorithm's outlier threshold (a
      multiple of the robust residual scale; ``None``, the default, picks it from the
      data), minimum number of rejection passes and step-5 weighting.
    - `iterations`: Huynh et al.'s correction iterations.
    - `delta`: the Huber loss parameter, in robust residual scales (``method="huber"``).
    - `max_steps`, `rtol`: budget of the missing-data solver.
    - `refine`, `trace_norm`: recover the shapes by Dai et al.'s nuclear-norm step given
      the rotations (:func:`jaxnrsfm.refine.refine_upgrade`; the default); ``trace_norm >
      0`` takes the rotations from the trace-norm relaxation with that weight.
      ``refine=False`` keeps the metric upgrade's rotations and shapes.
    - `rotation_rank`: with ``refine``, the rank of the factorization of the tracks whose
      rotation constraints give the rotations (:func:`jaxnrsfm.refine.high_rank_rotations`);
      ``None`` (the default) takes every direction of the centred tracks that stands
      above the noise (:func:`jaxnrsfm.refine.above_noise`); ``0`` keeps the metric
      upgrade's rotations. At most ``min(2m, n - 1)``.

    **Returns:** a :class:`Reconstruction`; its ``status`` reports, per trial, a solver
    that did not converge or more outliers than the data can lose.

    **Raises:** ``ValueError`` (before any compilation) for malformed tracks, an unknown
    method or form, a ``k`` too large for the data, or bad method options.
    """
    if method not in METHODS:
        raise ValueError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
    if form not in FORMS:
        raise ValueError(f"unknown form {form!r}; choose one of {', '.join(FORMS)}")
    if form == "registered" and method != "direct":
        raise ValueError(f"form='registered' supports only method='direct'; {method!r} needs the augmented form")
    if k is None:
        if isinstance(W, jax.core.Tracer) or isinstance(visible, jax.core.Tracer):
            raise ValueError("k=None chooses k from the tracks, which needs concrete arrays: under jit/vmap give k")
        k = choose_k(W, visible, robust=True)
    if not isinstance(k, int) or isinstance(k, bool) or k < 1:
        raise ValueError(f"k (the number of shape bases) must be a positive integer; got {k!r}")
    if (method == "oracle") != (outliers is not None):
        raise ValueError("method='oracle' needs the true `outliers` mask, and only it takes one")
    if not isinstance(delta, jax.core.Tracer) and not delta > 0:
        raise ValueError(f"the Huber parameter delta must be > 0; got {delta}")
    if not (threshold is None or threshold > 0) or passes < 1 or iterations < 1:
        raise ValueError(f"threshold must be > 0 and passes, iterations >= 1; got {threshold}, {passes}, {iterations}")
    rank = 3 * k + (form == "augmented")
    W0, vis = prepare_tracks(W, visible, rank=rank, rank_name=f"k={k} ({form} rank {rank})")
    if outliers is not None:
        outliers = jnp.asarray(outliers, dtype=bool)
        if outliers.shape != vis.shape:
            raise ValueError(f"outliers must have shape (m, n) = {vis.shape}; got {outliers.shape}")
    complete = not isinstance(vis, jax.core.Tracer) and bool(vis.all())
    if not trace_norm >= 0:
        raise ValueError(f"trace_norm must be >= 0; got {trace_norm}")
    if rotation_rank is None and not (refine and not trace_norm):
        rotation_rank = 0  # the default rule applies to refine's own rotations only
    if rotation_rank is not None and (
        not isinstance(rotation_rank, int) or isinstance(rotation_rank, bool) or rotation_rank < 0
    ):
        raise ValueError(f"rotation_rank must be None or a non-negative integer; got {rotation_rank!r}")
    if rotation_rank and not refine:
        raise ValueError("rotation_rank is used by refine=True only")
    if rotation_rank and trace_norm > 0:
        raise ValueError("choose one rotation source: trace_norm > 0 or rotation_rank > 0, not both")
    centred_rank = min(W0.shape[0], W0.shape[1] - 1)
    if (rotation_rank or 0) > centred_rank:
        raise ValueError(
            f"rotation_rank={rotation_rank} exceeds the rank of the centred tracks, min(2m, n - 1) = {centred_rank}"
        )
    options = Options(
        threshold, passes, weighted, iterations, delta, max_steps, rtol, refine, trace_norm, rotation_rank
    )
    return reconstruct_prepared(W0, vis, outliers, k=k, method=method, form=form, complete=complete, options=options)
