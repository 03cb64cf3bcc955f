"""The outlier stage: how a reconstruction's low-rank fit treats the observed entries.

Every strategy is an `OutlierStrategy`: an ``eqx.Module`` whose fields are its
options (documented under each), called on prepared tracks to give a
`jaxnrsfm.factorize.Factorization` whose ``inliers`` say which observed entries
it kept. The algorithms live in `jaxnrsfm.robust` (and `jaxnrsfm.factorize`
for the direct fit); a strategy is their configuration and their contract with the
pipeline. To add a robust loss, subclass `OutlierStrategy` and implement
``__call__``; `jaxnrsfm.reconstruct`, ``jax.vmap`` and ``jax.grad`` take it as
they take the built-in ones.
"""

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .. import robust
from ..factorize import Factorization, factorize_prepared
from .solver import MaskedALS


def _positive_or_none(name: str, value) -> None:
    if value is not None and not isinstance(value, jax.core.Tracer) and not value > 0:
        raise ValueError(f"{name} must be > 0 (or None); got {value!r}")


def _positive_int(name: str, value) -> None:
    if not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
        raise ValueError(f"{name} must be a positive integer; got {value!r}")


def _robust_loss(W, visible, rank, complete, solver, delta, threshold):
    # The Huber loss (delta in robust scales), or the L1 loss for delta None.
    return robust.huber(
        W,
        visible,
        rank=rank,
        complete=complete,
        delta=delta,
        threshold=threshold,
        solver=solver.least_squares,
        **solver.budget,
    )


class OutlierStrategy(eqx.Module):
    """The contract of the outlier stage.

    ``__call__(W, visible, *, rank, complete, solver)`` takes zero-filled tracks ``W``
    ``(2m, n)`` with their mask ``visible`` ``(m, n)`` (as
    `jaxnrsfm.prepare_tracks` returns them), the rank of the fit (``3k + 1`` for the
    augmented form, with the translations in ``M``'s last column), whether every entry
    is observed (static: ``True`` allows the plain SVD) and the missing-data
    `jaxnrsfm.stages.MaskedALS`, and returns the fit as a
    `jaxnrsfm.factorize.Factorization` (``translations`` zero: the pipeline
    separates them). It must be pure and jit-compatible, and must not raise on data: a
    fit that fails says so in ``converged`` (the pipeline turns that into the
    `jaxnrsfm.Status`). Where it is differentiable is its own docstring's to say.

    Two class variables tell the pipeline's status how to judge the result
    (`jaxnrsfm.pipeline.status_of`)."""

    judges_detection: ClassVar[bool] = False
    """The fit relies on the inliers it detected: its status also fails when it rejected
    more than the method survives or its kept residuals do not look like noise."""
    fits_every_entry: ClassVar[bool] = False
    """The fit uses every observed entry (its ``inliers`` are reported for comparison):
    its status checks that every frame and point has enough observations, not inliers."""

    @abc.abstractmethod
    def __call__(
        self, W: Float[Array, "2m n"], visible: Bool[Array, "m n"], *, rank: int, complete: bool, solver: MaskedALS
    ) -> Factorization:
        """The fit of ``W`` at ``rank`` (see the class docstring)."""

    def check(self, shape: tuple[int, int]) -> None:
        """Raise ``ValueError`` for options that do not suit tracks of ``shape = (m, n)``
        (called before anything is compiled). Nothing to check by default."""


class Direct(OutlierStrategy):
    """Least squares on every observed entry: no outlier handling (the paper's "direct"
    factorization). Differentiable in ``W`` (the SVD, or the missing-data fit through the
    implicit function theorem)."""

    fits_every_entry: ClassVar[bool] = True

    def __call__(self, W, visible, *, rank, complete, solver):
        return factorize_prepared(
            W, visible, rank=rank, register=False, complete=complete, solver=solver.least_squares, **solver.budget
        )


class Wang(OutlierStrategy):
    """The paper's robust algorithm (section 4.2, steps 1--5): rejection passes of a
    growing rank with soft Cauchy weights, inliers by the heavy-tailed residual model,
    rejected entries taken back where their own track predicts them, and a final weighted
    fit of the inliers (`jaxnrsfm.robust.wang`). Its inlier set is a constant to
    the gradient; the final fit and its weights are differentiated."""

    judges_detection: ClassVar[bool] = True
    threshold: float | None = None
    """Outlier threshold as a multiple of the robust residual scale; ``None`` (the
    default) takes the residual model's Bayes boundary (`jaxnrsfm.residuals`)."""
    passes: int = 3
    """Minimum number of rejection passes."""
    weighted: bool = True
    """Step 5's weighted factorization of the inliers (per-frame and per-point variances)."""

    def __check_init__(self):
        _positive_or_none("threshold", self.threshold)
        _positive_int("passes", self.passes)

    def __call__(self, W, visible, *, rank, complete, solver):
        return robust.wang(
            W,
            visible,
            rank=rank,
            complete=complete,
            threshold=self.threshold,
            passes=self.passes,
            weighted=self.weighted,
            **solver.budget,
        )


