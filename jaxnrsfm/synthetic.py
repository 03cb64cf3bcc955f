"""Synthetic nonrigid sequences with ground truth: the paper's deformable cube (section
5.1), random Bregler sequences, an articulated figure like motion capture, and the noise /
outlier / missing-data injectors.

Every generator is a pure function of a PRNG key, so a Monte Carlo batch is
``jax.vmap(partial(deformable_cube, ...))(jax.random.split(key, trials))``. Each is
jit-compiled, its sizes and dtype static: called op by op, a first call dispatched some 70
small programs, each compiled on its own (the cube 1.5-2.0 s, a Bregler sequence 1.7-2.1 s;
compiled as one, 0.7 and 0.8 s). Compiled, the generators' tracks differ from the op-by-op
ones in the last bits (XLA fuses their arithmetic); the injectors' are the same to the bit.

Cameras are orthographic with unit scale (``x_ij = R_i[:2] X_j + c_i``): world units are
image units. A general affine camera admits no Euclidean upgrade, and under a per-frame
scale the Bregler weights absorb the scale, so unit-scale orthographic cameras are the
family in which the ground-truth shapes are recoverable exactly.
"""

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray

from .camera import rotation_exp
from .tracks import from_frames, row_mask

IMAGE_SIZE = 800.0
"""Side of the square image of the paper's experiments, in image units."""
CUBE_HALF_WIDTH = 100.0
"""Half the side of the synthetic cube, in world (= image) units."""


class SyntheticSequence(eqx.Module):
    """Observed tracks and the ground truth that produced them."""

    W: Float[Array, "2m n"]
    """Observed tracks: noisy, with outliers, NaN where missing."""
    visible: Bool[Array, "m n"]
    """Observed entries."""
    W_clean: Float[Array, "2m n"]
    """Noise-free, outlier-free, complete tracks."""
    shapes: Float[Array, "m 3 n"]
    """True 3-D shape of every frame, ``sum_l weights[i, l] bases[l]``."""
    rotations: Float[Array, "m 3 3"]
    """True camera rotations; the camera of frame ``i`` is ``rotations[i, :2]``."""
    translations: Float[Array, "m 2"]
    """True image translations ``c_i``."""
    weights: Float[Array, "m k"] | None
    """True deformation weights (``None`` for `articulated_sequence`, which no Bregler
    model describes)."""
    bases: Float[Array, "k 3 n"] | None
    """True shape bases (``None`` for `articulated_sequence`)."""
    outliers: Bool[Array, "m n"]
    """Entries displaced by the outlier injector."""
    noise: Float[Array, ""]
    """Standard deviation of the Gaussian noise on each coordinate."""


