"""The rotation stage: each frame's camera rotation, given the factorization and its
metric upgrade.

Three recoveries: the metric upgrade's own (`UpgradeRotations`, the paper's),
the rotation constraints on a high-rank factorization of the tracks
(`HighRankRotations`, the default for real tracks) and Dai, Li & He's trace-norm
relaxation (`TraceNormRotations`). The kernels live in `jaxnrsfm.refine` and
`jaxnrsfm.upgrade`. A new recovery subclasses `RotationRecovery`.
"""

import abc
from typing import ClassVar, Literal

import equinox as eqx
import jax
from jaxtyping import Array, Bool, Float

from ..camera import camera_prior
from ..refine import high_rank_rotations, trace_norm_triple
from ..tracks import to_frames
from ..upgrade import Euclidean, flip_frames, frame_signs, nearest_rotations


class RotationRecovery(eqx.Module):
    """The contract of the rotation stage.

    ``__call__(frames, observed, *, k, upgrade, M)`` takes the centred tracks per frame
    ``(m, 2, n)`` (observed inliers; missing and rejected entries interpolated along their
    tracks or, where the tracks are not smooth in time, the fit's values:
    `jaxnrsfm.pipeline.filled_tracks`), the mask of the observed inliers (``None``: all),
    the number of shape bases,
    the metric upgrade (`jaxnrsfm.Euclidean`) and the centred affine motion ``M``
    ``(2m, 3k)`` it came from, and returns rotations ``(m, 3, 3)``: frame ``i`` projects
    with ``rotations[i, :2]``, in the frame sign (reflection) that fits the tracks. Pure
    and jit-compatible.

    ``upgrade`` is ``None`` where neither stage of the pipeline uses it (`needs_upgrade`
    False for both): the pipeline then does not compute it."""

    needs_upgrade: ClassVar[bool] = True
    """Whether ``__call__`` reads the metric upgrade (a recovery of one's own: True unless
    it says otherwise)."""

    @abc.abstractmethod
    def __call__(
        self,
        frames: Float[Array, "m 2 n"],
        observed: Bool[Array, "m n"] | None,
        *,
        k: int,
        upgrade: Euclidean,
        M: Float[Array, "2m 3k"],
    ) -> Float[Array, "m 3 3"]:
        """The rotations (see the class docstring)."""

    def check(self, shape: tuple[int, int], k: int) -> None:
        """Raise ``ValueError`` for options that do not suit tracks of ``shape = (m, n)``
        and ``k`` bases (called before anything is compiled). Nothing by default."""


class UpgradeRotations(RotationRecovery):
    """The metric upgrade's rotations (Gauss--Newton on the rotation constraints in the
    rank-``3k`` motion space, `jaxnrsfm.metric_upgrade`): the paper's. Differentiable."""

    def __call__(self, frames, observed, *, k, upgrade, M):
        return upgrade.rotations


