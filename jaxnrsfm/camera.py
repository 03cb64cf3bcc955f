"""A prior on the camera's motion: a camera turning at a constant angular velocity.

A factorization fixes each frame's rotation only up to the split between the camera's
motion and the object's own turning: ``R_i S_i = (R_i Q_i) (Q_i^T S_i)`` for any rotations
``Q_i``, and both explain the tracks equally. The high-rank rotations
(`jaxnrsfm.refine.high_rank_rotations`) take the frame in which a rigid combination of the
points stands still. On motion capture that is not the frame of the ground truth: the
subject turns a little in the room (drink, pickup, yoga, stretch: the recovered rotations
0.3, 5.4, 3.2 and 3.3 degrees off the true cameras on average), and that error varies slowly
(averaging the rotations over 3--9 neighbouring frames changed neither it nor e3D). It is
the shape step's largest error: with the true rotations e3D is 0.024--0.043 on these four.

The prior: the camera turns at a constant angular velocity, ``R_i = exp(t_i [w]_x) R_0``
(an orbit, a turntable, or a static camera, ``w = 0``), and the object's turning beyond it
belongs to the shapes. Its estimate (`constant_velocity`) is closed-form and robust to the
object's turning: ``w`` is the median of the frame-to-frame rotation vectors
``log(R_{i+1} R_i^T)``, ``R_0`` the rotation nearest to ``sum_i exp(t_i [w]_x)^T R_i``.
(A least-squares fit of both, Levenberg--Marquardt from that estimate, gave the same e3D or
worse on 11 of the 15 Akhter sequences and halves, e.g. yoga 0.0473 against 0.0324, and
compiled in 1.3 s.)

Where the recovered rotations stray from the fitted trajectory by more than `MAX_TURN`
(median over the frames) the camera does not follow it -- a panning or hand-held camera,
frames in no temporal order -- and they are kept (`camera_prior`).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .upgrade import nearest_rotations

MAX_TURN = 20.0
"""Largest median angle, in degrees, between the recovered rotations and the fitted
constant-velocity camera at which `camera_prior` adopts the camera: the object's own
turning it takes into the shapes. Measured (median angle): Akhter's sequences and their
halves 0.2--11.9 (pickup's first half); `jaxnrsfm.articulated_sequence` under an orbiting
camera whose tilt wobbles by 5 degrees 7.5--31.2 (keys 0-5; taken at 7.5, 10.2 and 19.3,
e3D 0.2291 -> 0.2028, 0.2100 -> 0.0898, 0.3132 -> 0.1965: ``benchmarks/synthetic_mocap.py``),
under a camera panning +-60 degrees, which the prior would misread, 26.0--77.9; random
cameras (Bregler sequences) 112--128."""


def _skew(v: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    zero = jnp.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return jnp.stack([jnp.stack([zero, -z, y], -1), jnp.stack([z, zero, -x], -1), jnp.stack([-y, x, zero], -1)], -2)


def rotation_exp(v: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    """The rotations ``exp([v]_x)`` of rotation vectors ``v`` (Rodrigues' formula)."""
    angle2 = jnp.sum(v * v, axis=-1)[..., None, None]
    small = angle2 < jnp.finfo(v.dtype).eps
    angle = jnp.sqrt(jnp.where(small, 1.0, angle2))
    # Taylor series near zero: the closed forms divide by the angle, and their derivative too.
    sinc = jnp.where(small, 1 - angle2 / 6, jnp.sin(angle) / angle)
    cosc = jnp.where(small, 0.5 - angle2 / 24, (1 - jnp.cos(angle)) / jnp.where(small, 1.0, angle2))
    K = _skew(v)
    return jnp.eye(3, dtype=v.dtype) + sinc * K + cosc * K @ K


def rotation_log(R: Float[Array, "... 3 3"]) -> Float[Array, "... 3"]:
    """The rotation vectors ``v`` with ``exp([v]_x) = R``, angles in ``[0, pi)``."""
    half = jnp.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1) / 2
    sine2 = jnp.sum(half * half, axis=-1)
    small = sine2 < jnp.finfo(R.dtype).eps
    sine = jnp.sqrt(jnp.where(small, 1.0, sine2))
    cosine = (jnp.trace(R, axis1=-2, axis2=-1) - 1) / 2
    # angle / sin(angle) from atan2, which is accurate at every angle (arccos is not near 0).
    ratio = jnp.where(small, 1.0, jnp.arctan2(sine, cosine) / sine)
    return half * ratio[..., None]


def constant_velocity(rotations: Float[Array, "m 3 3"]) -> Float[Array, "m 3 3"]:
    """The camera turning at a constant angular velocity nearest to ``rotations``:
    ``exp(t_i [w]_x) R_0`` (``t_i`` frames from the middle one) with ``w`` the median
    frame-to-frame rotation vector and ``R_0`` the rotation nearest to
    ``sum_i exp(t_i [w]_x)^T R_i`` (module docstring)."""
    m = rotations.shape[0]
    steps = rotation_log(rotations[1:] @ jnp.swapaxes(rotations[:-1], -1, -2))
    w = jnp.median(steps, axis=0)
    # Time from the middle frame: an error in w moves the frames by at most m / 2 times it.
    turn = rotation_exp((jnp.arange(m, dtype=rotations.dtype) - (m - 1) / 2)[:, None] * w)
    # sum_i turn_i^T R_i is R_0 times the frame count when the rotations follow the model;
    # the orthonormal pair nearest to its first two rows (and their cross product) is R_0.
    mean = jnp.einsum("iba,ibc->ac", turn, rotations)
    return turn @ nearest_rotations(mean[None, :2])[0]


def turning(rotations: Float[Array, "m 3 3"], camera: Float[Array, "m 3 3"]) -> Float[Array, " m"]:
    """The angle, in degrees, of each frame's rotation from ``camera``'s: the object's own
    turning under that camera."""
    return jnp.degrees(jnp.linalg.norm(rotation_log(rotations @ jnp.swapaxes(camera, -1, -2)), axis=-1))


def camera_prior(rotations: Float[Array, "m 3 3"], max_turn: float = MAX_TURN) -> Float[Array, "m 3 3"]:
    """The constant-velocity camera nearest to ``rotations`` (`constant_velocity`) where
    they stray from it by at most ``max_turn`` degrees (median over the frames), else
    ``rotations`` unchanged. The choice is discrete: a constant to the gradient."""
    camera = constant_velocity(rotations)
    adopt = jnp.median(turning(*jax.lax.stop_gradient((rotations, camera)))) <= max_turn
    return jnp.where(adopt, camera, rotations)