@partial(jax.jit, static_argnames=("m", "dtype"))
def random_rotations(key: PRNGKeyArray, m: int, dtype=None) -> Float[Array, "m 3 3"]:
    """``m`` rotations drawn uniformly from SO(3) (normalised Gaussian quaternions)."""
    q = jax.random.normal(key, (m, 4), dtype=dtype)
    w, x, y, z = (q / jnp.linalg.norm(q, axis=1, keepdims=True)).T
    return jnp.stack(
        [
            jnp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            jnp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            jnp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


def _choose(key: PRNGKeyArray, candidates: Bool[Array, "m n"], ratio) -> Bool[Array, "m n"]:
    """Exactly ``round(ratio * #candidates)`` candidate entries, uniformly at random."""
    u = jnp.where(candidates, jax.random.uniform(key, candidates.shape), 2.0)
    rank = jnp.argsort(jnp.argsort(u.ravel())).reshape(u.shape)
    return rank < jnp.round(ratio * candidates.sum())


@jax.jit
def inject_outliers(
    key: PRNGKeyArray,
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"] | None = None,
    ratio: float = 0.1,
    *,
    magnitude: tuple[float, float] = (20.0, 100.0),
) -> tuple[Float[Array, "2m n"], Bool[Array, "m n"]]:
    """Displace a fraction of the observed entries far beyond the noise.

    Exactly ``round(ratio * #visible)`` (frame, point) entries are chosen uniformly at
    random among the visible ones; each has both coordinates moved by a vector of
    uniformly random direction and length uniform in ``magnitude`` (image units; on
    the paper's 800x800 image, 20 to 100). Works on real tracks as well as synthetic.

    **Returns:** ``(W_with_outliers, outlier_mask)``.
    """
    if visible is None:
        visible = jnp.ones((W.shape[0] // 2, W.shape[1]), bool)
    k_pick, k_dir, k_len = jax.random.split(key, 3)
    chosen = _choose(k_pick, visible, ratio)
    angle = jax.random.uniform(k_dir, chosen.shape, W.dtype, 0.0, 2 * jnp.pi)
    length = jax.random.uniform(k_len, chosen.shape, W.dtype, *magnitude)
    step = from_frames(jnp.stack([jnp.cos(angle), jnp.sin(angle)], axis=1) * length[:, None])
    return W + jnp.where(row_mask(chosen), step, 0.0), chosen


@jax.jit
def drop_entries(key: PRNGKeyArray, visible: Bool[Array, "m n"], ratio: float) -> Bool[Array, "m n"]:
    """Hide exactly ``round(ratio * #visible)`` visible entries, chosen uniformly."""
    return visible & ~_choose(key, visible, ratio)


def _observe(key, shapes, rotations, translations, weights, bases, noise, outlier_ratio, missing_ratio):
    proj = jnp.einsum("iab,ibn->ian", rotations[:, :2], shapes) + translations[:, :, None]
    W_clean = from_frames(proj)
    k_noise, k_miss, k_out = jax.random.split(key, 3)
    visible = drop_entries(k_miss, jnp.ones(shapes[:, 0].shape, bool), missing_ratio)
    W = W_clean + noise * jax.random.normal(k_noise, W_clean.shape, W_clean.dtype)
    W, outliers = inject_outliers(k_out, W, visible, outlier_ratio)
    W = jnp.where(row_mask(visible), W, jnp.nan)
    return SyntheticSequence(
        W,
        visible,
        W_clean,
        shapes,
        rotations,
        translations,
        weights,
        bases,
        outliers,
        jnp.asarray(noise, W.dtype),
    )


def _random_translations(key, m, dtype):
    return IMAGE_SIZE / 2 + jax.random.uniform(key, (m, 2), dtype, -100.0, 100.0)


def _cube_geometry() -> tuple[np.ndarray, np.ndarray]:
    """The cube at rest (3 x 252) and its three outward deformation modes (3 x 3 x 252).

    153 rigid points: 17 evenly spaced points inside each of the nine edges that do not
    meet at the corner shared by the three deforming faces. 99 moving points: a disc of
    33 points (1 + 8 + 12 + 12 on rings of radius 0, h/4, h/2, 3h/4) centred on each of
    the faces +x, +y, +z, which moves outward along the rays from the cube's centre: the
    disc's points are scaled by ``1 + d(t)``, so each mode is a full-rank 3 x n basis
    (a displacement along the face normal alone would be rank one and the sequence's
    rank would fall below ``3k``).
    """
    h = CUBE_HALF_WIDTH
    t = np.linspace(-h, h, 19)[1:-1]
    rigid = []
    for axis in range(3):  # edges parallel to `axis`, at the four (+-h, +-h) positions
        others = [a for a in range(3) if a != axis]
        for s1 in (-h, h):
            for s2 in (-h, h):
                if s1 > 0 and s2 > 0:
                    continue  # edge shared by two deforming faces
                p = np.zeros((3, t.size))
                p[axis], p[others[0]], p[others[1]] = t, s1, s2
                rigid.append(p)
    rigid = np.concatenate(rigid, axis=1)
    radii = np.concatenate([[0.0], np.full(8, h / 4), np.full(12, h / 2), np.full(12, 3 * h / 4)])
    angles = np.concatenate(
        [
            [0.0],
            np.arange(8) * 2 * np.pi / 8,
            np.arange(12) * 2 * np.pi / 12,
            (np.arange(12) + 0.5) * 2 * np.pi / 12,
        ]
    )
    discs, modes = [], np.zeros((3, 3, 153 + 99))
    for face in range(3):
        others = [a for a in range(3) if a != face]
        p = np.zeros((3, 33))
        p[face] = h
        p[others[0]], p[others[1]] = radii * np.cos(angles), radii * np.sin(angles)
        discs.append(p)
        start = 153 + 33 * face
        modes[face, :, start : start + 33] = p
    return np.concatenate([rigid, *discs], axis=1), modes


@partial(jax.jit, static_argnames=("n_frames", "dtype"))
def deformable_cube(
    key: PRNGKeyArray,
    *,
    n_frames: int = 100,
    noise: float = 0.0,
    outlier_ratio: float = 0.0,
    missing_ratio: float = 0.0,
    dtype=None,
) -> SyntheticSequence:
    """The paper's deformable cube (section 5.1) seen by random orthographic cameras.

    252 points: 153 rigid points on the cube's edges and three sets of 33 points on
    three adjacent faces that move outward from the cube's centre, each set scaled by
    ``1 + d_l(t)`` with its own random smooth timing (``0 <= d_l(t) <= 0.8``). That is a
    Bregler model with ``k = 4``: the cube at rest with weight 1 and the three outward
    modes with weights ``d_l``. Each frame has a
    uniformly random rotation and a translation placing the cube inside the 800x800
    image. Gaussian noise of standard deviation ``noise`` is added to every coordinate;
    then ``missing_ratio`` of the entries are hidden and ``outlier_ratio`` of the
    visible ones are displaced by `inject_outliers`.
    """
    dtype = dtype or jnp.result_type(float)
    rest, modes = _cube_geometry()
    bases = jnp.asarray(np.concatenate([rest[None], modes]), dtype)
    k_rot, k_t, k_freq, k_phase, k_obs = jax.random.split(key, 5)
    time = jnp.arange(n_frames, dtype=dtype) / n_frames
    freq = jax.random.uniform(k_freq, (3,), dtype, 0.5, 2.0)
    phase = jax.random.uniform(k_phase, (3,), dtype, 0.0, 2 * jnp.pi)
    bulge = 0.4 * (1 - jnp.cos(2 * jnp.pi * freq * time[:, None] + phase))
    weights = jnp.concatenate([jnp.ones((n_frames, 1), dtype), bulge], axis=1)
    shapes = jnp.einsum("il,lan->ian", weights, bases)
    rotations = random_rotations(k_rot, n_frames, dtype)
    translations = _random_translations(k_t, n_frames, dtype)
    return _observe(k_obs, shapes, rotations, translations, weights, bases, noise, outlier_ratio, missing_ratio)


@partial(jax.jit, static_argnames=("k", "n_frames", "n_points", "dtype"))
def bregler_sequence(
    key: PRNGKeyArray,
    *,
    k: int,
    n_frames: int,
    n_points: int,
    noise: float = 0.0,
    outlier_ratio: float = 0.0,
    missing_ratio: float = 0.0,
    dtype=None,
) -> SyntheticSequence:
    """A random Bregler sequence: ``k`` Gaussian bases, random rotations and weights.

    The first basis is a mean shape with weight 1 in every frame; the others deform
    it with Gaussian weights of standard deviation 0.3. A dominant mean shape is what
    makes the per-frame sign of a Bregler reconstruction identifiable: ``(w_i, R_i)``
    and ``(-w_i, diag(-1, -1, 1) R_i)`` project identically, and the library resolves
    the choice by the signs under which one rigid shape explains the tracks best
    (`jaxnrsfm.upgrade.frame_signs`).
    ``k = 1`` is a rigid object. Bases have a standard deviation of 50 image units.
    """
    dtype = dtype or jnp.result_type(float)
    k_b, k_w, k_rot, k_t, k_obs = jax.random.split(key, 5)
    bases = 50.0 * jax.random.normal(k_b, (k, 3, n_points), dtype)
    bases = bases - bases.mean(axis=2, keepdims=True)
    deform = 0.3 * jax.random.normal(k_w, (n_frames, k - 1), dtype)
    weights = jnp.concatenate([jnp.ones((n_frames, 1), dtype), deform], axis=1)
    shapes = jnp.einsum("il,lan->ian", weights, bases)
    rotations = random_rotations(k_rot, n_frames, dtype)
    translations = _random_translations(k_t, n_frames, dtype)
    return _observe(k_obs, shapes, rotations, translations, weights, bases, noise, outlier_ratio, missing_ratio)


SKELETON = (
    (-1, (0.0, 0.0, 0.0), 0.0),  # 0 pelvis: the root, still in the world frame
    (0, (0.0, 25.0, 0.0), 0.25),  # 1 spine
    (1, (0.0, 25.0, 0.0), 0.25),  # 2 chest
    (2, (0.0, 15.0, 0.0), 0.3),  # 3 neck
    (3, (0.0, 12.0, 0.0), 0.3),  # 4 head
    (2, (18.0, 8.0, 0.0), 0.8),  # 5-7 left shoulder, elbow, wrist
    (5, (0.0, -28.0, 0.0), 1.0),
    (6, (0.0, -25.0, 0.0), 0.5),
    (2, (-18.0, 8.0, 0.0), 0.8),  # 8-10 right arm
    (8, (0.0, -28.0, 0.0), 1.0),
    (9, (0.0, -25.0, 0.0), 0.5),
    (0, (10.0, -5.0, 0.0), 0.6),  # 11-13 left hip, knee, ankle
    (11, (0.0, -42.0, 0.0), 0.8),
    (12, (0.0, -42.0, 0.0), 0.3),
    (0, (-10.0, -5.0, 0.0), 0.6),  # 14-16 right leg
    (14, (0.0, -42.0, 0.0), 0.8),
    (15, (0.0, -42.0, 0.0), 0.3),
)
"""The articulated figure's joints: (parent, offset from the parent joint at rest in
world units ~ cm, the amplitude of the joint's rotation in radians)."""


@partial(jax.jit, static_argnames=("n_frames", "camera", "dtype"))
def articulated_sequence(
    key: PRNGKeyArray,
    *,
    n_frames: int = 250,
    camera: str = "orbit",
    noise: float = 0.0,
    outlier_ratio: float = 0.0,
    missing_ratio: float = 0.0,
    dtype=None,
) -> SyntheticSequence:
    """A moving human-like figure with 41 markers, like motion capture, seen by a moving
    orthographic camera: nonrigid data with ground truth that no Bregler model describes.

    A 17-joint skeleton (`SKELETON`, ~170 units tall). Each joint turns about its parent
    by a rotation vector mixed at random from 3 latent smooth signals (sums of two
    sinusoids of periods 60-250 frames), half its amplitude in `SKELETON`: movements are
    coordinated, as a body's are. The markers: the 17 joints, 4 on the pelvis and 4 on the
    chest (a 3-D torso, 16 units deep), and 16 on random limb segments with 4-unit skin
    offsets; every marker but the joints wobbles on its bone by 0.1 units (periods 20-100
    frames). Made to resemble Akhter's sequences (measured on keys 0-3): the shapes' RMS
    deviation from the mean shape is 0.20-0.31 of its RMS (Akhter: 0.13-0.27) and the
    deviations' singular values fall like Akhter's (the 4th, 7th and 11th at 0.11-0.27,
    0.02-0.05 and 0.00-0.01 of the first; Akhter 0.09-0.19, 0.04-0.08, 0.02-0.03).

    ``camera``: ``"orbit"``, turning about the vertical at 2.5-7.5 degrees a frame with its
    tilt (within 20 degrees) wobbling by 5 degrees, or ``"pan"``, swinging 60 degrees
    either way about the vertical (periods 100-200 frames). The pelvis stands still in the
    world frame: the ground truth's ``shapes`` are in it. The image drifts smoothly by up to
    100 units. Noise, missing entries and outliers as in `deformable_cube`; ``weights`` and
    ``bases`` are ``None``.
    """
    dtype = dtype or jnp.result_type(float)
    if camera not in ("orbit", "pan"):
        raise ValueError(f"camera must be 'orbit' or 'pan'; got {camera!r}")
    keys = iter(jax.random.split(key, 16))
    t = jnp.arange(n_frames, dtype=dtype)
    joints = len(SKELETON)

    def waves(key, shape, shortest, longest):
        # sin(2 pi t / period + phase), one per element of ``shape``, over the frames.
        k1, k2 = jax.random.split(key)
        period = jax.random.uniform(k1, shape, dtype, shortest, longest)
        phase = jax.random.uniform(k2, shape, dtype, 0.0, 2 * jnp.pi)
        return jnp.sin(2 * jnp.pi * t.reshape(-1, *([1] * len(shape))) / period + phase)

    latent = waves(next(keys), (3, 2), 60.0, 250.0).sum(-1) / jnp.sqrt(2.0)  # (m, 3)
    amplitude = 0.5 * jnp.asarray([a for _, _, a in SKELETON], dtype)
    mix = jax.random.normal(next(keys), (joints, 3, 3), dtype) / jnp.sqrt(3.0) * amplitude[:, None, None]
    local = rotation_exp(jnp.einsum("jaq,iq->ija", mix, latent))  # (m, joints, 3, 3)
    frames, positions = [], []
    for j, (parent, offset, _) in enumerate(SKELETON):
        if parent < 0:
            frames.append(local[:, j])
            positions.append(jnp.zeros((n_frames, 3), dtype))
        else:
            frames.append(frames[parent] @ local[:, j])
            positions.append(positions[parent] + frames[parent] @ jnp.asarray(offset, dtype))
    G, P = jnp.stack(frames, 1), jnp.stack(positions, 1)  # (m, joints, 3, 3), (m, joints, 3)

    # Markers on bones: (joint whose frame carries it, offset in that frame).
    torso = [(0, (sx * 12.0, 0.0, sz * 8.0)) for sx in (-1, 1) for sz in (-1, 1)]
    torso += [(2, (sx * 15.0, 10.0, sz * 8.0)) for sx in (-1, 1) for sz in (-1, 1)]
    torso_bone = jnp.asarray([b for b, _ in torso])
    torso_offset = jnp.asarray([o for _, o in torso], dtype) + jax.random.normal(next(keys), (8, 3), dtype)
    # A limb marker lies on a joint's segment towards one child (the last listed, where a
    # joint has several: the pelvis's towards the right hip, the chest's the right shoulder).
    segment = {parent: child for child, (parent, _, _) in enumerate(SKELETON) if parent >= 0}
    bones = sorted(segment)
    pick = jax.random.choice(next(keys), len(bones), (16,))
    limb_bone = jnp.asarray(bones)[pick]
    towards = jnp.asarray([SKELETON[segment[b]][1] for b in bones], dtype)[pick]
    along = jax.random.uniform(next(keys), (16, 1), dtype, 0.2, 0.8) * towards
    limb_offset = along + 4.0 * jax.random.normal(next(keys), (16, 3), dtype)
    bone = jnp.concatenate([torso_bone, limb_bone])
    offset = jnp.concatenate([torso_offset, limb_offset])[None] + 0.1 * waves(next(keys), (24, 3), 20.0, 100.0)
    markers = P[:, bone] + jnp.einsum("imab,imb->ima", G[:, bone], offset)
    shapes = jnp.swapaxes(jnp.concatenate([P, markers], 1), 1, 2)
    shapes = shapes - shapes.mean(axis=2, keepdims=True)

    up = jnp.asarray([0.0, 1.0, 0.0], dtype)
    start = jax.random.uniform(next(keys), (), dtype, 0.0, 2 * jnp.pi)
    if camera == "orbit":
        direction = jnp.where(jax.random.bernoulli(next(keys)), 1.0, -1.0)
        speed = jnp.radians(5.0) * jax.random.uniform(next(keys), (), dtype, 0.5, 1.5)
        yaw = start + direction * speed * t
        tilt = jnp.radians(
            jax.random.uniform(next(keys), (), dtype, -20.0, 20.0) + 5.0 * waves(next(keys), (), 100.0, 300.0)
        )
    else:
        yaw = start + jnp.radians(60.0) * waves(next(keys), (), 100.0, 200.0)
        tilt = jnp.zeros_like(t)
    rotations = rotation_exp(tilt[:, None] * jnp.asarray([1.0, 0.0, 0.0], dtype)) @ rotation_exp(yaw[:, None] * up)
    # The image drifts smoothly (+-100 units, periods 100-300 frames), as a tracked subject
    # does: with the cube's random jumps no track is smooth in time and the temporal prior
    # (jaxnrsfm.temporal) could never act, as it does on motion capture.
    translations = IMAGE_SIZE / 2 + 100.0 * waves(next(keys), (2,), 100.0, 300.0)
    return _observe(next(keys), shapes, rotations, translations, None, None, noise, outlier_ratio, missing_ratio)