class HighRankRotations(RotationRecovery):
    """The rotation constraints on a high-rank factorization of the centred tracks
    (`jaxnrsfm.refine.high_rank_rotations`): in a high-rank space the constraints can
    pick a combination of points that the deformation barely moves, where the rank-``3k``
    motion space leaks the deformation ``k`` bases do not explain. Unobserved and rejected
    entries (and, with `held_out`, a fraction of the others) are refilled from the
    nuclear-norm shapes and the rotations solved again. Then,
    by default, the camera turning at a constant angular velocity nearest to them where they
    follow one (`jaxnrsfm.camera.camera_prior`). Not tested for gradients."""

    needs_upgrade: ClassVar[bool] = False

    rank: int | None = None
    """Rank of the factorization; ``None`` (the default): every direction of the tracks
    above the noise (`jaxnrsfm.refine.above_noise`), at least ``3k``. At most
    ``min(2m, n - 1)``."""
    starts: int = 16
    """Random starts of the Gauss--Newton solve for the rotation triple."""
    refills: int = 2
    """Refills of the unobserved entries from the shapes, each followed by a new solve."""
    steps: int = 500
    """ADMM iterations of the refills' nuclear-norm shapes."""
    held_out: float = 0.0
    """Fraction of the entries, a fixed pseudo-random set, that the rotation solve sees only
    through the refills from the shapes, as it sees the unobserved ones (``0``, the
    default: every observed entry as it is). Where the body has exactly rigid parts the
    rotation constraints have an exact solution for each, and on complete tracks the solve
    can land on one; an entry predicted by the low-rank shapes under the current rotations
    is exact for no single part. On `jaxnrsfm.articulated_sequence` (rigid bones; keys 0-5,
    orbiting and panning cameras; `benchmarks/synthetic_mocap.py`) ``0.1`` lowered e3D on
    11 of 12, e.g. 0.6603 -> 0.0868, 0.6049 -> 0.1194, 0.8745 -> 0.2509 (pan key 2: 0.2686
    -> 0.3178); on Akhter's sequences, whose markers sit on skin, it cost a little clean
    (0.0238 / 0.0428 / 0.0324 / 0.0443 / 0.1648 -> 0.0240 / 0.0435 / 0.0328 / 0.0460 /
    0.1638) and more with outliers (yoga +33.7% on one injection, where it had +2.0%): not
    the default."""
    camera: Literal["constant_velocity", "free"] = "constant_velocity"
    """The camera's motion: ``"constant_velocity"`` (the default) takes the camera turning
    at a constant angular velocity nearest to the recovered rotations where they stray from
    it by at most `jaxnrsfm.camera.MAX_TURN` degrees, the object's own turning going to the
    shapes (`jaxnrsfm.camera`; Akhter's sequences: e3D 0.0263 / 0.1554 / 0.0962 / 0.1114 /
    0.1740 -> 0.0238 / 0.0428 / 0.0324 / 0.0443 / 0.1649, drink, pickup, yoga, stretch,
    dance); ``"free"`` keeps the frame in which the points' rigid combination stands still."""

    def __check_init__(self):
        if self.rank is not None and not (isinstance(self.rank, int) and self.rank >= 1):
            raise ValueError(f"rank must be None or a positive integer; got {self.rank!r}")
        for name in ("starts", "steps"):
            if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
                raise ValueError(f"{name} must be a positive integer; got {getattr(self, name)!r}")
        if not (isinstance(self.refills, int) and self.refills >= 0):
            raise ValueError(f"refills must be a non-negative integer; got {self.refills!r}")
        if not 0 <= self.held_out < 1:
            raise ValueError(f"held_out must be in [0, 1); got {self.held_out!r}")
        if self.camera not in ("constant_velocity", "free"):
            raise ValueError(f"camera must be 'constant_velocity' or 'free'; got {self.camera!r}")

    def check(self, shape, k):
        m, n = shape
        if self.rank is not None and self.rank > (top := min(2 * m, n - 1)):
            raise ValueError(f"rotation rank {self.rank} exceeds the centred tracks' rank, min(2m, n - 1) = {top}")

    def __call__(self, frames, observed, *, k, upgrade, M):
        # Where the shape step made the pipeline compute the upgrade, the data dependency on
        # it orders these LAPACK calls after its own: two independent batched LAPACK calls
        # in one jit can deadlock on the CPU backend.
        if self.held_out > 0:
            m, _, n = frames.shape
            shown = jax.random.uniform(jax.random.key(0), (m, n), frames.dtype) >= self.held_out
            observed = shown if observed is None else observed & shown
        R = high_rank_rotations(
            frames if upgrade is None else frames + 0.0 * upgrade.metric_residual,
            self.rank,
            observed,
            min_rank=3 * k,
            starts=self.starts,
            refills=self.refills,
            steps=self.steps,
        )
        return camera_prior(R) if self.camera == "constant_velocity" else R


class TraceNormRotations(RotationRecovery):
    """A rotation triple from Dai, Li & He's trace-norm relaxation of the rotation
    constraints on the upgrade's motion matrix (`jaxnrsfm.refine.trace_norm_triple`)."""

    weight: float = 0.1
    """Weight of the trace norm against the constraints' misfit."""

    def __check_init__(self):
        if not self.weight > 0:
            raise ValueError(f"the trace-norm weight must be > 0; got {self.weight!r}")

    def __call__(self, frames, observed, *, k, upgrade, M):
        M = M + 0.0 * upgrade.metric_residual  # ordered after the upgrade (see HighRankRotations)
        R = nearest_rotations(to_frames(M) @ trace_norm_triple(M, weight=self.weight))
        return flip_frames(R, frame_signs(R, frames))


ROTATIONS: dict[str, type[RotationRecovery]] = {
    "upgrade": UpgradeRotations,
    "high_rank": HighRankRotations,
    "trace_norm": TraceNormRotations,
}
"""The built-in rotation recoveries by the names the command line uses."""
