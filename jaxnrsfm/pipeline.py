"""The user entry point: tracks in, Euclidean reconstruction out.

``reconstruct`` validates the tracks and the stages (before anything is compiled), then
runs one jit-compiled pure pipeline of the stages (`jaxnrsfm.stages`): the outlier
strategy's low-rank fit -> metric upgrade (where a stage reads it) -> the rejected and
missing entries filled (`filled_tracks`) -> rotation recovery -> shape step. One sequence
per call; a batch is ``jax.vmap`` of the same call.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from . import residuals, temporal
from .choose import choose_k
from .factorize import Factorization, centroids, finish
from .metrics import entry_errors
from .stages import (
    ROTATIONS,
    SHAPES,
    STRATEGIES,
    Direct,
    MaskedALS,
    OutlierStrategy,
    RotationRecovery,
    ShapeStep,
)
from .status import Status
from .threads import compute_single_threaded
from .tracks import centred_spread, from_frames, prepare_tracks, row_mask, to_frames
from .upgrade import Euclidean, metric_upgrade, split_translation

FORMS = ("augmented", "registered")
"""Factorization forms: rank ``3k + 1`` without registration, or rank ``3k`` registered."""


class Reconstruction(eqx.Module):
    """The result of `reconstruct` for one sequence (or a batch, under vmap)."""

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
        """``shapes`` (``"world"``) or `camera_shapes` (``"camera"``): the shapes in the
        frame a ground truth is given in (``jaxnrsfm.datasets.Tracks.frame``)."""
        if frame not in ("world", "camera"):
            raise ValueError(f"frame must be 'world' or 'camera'; got {frame!r}")
        return self.shapes if frame == "world" else self.camera_shapes

    def reproject(self) -> Float[Array, "2m n"]:
        """The Euclidean model's tracks ``R_i[:2] S_i + t_i``. Equal to ``W_hat`` for exact
        data; with noise it also carries the Bregler model's stricter structure."""
        proj = jnp.einsum("iab,ibn->ian", self.rotations[:, :2], self.shapes)
        return from_frames(proj + self.translations[:, :, None])


MAX_REJECTED = 0.375
"""Largest fraction of the observed entries a detecting method may reject and still
report success. Measured with ``wang`` on the cube (sigma 2, two seeds each): with 35%
outliers it rejected 36% and fitted within 15% of the oracle; with 40% it rejected 40%,
found them (precision and recall >= 0.96), and still failed (errors 2.1 and 7.1 against
the oracle's 0.9, from a few points left with too few inliers) while its kept residuals
looked like noise; only this count gives it away."""


MISFIT = 0.12
"""Largest Kolmogorov--Smirnov distance between the kept residuals and the fitted inlier
law (`jaxnrsfm.residuals.misfit`) of a detecting method that reports success."""

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
their RMS in-plane extent that `implausible` accepts. The in-plane part of a shape
is what the tracks show; a real object seen from moving cameras is not ten times deeper
than it is wide in every view. (The failure it catches: an upgrade whose ``H^-1``
amplified the misfit into shapes 10^4 times larger than the object, reported as a
success with a metric residual of 2e-8.)"""

REPROJECTION_RATIO = 0.5
"""Largest RMS distance, relative to the tracks' RMS spread, between the Euclidean
model's reprojection and the fitted tracks that `implausible` accepts."""


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


def status_of(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    fac: Factorization,
    eu: Euclidean,
    rank: int,
    method: OutlierStrategy,
) -> Status:
    """The outcome of a reconstruction: the fit's convergence, the plausibility of the
    Euclidean result, and whether the entries the fit relies on suffice -- the kept inliers,
    or every observed entry for a strategy that fits them all (the paper's baselines,
    ``OutlierStrategy.fits_every_entry``), whose status is then their own iteration's
    convergence to its stopping rule, as their papers define them. A strategy that judges
    its detection (``OutlierStrategy.judges_detection``: the robust algorithm and the robust
    losses) also fails when it rejected more than it survives or its kept residuals do not
    look like noise."""
    finite = jnp.all(jnp.isfinite(fac.W_hat)) & jnp.all(jnp.isfinite(eu.shapes))
    status = Status.where(fac.converged, Status.success, Status.not_converged)
    status = Status.where(implausible(eu.rotations, eu.shapes, eu.translations, fac.W_hat), Status.implausible, status)
    # Too few of the entries the fit relies on (the inliers it kept; every observed entry
    # for a baseline) to determine a frame's motion or a point's structure: the fit
    # cannot be trusted.
    used = visible if method.fits_every_entry else fac.inliers
    starved = jnp.any(used.sum(1) < rank) | jnp.any(2 * used.sum(0) < rank)
    starved |= used.sum() < 0.5 * visible.sum()
    if method.judges_detection:
        # More rejected than the method survives (the median scale breaks down at half),
        # or kept residuals that do not look like noise.
        starved |= used.sum() < (1 - MAX_REJECTED) * visible.sum()
        errors = entry_errors(W, fac.W_hat)
        model = residuals.fit(errors, visible, residuals.scale_floor(W, visible))
        starved |= residuals.misfit(errors, used, model) > MISFIT
        starved |= model.sigma > SCALE_RATIO * centred_spread(W, visible)
    status = Status.where(starved, Status.too_many_outliers, status)
    return Status.where(finite, status, Status.nonfinite)


