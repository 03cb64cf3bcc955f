import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnrsfm as nr


def test_cube_layout(key):
    seq = nr.deformable_cube(key, n_frames=100)
    assert seq.W.shape == (200, 252) and seq.shapes.shape == (100, 3, 252)
    assert seq.bases.shape == (4, 3, 252) and seq.weights.shape == (100, 4)
    # 153 rigid points never move; the 99 others (3 sets of 33) do.
    motion = jnp.ptp(seq.shapes, axis=0).max(axis=0)
    assert int(jnp.sum(motion == 0)) == 153 and int(jnp.sum(motion > 1.0)) == 99
    # outward: every moving point is farther from the centre than at rest
    rest = seq.bases[0]
    dist = jnp.linalg.norm(seq.shapes, axis=1) - jnp.linalg.norm(rest, axis=0)
    assert bool(jnp.all(dist[:, 153:] >= -1e-9))
    # orthographic cameras: W_clean = R_i[:2] S_i + c_i, inside the 800 x 800 image
    proj = jnp.einsum("iab,ibn->ian", seq.rotations[:, :2], seq.shapes) + seq.translations[:, :, None]
    np.testing.assert_allclose(nr.from_frames(proj), seq.W_clean, atol=1e-9)
    assert float(seq.W_clean.min()) > 0 and float(seq.W_clean.max()) < 800
    # the rank is exactly 3k + 1 = 13 (3k = 12 after registration)
    s = jnp.linalg.svd(seq.W_clean, compute_uv=False)
    assert float(s[12] / s[0]) > 1e-6 and float(s[13] / s[0]) < 1e-12


def test_noise_outliers_missing_counts(key):
    seq = nr.deformable_cube(key, noise=2.0, outlier_ratio=0.1, missing_ratio=0.2)
    n_entries = 100 * 252
    n_visible = int(seq.visible.sum())
    assert n_visible == n_entries - round(0.2 * n_entries)
    assert int(seq.outliers.sum()) == round(0.1 * n_visible)
    assert not bool(jnp.any(seq.outliers & ~seq.visible))
    assert bool(jnp.all(jnp.isnan(nr.to_frames(seq.W)).all(axis=1) == ~seq.visible))
    err = nr.entry_errors(jnp.nan_to_num(seq.W), seq.W_clean)
    inlier = seq.visible & ~seq.outliers
    # inliers: Gaussian noise, sigma 2 per coordinate; outliers: 20 to 100 units away, give or take the noise
    assert abs(float(jnp.sqrt(jnp.mean(err[inlier] ** 2) / 2)) - 2.0) < 0.05
    assert float(err[seq.outliers].min()) > 20 - 6 * 2 and float(err[seq.outliers].max()) < 100 + 6 * 2


def test_injector_on_real_style_tracks(key):
    W = jnp.zeros((8, 30))
    W2, outliers = nr.inject_outliers(key, W, None, 0.25, magnitude=(20.0, 100.0))
    lengths = nr.entry_errors(W2, W)
    assert int(outliers.sum()) == 30  # a quarter of 4 frames x 30 points
    assert bool(jnp.all((lengths[outliers] >= 20) & (lengths[outliers] <= 100)))
    assert bool(jnp.all(lengths[~outliers] == 0))


def test_generators_vmap(key):
    keys = jax.random.split(key, 5)
    seqs = jax.jit(jax.vmap(lambda k: nr.bregler_sequence(k, k=3, n_frames=12, n_points=10, noise=1.0)))(keys)
    assert seqs.W.shape == (5, 24, 10)
    one = nr.bregler_sequence(keys[3], k=3, n_frames=12, n_points=10, noise=1.0)
    np.testing.assert_allclose(seqs.W[3], one.W, rtol=1e-12)
    rot = seqs.rotations
    np.testing.assert_allclose(
        jnp.einsum("tiab,tiac->tibc", rot, rot), jnp.broadcast_to(jnp.eye(3), rot.shape), atol=1e-12
    )


def test_articulated_figure_moves_rigid_bones():
    seq = nr.articulated_sequence(jax.random.key(0), n_frames=30)
    assert seq.W.shape == (60, 41) and seq.shapes.shape == (30, 3, 41)
    assert seq.weights is None and seq.bases is None
    proj = jnp.einsum("iab,ibn->ian", seq.rotations[:, :2], seq.shapes) + seq.translations[:, :, None]
    np.testing.assert_allclose(nr.from_frames(proj), seq.W_clean, atol=1e-9)
    # The first 17 points are the joints: every bone keeps its length while the figure moves.
    for child, (parent, offset, _) in enumerate(nr.synthetic.SKELETON):
        if parent >= 0:
            length = jnp.linalg.norm(seq.shapes[:, :, child] - seq.shapes[:, :, parent], axis=1)
            np.testing.assert_allclose(length, np.linalg.norm(offset), rtol=1e-12)
    assert float(jnp.ptp(seq.shapes[:, :, 6] - seq.shapes[:, :, 0], axis=0).max()) > 5.0  # the elbow moves
    # The orbiting camera turns steadily about the vertical; a panning one swings back.
    steps = jnp.einsum("iab,iab->i", seq.rotations[1:], seq.rotations[:-1])
    assert bool(jnp.all(steps < 3 - 1e-4))
    pan = nr.articulated_sequence(jax.random.key(0), n_frames=30, camera="pan")
    np.testing.assert_allclose(pan.shapes, seq.shapes)
    with pytest.raises(ValueError, match="camera must be"):
        nr.articulated_sequence(jax.random.key(0), camera="handheld")
