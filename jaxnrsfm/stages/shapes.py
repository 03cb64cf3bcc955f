"""The shape stage: per-frame 3-D shapes given the rotations.

Two steps: Dai, Li & He's nuclear-norm shapes (`NuclearShapes`, the default for
real tracks: the least nuclear norm of the deformations that reproject exactly onto the
observed inliers' part above the noise) and the paper's own, ``H^-1 S`` from the metric upgrade
(`UpgradeShapes`). A shape prior of one's own subclasses `ShapeStep` and
implements ``__call__``; the pipeline puts its shapes in the canonical gauge
(`jaxnrsfm.upgrade.euclidean_from_shapes`).
"""

import abc
from typing import ClassVar

import equinox as eqx
from jaxtyping import Array, Bool, Float

from ..refine import above_noise_part, nuclear_shapes
from ..upgrade import Euclidean, euclidean_from_shapes
from .rotations import HighRankRotations, RotationRecovery, UpgradeRotations


class ShapeStep(eqx.Module):
    """The contract of the shape stage.

    ``__call__(frames, rotations, observed, *, upgrade)`` takes the centred tracks per
    frame ``(m, 2, n)`` (values where ``observed`` is False are the fit's, not data), the
    rotations ``(m, 3, 3)``, the mask of the observed inliers (``None``: all) and the
    metric upgrade, and returns shapes ``(m, 3, n)`` whose projections
    ``rotations[i, :2] @ shapes[i]`` explain the observed tracks. Pure and jit-compatible.

    `euclidean` turns them into the reconstruction's `jaxnrsfm.Euclidean`
    (translations, canonical gauge, principal bases); `default_rotations` is the
    rotation recovery a pipeline uses with this step when none is given. ``upgrade`` is
    ``None`` where neither stage of the pipeline uses it (`needs_upgrade` False for both):
    the pipeline then does not compute it."""

    needs_upgrade: ClassVar[bool] = True
    """Whether the step reads the metric upgrade (a step of one's own: True unless it says
    otherwise)."""

    @abc.abstractmethod
    def __call__(
        self,
        frames: Float[Array, "m 2 n"],
        rotations: Float[Array, "m 3 3"],
        observed: Bool[Array, "m n"] | None,
        *,
        upgrade: Euclidean,
    ) -> Float[Array, "m 3 n"]:
        """The shapes (see the class docstring)."""

    def default_rotations(self) -> RotationRecovery:
        """The rotation recovery used with this step when a pipeline names none."""
        return HighRankRotations()

    def check_rotations(self, rotations: RotationRecovery) -> None:
        """Raise ``ValueError`` if this step cannot take its rotations from ``rotations``."""

    def euclidean(
        self,
        tracks: Float[Array, "m 2 n"],
        rotations: Float[Array, "m 3 3"],
        observed: Bool[Array, "m n"] | None,
        *,
        k: int,
        upgrade: Euclidean,
    ) -> Euclidean:
        """The reconstruction from uncentred ``tracks``: this step's shapes in the
        canonical gauge, with ``k`` principal bases."""
        centred = tracks - tracks.mean(axis=2, keepdims=True)
        shapes = self.fit(centred, rotations, observed, k=k, upgrade=upgrade)
        return euclidean_from_shapes(rotations, shapes, tracks, k, observed)

    def fit(
        self,
        frames: Float[Array, "m 2 n"],
        rotations: Float[Array, "m 3 3"],
        observed: Bool[Array, "m n"] | None,
        *,
        k: int,
        upgrade: Euclidean | None,
    ) -> Float[Array, "m 3 n"]:
        """The shapes for ``k`` shape bases: ``__call__`` by default; a step that does not
        read the upgrade (`needs_upgrade` False) overrides this to work from ``k``."""
        return self(frames, rotations, observed, upgrade=upgrade)


class NuclearShapes(ShapeStep):
    """Dai, Li & He's shapes (BMM): of least nuclear norm of their deviations from the
    mean shape, projecting exactly onto the observed inliers (``denoise``: onto their
    part above the noise); unobserved and rejected entries are left free
    (`jaxnrsfm.refine.nuclear_shapes`). With the true rotations e3D 0.03--0.05 on the
    Akhter sequences: the rotations limit accuracy.

    Denoised, the shapes fit the signal instead of reprojecting the noise: with the true
    rotations, random Bregler sequences at sigma 1 (k = 2, 40 x 30) 0.027 -> 0.015; with
    the default's rotations, on 8 synthetic sequences with 10% outliers (the 40-frame cube
    at sigma 2, Bregler k = 2, 3 at sigma 1, 0.5) better in every one, 0.050 -> 0.044 on
    average (`shapes="upgrade"`: 0.060); the Akhter
    sequences' first 150 frames with noise 1% of their RMS: yoga 0.0439 -> 0.0401, pickup
    0.1472 -> 0.1463, stretch 0.1241 -> 0.1235. On motion capture's exact projections
    the part above the noise is nearly all (drink 0.0262 -> 0.0263; the others unchanged)."""

    needs_upgrade: ClassVar[bool] = False

    steps: int = 500
    """ADMM iterations (a fixed count: jit- and vmap-friendly)."""
    rho: float = 1.0
    """ADMM penalty, relative to the tracks normalised to unit RMS."""

    denoise: bool = True
    """Fit the tracks' part above the noise (`jaxnrsfm.refine.above_noise_part`, at least
    ``3k`` directions) instead of the tracks themselves."""

    def __check_init__(self):
        if not (isinstance(self.steps, int) and self.steps >= 1) or not self.rho > 0:
            raise ValueError(f"steps must be a positive integer and rho > 0; got {self.steps!r}, {self.rho!r}")
        if not isinstance(self.denoise, bool):
            raise ValueError(f"denoise must be True or False; got {self.denoise!r}")

    def __call__(self, frames, rotations, observed, *, upgrade):
        # k is the upgrade's: its weights are (m, k).
        return self.fit(frames, rotations, observed, k=upgrade.weights.shape[-1], upgrade=upgrade)

    def fit(self, frames, rotations, observed, *, k, upgrade):
        # The pipeline computes no upgrade for this step (needs_upgrade): k alone.
        if self.denoise:
            frames = above_noise_part(frames, 3 * k)
        return nuclear_shapes(frames, rotations, observed, steps=self.steps, rho=self.rho)


class UpgradeShapes(ShapeStep):
    """The paper's shapes, ``S_i = sum_l w_il B_l`` with ``B = H^-1 S`` from the metric
    upgrade (`jaxnrsfm.metric_upgrade`), in the upgrade's own gauge. They belong to
    the upgrade's rotations, so this step takes only `UpgradeRotations`.
    Differentiable."""

    def default_rotations(self):
        return UpgradeRotations()

    def check_rotations(self, rotations):
        if not isinstance(rotations, UpgradeRotations):
            raise ValueError(
                "UpgradeShapes are the metric upgrade's own and need its rotations (UpgradeRotations); "
                f"got {type(rotations).__name__}"
            )

    def __call__(self, frames, rotations, observed, *, upgrade):
        return upgrade.shapes

    def euclidean(self, tracks, rotations, observed, *, k, upgrade):
        return upgrade


SHAPES: dict[str, type[ShapeStep]] = {"nuclear": NuclearShapes, "upgrade": UpgradeShapes}
"""The built-in shape steps by the names the command line uses."""