def filled_tracks(
    W: Float[Array, "2m n"], inliers: Bool[Array, "m n"], W_hat: Float[Array, "2m n"]
) -> Float[Array, "2m n"]:
    """The tracks that the rotation and shape stages see: the observed inliers, the rejected
    and missing entries interpolated along their tracks where the tracks predict them
    better than the fit's typical residual (`jaxnrsfm.temporal.interpolate`; motion
    capture), elsewhere the fit's values ``W_hat``.

    Why: the high-rank rotations (`jaxnrsfm.stages.HighRankRotations`) need every entry,
    and the fit's rank-``3k + 1`` values lack the deformation's tail they rely on. On the
    Akhter sequences with 30% of the entries hidden the fit's values were 0.007--0.015 off
    (RMS of the entries' lengths), the interpolation 0.00007--0.0012. The filled entries
    stay unobserved for the rotations: the fill starts their first solve and the refills
    from the shapes replace it (see `reconstruct_prepared`)."""
    filled = jnp.where(row_mask(inliers), W, W_hat)
    return temporal.interpolate(filled, inliers, residuals.masked_median(entry_errors(W, W_hat), inliers))[0]


@eqx.filter_jit
def reconstruct_prepared(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    *,
    k: int,
    method: OutlierStrategy,
    rotations: RotationRecovery,
    shapes: ShapeStep,
    solver: MaskedALS,
    form: Literal["augmented", "registered"] = "augmented",
    complete: bool = False,
) -> Reconstruction:
    """`reconstruct` on tracks already checked by `prepare_tracks` (zero-filled,
    with their effective mask) and stage instances already checked against them: the pure,
    jit-compiled pipeline that a batch vmaps. ``complete`` (static) says every entry is
    observed."""
    rank = 3 * k + (form == "augmented")
    if form == "registered":
        # Eq. 8: each frame centred on its visible centroid, then a rank-3k fit.
        t = centroids(W, visible)
        fac = method(
            jnp.where(row_mask(visible), W - t.reshape(-1)[:, None], 0.0),
            visible,
            rank=rank,
            complete=complete,
            solver=solver,
        )
        fac = finish(W, fac.inliers, fac.M, fac.S, t, fac.steps, fac.converged)
        M, S, t = fac.M, fac.S, fac.translations
    else:
        fac = method(W, visible, rank=rank, complete=complete, solver=solver)
        M, S, t, _ = split_translation(fac.M, fac.S)
    # The metric upgrade only where a stage reads it: the default stages do not, and on the
    # paper's cube it was ~15% of the default pipeline's tracing.
    upgrade = metric_upgrade(M, S, t, k) if rotations.needs_upgrade or shapes.needs_upgrade else None
    # The shapes explain the observed inliers, not the rank-3k+1 fit (with wang on the
    # Akhter sequences e3D fell by 0.4--4%, drink 0.0384 from the fit, 0.0368 from the
    # inliers); elsewhere the filled values (filled_tracks) only place each frame's centroid
    # and complete the tracks for the rotations.
    # The rotations are told which entries were observed, not which were interpolated: the
    # refills of the high-rank rotations then replace the interpolated values with the
    # projections of their shapes. Counting the interpolated entries as observed (no
    # refills) was the rule before the camera prior. On the Akhter sequences with 10%
    # outliers or 30% missing (``benchmarks/real_sequences.py --seeds 4``: 20 runs of each)
    # e3D moved from clean by -1.7%..+18.1% and -2.5%..+41.4% that way (4 runs beyond
    # +10% and +20%), by -5.0%..+11.3% and -2.3%..+18.9% with the refills (1 run).
    # Known at trace time to have every entry: no mask, nothing to fill, and no refills of
    # the rotations.
    if complete and isinstance(method, Direct):
        frames, observed = to_frames(W), None
    else:
        frames, observed = to_frames(filled_tracks(W, fac.inliers, fac.W_hat)), fac.inliers
    R = rotations(frames - frames.mean(axis=2, keepdims=True), observed, k=k, upgrade=upgrade, M=M)
    eu = shapes.euclidean(frames, R, observed, k=k, upgrade=upgrade)
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
        status_of(W, visible, fac, eu, rank, method),
    )