class Huynh(OutlierStrategy):
    """Huynh, Hartley & Heyden (2003): pseudo observations whose residuals are clipped at a
    decreasing multiple of the robust scale (`jaxnrsfm.robust.huynh`). A baseline:
    its status is its own iteration's convergence."""

    fits_every_entry: ClassVar[bool] = True
    iterations: int = 10
    """Correction iterations (the clipping falls from 6 to 2.5 robust scales over them)."""

    def __check_init__(self):
        _positive_int("iterations", self.iterations)

    def __call__(self, W, visible, *, rank, complete, solver):
        return robust.huynh(W, visible, rank=rank, complete=complete, iterations=self.iterations, **solver.budget)


class KeKanade(OutlierStrategy):
    """Ke & Kanade (2005): the L1 factorization by alternating linear programs
    (`jaxnrsfm.robust.ke_kanade`). A baseline: its status is its own convergence;
    ``threshold`` only sets which entries it reports as outliers."""

    fits_every_entry: ClassVar[bool] = True
    threshold: float | None = None
    """Multiple of the robust scale beyond which an entry is reported as an outlier;
    ``None``: the residual model's boundary."""

    def __check_init__(self):
        _positive_or_none("threshold", self.threshold)

    def __call__(self, W, visible, *, rank, complete, solver):
        return robust.ke_kanade(W, visible, rank=rank, complete=complete, threshold=self.threshold)


class Huber(OutlierStrategy):
    """The Huber loss of the reprojection residuals' lengths, minimised by optimistix's
    Levenberg--Marquardt from the least-squares fit (`jaxnrsfm.robust.huber`).
    Differentiable in ``W`` and in ``delta`` (which may be a traced array)."""

    judges_detection: ClassVar[bool] = True
    delta: float | Float[Array, ""] = 1.345
    """The loss's kink, in robust residual scales (1.345: 95% efficient under Gaussian noise)."""
    threshold: float | None = None
    """Multiple of the robust scale beyond which an entry is reported as an outlier;
    ``None``: the residual model's boundary."""

    def __check_init__(self):
        if not isinstance(self.delta, jax.Array) and not self.delta > 0:
            raise ValueError(f"the Huber parameter delta must be > 0; got {self.delta!r}")
        _positive_or_none("threshold", self.threshold)

    def __call__(self, W, visible, *, rank, complete, solver):
        return _robust_loss(W, visible, rank, complete, solver, self.delta, self.threshold)


class L1(OutlierStrategy):
    """The L1 loss of the reprojection residuals' lengths: the Huber loss with a kink far
    below the noise (`jaxnrsfm.objective.L1_DELTA` robust scales), minimised like
    `Huber`."""

    judges_detection: ClassVar[bool] = True
    threshold: float | None = None
    """Multiple of the robust scale beyond which an entry is reported as an outlier;
    ``None``: the residual model's boundary."""

    def __check_init__(self):
        _positive_or_none("threshold", self.threshold)

    def __call__(self, W, visible, *, rank, complete, solver):
        return _robust_loss(W, visible, rank, complete, solver, None, self.threshold)


class Oracle(OutlierStrategy):
    """Least squares told the true outliers: the best any outlier rejection can do, the
    yardstick of the paper's comparison (`jaxnrsfm.robust.oracle`)."""

    outliers: Bool[Array, "m n"] = eqx.field(converter=jnp.asarray)
    """The true outlier mask (an array: under ``jax.vmap`` one per trial)."""

    def check(self, shape):
        if tuple(self.outliers.shape) != tuple(shape):
            raise ValueError(f"Oracle's outliers must have shape (m, n) = {tuple(shape)}; got {self.outliers.shape}")

    def __call__(self, W, visible, *, rank, complete, solver):
        return robust.oracle(
            W, visible, self.outliers.astype(bool), rank=rank, solver=solver.least_squares, **solver.budget
        )


STRATEGIES: dict[str, type[OutlierStrategy]] = {
    "direct": Direct,
    "wang": Wang,
    "huynh": Huynh,
    "ke_kanade": KeKanade,
    "huber": Huber,
    "l1": L1,
    "oracle": Oracle,
}
"""The built-in strategies by the names the command line and sweeps use."""