ONE_CALL_OPTIONS = {"xla_backend_optimization_level": 0, "xla_cpu_use_fusion_emitters": False}
"""XLA options of the program that a single `reconstruct` call compiles on a CPU: LLVM's
lowest optimisation level and XLA:CPU's older fusion emitters. A single call's time is
mostly compilation, and these compile the pipeline 4-5 times faster for a run about twice
as slow. Measured on a 2-core CPU (on a slow day: one NumPy SVD of a 200 x 252 matrix
14.7 ms), XLA's defaults against these, compile and run: the default call on yoga's first
150 frames (k = 2) 34.6 + 2.7 s against 7.0 + 3.8 s; on the paper's 100-frame cube
(k = 4, 10% outliers) 37.4 + 2.5 s against 7.7 + 4.9 s, and with ``shapes="upgrade"``
30.5 + 0.70 s against 5.8 + 1.27 s; the same e3D to the digit. Many trials of one size
run faster through `jaxnrsfm.reconstruct_batch` and the sweeps, which keep XLA's
defaults, as does `reconstruct` under an outer ``jax.jit`` (whose options rule) and on an
accelerator."""

_reconstruct_once = eqx.filter_jit(reconstruct_prepared.__wrapped__, compiler_options=ONE_CALL_OPTIONS)


def _compiled_for_one_call(*inputs):
    # Only a call on concrete arrays outside any transformation: a jit staged into another
    # program (under jax.jit, lax.scan, or reverse-mode differentiation, which stages the
    # forward pass) may not carry compiler options of its own, and a transformed call is
    # part of a larger computation. Under a staging trace even a constant is a tracer.
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((inputs, jnp.zeros(()))))
    return reconstruct_prepared if traced or jax.default_backend() != "cpu" else _reconstruct_once


def _stage(value, table: dict, base: type, what: str):
    # A stage given by its command-line name (default options) or as an instance.
    if isinstance(value, base):
        return value
    if isinstance(value, str) and value in table:
        return table[value]()
    raise ValueError(f"unknown {what} {value!r}; choose one of {', '.join(table)} or a {base.__name__} instance")


def resolve_stages(
    method: "str | OutlierStrategy",
    rotations: "str | RotationRecovery | None",
    shapes: "str | ShapeStep",
    solver: MaskedALS | None,
    form: str = "augmented",
) -> dict:
    """The stage instances of a pipeline, from names or instances, checked against each
    other (a ``ValueError``): the keyword arguments of `reconstruct_prepared`.
    ``rotations=None`` takes the shape step's
    `jaxnrsfm.stages.ShapeStep.default_rotations`."""
    if method == "oracle":
        raise ValueError("method 'oracle' needs the true outliers: pass method=Oracle(outliers)")
    method = _stage(method, STRATEGIES, OutlierStrategy, "method")
    shapes = _stage(shapes, SHAPES, ShapeStep, "shape step")
    rotations = shapes.default_rotations() if rotations is None else rotations
    rotations = _stage(rotations, ROTATIONS, RotationRecovery, "rotation recovery")
    solver = MaskedALS() if solver is None else solver
    if not isinstance(solver, MaskedALS):
        raise ValueError(f"solver must be a MaskedALS instance; got {solver!r}")
    if form not in FORMS:
        raise ValueError(f"unknown form {form!r}; choose one of {', '.join(FORMS)}")
    if form == "registered" and not isinstance(method, Direct):
        raise ValueError(
            f"form='registered' supports only the direct fit; {type(method).__name__} needs the augmented form"
        )
    shapes.check_rotations(rotations)
    return dict(method=method, rotations=rotations, shapes=shapes, solver=solver, form=form)


def check_stages(stages: dict, shape: tuple[int, int], k: int) -> None:
    """Check the stages of `resolve_stages` against tracks of ``shape = (m, n)`` with
    ``k`` bases (a ``ValueError`` before anything is compiled)."""
    stages["method"].check(shape)
    stages["rotations"].check(shape, k)


def reconstruct(
    W: ArrayLike,
    visible: ArrayLike | None = None,
    *,
    k: int | None = None,
    method: "str | OutlierStrategy" = "wang",
    rotations: "str | RotationRecovery | None" = None,
    shapes: "str | ShapeStep" = "nuclear",
    solver: MaskedALS | None = None,
    form: Literal["augmented", "registered"] = "augmented",
) -> Reconstruction:
    """Reconstruct a nonrigid object from its tracks.

    A reconstruction is a composition of stages (`jaxnrsfm.stages`), each an
    ``eqx.Module`` whose fields are its options: the outlier strategy's low-rank fit with
    the missing-data solver, the metric upgrade, a rotation recovery and a shape step.
    Each is given as an instance, or by name with its default options. The defaults are
    the configuration measured best on real tracks (``benchmarks/real_sequences.py``):
    ``k`` chosen from the tracks (`jaxnrsfm.choose_k` with ``robust=True``), the
    paper's robust algorithm (`jaxnrsfm.stages.Wang`), rotations from the rotation
    constraints on a high-rank factorization of the tracks
    (`jaxnrsfm.stages.HighRankRotations`) and Dai et al.'s nuclear-norm shapes
    (`jaxnrsfm.stages.NuclearShapes`). The paper's own pipeline -- factorization
    and metric upgrade, shapes ``H^-1 S`` -- is ``shapes="upgrade"``.

    **Arguments:**

    - `W`: tracks ``(2m, n)``; rows ``2i, 2i+1`` are u, v of frame ``i``; NaN = missing.
    - `visible`: optional ``(m, n)`` mask of observed entries.
    - `k`: number of shape bases (1 = rigid); ``None`` (the default) chooses it from the
      tracks, `jaxnrsfm.choose_k` with ``robust=True`` (needs concrete tracks:
      under ``jit`` or ``vmap`` give ``k``).
    - `method`: the outlier strategy (`jaxnrsfm.stages.OutlierStrategy`):
      ``"wang"`` / ``Wang(...)`` (the default) is the paper's robust algorithm;
      ``"direct"`` fits every observed entry by least squares; ``"huynh"`` is Huynh et
      al.'s pseudo-observation correction; ``"ke_kanade"`` Ke & Kanade's L1 factorization
      by alternating linear programs; ``"huber"`` and ``"l1"`` minimise the Huber or L1
      loss of the reprojection residuals with optimistix; ``Oracle(outliers)`` is least
      squares told the true outliers.
    - `rotations`: the rotation recovery (`jaxnrsfm.stages.RotationRecovery`):
      ``"high_rank"``, ``"upgrade"`` (the metric upgrade's own) or ``"trace_norm"``;
      ``None`` (the default): the shape step's choice (high-rank for the nuclear-norm
      shapes, the upgrade's for its own shapes).
    - `shapes`: the shape step (`jaxnrsfm.stages.ShapeStep`): ``"nuclear"`` (the
      default) or ``"upgrade"`` (the paper's ``H^-1 S``, with the upgrade's rotations only).
    - `solver`: the missing-data solver, `jaxnrsfm.stages.MaskedALS` (its budget,
      and whether VarPro finishes the least-squares fits).
    - `form`: ``"augmented"`` (the paper's rank-(3k+1) factorization, eq. 12, no
      registration; the default) or ``"registered"`` (rank 3k after centring each frame
      on its visible centroid, eq. 8; the direct fit only).

    **Returns:** a `Reconstruction`; its ``status`` reports, per trial, a solver
    that did not converge, more outliers than the data can lose, or implausible shapes.

    **Raises:** ``ValueError`` (before any compilation) for malformed tracks, an unknown
    stage or form, a ``k`` too large for the data, or options that do not suit the tracks.
    """
    if form not in FORMS:
        raise ValueError(f"unknown form {form!r}; choose one of {', '.join(FORMS)}")
    if k is None:
        if isinstance(W, jax.core.Tracer) or isinstance(visible, jax.core.Tracer):
            raise ValueError("k=None chooses k from the tracks, which needs concrete arrays: under jit/vmap give k")
        k = choose_k(W, visible, robust=True)
    if not isinstance(k, int) or isinstance(k, bool) or k < 1:
        raise ValueError(f"k (the number of shape bases) must be a positive integer; got {k!r}")
    rank = 3 * k + (form == "augmented")
    W0, vis = prepare_tracks(W, visible, rank=rank, rank_name=f"k={k} ({form} rank {rank})")
    stages = resolve_stages(method, rotations, shapes, solver, form)
    check_stages(stages, vis.shape, k)
    complete = not isinstance(vis, jax.core.Tracer) and bool(vis.all())
    run = _compiled_for_one_call(W0, vis, stages)
    if run is reconstruct_prepared:  # part of a larger computation, or on an accelerator
        return run(W0, vis, k=k, complete=complete, **stages)
    return compute_single_threaded(run, W0, vis, k=k, complete=complete, **stages)
