"""The factorizations and the metric upgrade against the ground truth."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnrsfm as nr
from jaxnrsfm.factorize import masked_als, motion_given_structure, structure_given_motion

FORMS = ("augmented", "registered")
PAPER = dict(method="direct", shapes="upgrade")
DEFAULT_DIRECT = nr.pipeline.resolve_stages("direct", None, "nuclear", None)
"""The paper's pipeline: least squares, metric upgrade, shapes H^-1 S."""


def _check_exact(seq, k, form):
    rec = nr.reconstruct(seq.W, k=k, form=form, **PAPER)
    assert bool(rec.status == nr.Status.success)
    # M S (+ translations) reproduces W to 1e-9 relative
    rel = jnp.linalg.norm(rec.W_hat - seq.W) / jnp.linalg.norm(seq.W)
    assert float(rel) < 1e-9
    fit = rec.M @ rec.S + (0.0 if form == "augmented" else nr.from_frames(rec.translations[:, :, None]))
    assert float(jnp.linalg.norm(fit - seq.W) / jnp.linalg.norm(seq.W)) < 1e-9
    # Euclidean shapes match the truth, and the Euclidean model reprojects exactly
    assert float(nr.e3d(rec.shapes, seq.shapes)) < 1e-6
    assert float(jnp.abs(rec.reproject() - seq.W).max()) < 1e-6 * float(jnp.abs(seq.W).max())
    # every rotation orthonormal (and proper) to 1e-8
    RtR = jnp.einsum("iab,iac->ibc", rec.rotations, rec.rotations)
    assert float(jnp.abs(RtR - jnp.eye(3)).max()) < 1e-8
    assert float(jnp.abs(jnp.linalg.det(rec.rotations) - 1).max()) < 1e-8
    # the Bregler decomposition is consistent with the shapes
    np.testing.assert_allclose(jnp.einsum("il,lan->ian", rec.weights, rec.bases), rec.shapes, atol=1e-8)
    assert float(rec.metric_residual) < 1e-6


@pytest.mark.parametrize("form", FORMS)
def test_noise_free_cube_exact(form):
    _check_exact(nr.deformable_cube(jax.random.key(3)), 4, form)


@pytest.mark.parametrize("k", [1, 2, 3, 4])
@pytest.mark.parametrize("form", FORMS)
def test_noise_free_bregler_exact(k, form):
    seq = nr.bregler_sequence(jax.random.key(10 + k), k=k, n_frames=40, n_points=30)
    _check_exact(seq, k, form)


def test_rotations_match_truth_up_to_one_orthogonal_transform():
    seq = nr.bregler_sequence(jax.random.key(7), k=3, n_frames=40, n_points=30)
    rec = nr.reconstruct(seq.W, k=3, **PAPER)
    # The cameras R_i[:2] equal R_true_i[:2] Q for one orthogonal Q: the world frame is
    # arbitrary, and orthographic projection cannot tell a shape from its mirror image
    # (det Q = -1), whose proper rotations then differ from the truth in the third row.
    X, Y = rec.rotations[:, :2].reshape(-1, 3), seq.rotations[:, :2].reshape(-1, 3)
    U, _, Vt = jnp.linalg.svd(X.T @ Y)
    # Noise-free, the upgrade's alternation of rotations and triples stalls at a metric
    # residual of about 1e-8 (the exact rotations would give 1e-15), and the cameras
    # then agree to about 2e-7, by a margin that moves with the CPU's round-off.
    np.testing.assert_allclose(rec.rotations[:, :2] @ (U @ Vt), seq.rotations[:, :2], atol=1e-6)


def test_eq14_error_difference_is_next_singular_value(key):
    """E_3k - E_3k+1 = sigma_{3k+1}^2 (eq. 14) on complete noisy data."""
    k = 4
    seq = nr.deformable_cube(key, noise=2.0)
    s = jnp.linalg.svd(seq.W, compute_uv=False)
    E3k = nr.factorize(seq.W, rank=3 * k).cost
    E3k1 = nr.factorize(seq.W, rank=3 * k + 1).cost
    np.testing.assert_allclose(E3k - E3k1, s[3 * k] ** 2, rtol=1e-8)
    np.testing.assert_allclose(E3k1, jnp.sum(s[3 * k + 1 :] ** 2), rtol=1e-8)
    # the registered rank-3k fit leaves the tail of the centred matrix's spectrum
    reg = nr.factorize(seq.W, rank=3 * k, form="registered")
    sc = jnp.linalg.svd(seq.W - seq.W.mean(axis=1, keepdims=True), compute_uv=False)
    np.testing.assert_allclose(reg.cost, jnp.sum(sc[3 * k :] ** 2), rtol=1e-8)


def test_complete_noisy_data_reaches_statistical_floor(key):
    seq = nr.deformable_cube(key, noise=2.0)
    for form, rank in (("augmented", 13), ("registered", 12)):
        rec = nr.reconstruct(seq.W, k=4, form=form, **PAPER)
        err = nr.rms_error(seq.W_clean, rec.W_hat, jnp.ones((100, 252), bool))
        floor = nr.statistical_floor(2.0, 100, 252, rank)
        assert 0.9 * float(floor) < float(err) < 1.1 * float(floor)


def test_augmented_beats_registered_with_missing_data():
    """With missing entries the visible centroid is wrong and registration suffers.

    Over five trials the augmented factorization's 3-D error is lower in every trial,
    and on average its 2-D error against the noise-free tracks (missing entries
    included) and its 3-D error are both well below the registered one's. (In a single
    trial the registered 2-D fit can absorb much of the centroid error and come close.)
    """
    rms, e3d = {f: [] for f in FORMS}, {f: [] for f in FORMS}
    for seed in range(5):
        seq = nr.deformable_cube(jax.random.key(seed), noise=2.0, missing_ratio=0.2)
        for form in FORMS:
            rec = nr.reconstruct(seq.W, k=4, form=form, **PAPER)
            rms[form].append(float(nr.rms_error(seq.W_clean, rec.W_hat, ~seq.outliers)))
            e3d[form].append(float(nr.e3d(rec.shapes, seq.shapes)))
    assert all(a < r for a, r in zip(e3d["augmented"], e3d["registered"], strict=True))
    assert np.mean(e3d["augmented"]) < 0.5 * np.mean(e3d["registered"])
    assert np.mean(rms["augmented"]) < 0.8 * np.mean(rms["registered"])


def test_vmap_equals_loop():
    """25 small trials with missing data: vmap of the pipeline == a Python loop of it."""
    keys = jax.random.split(jax.random.key(5), 25)

    def make(key):
        return nr.bregler_sequence(key, k=2, n_frames=20, n_points=20, noise=1.0, missing_ratio=0.1)

    seqs = jax.vmap(make)(keys)
    batched = jax.vmap(lambda W, v: nr.reconstruct(W, v, k=2, **PAPER))(seqs.W, seqs.visible)
    ok = batched.status == nr.Status.success
    assert int(jnp.sum(ok)) >= 23
    for t in range(25):
        one = nr.reconstruct(seqs.W[t], seqs.visible[t], k=2, **PAPER)
        assert bool(one.status == nr.Status.success) == bool(ok[t])
        if not ok[t]:
            continue  # an unconverged iterate depends on round-off; its status agrees
        scale = float(jnp.abs(one.shapes).max())
        np.testing.assert_allclose(batched.W_hat[t], one.W_hat, rtol=1e-9, atol=1e-9 * scale)
        np.testing.assert_allclose(batched.shapes[t], one.shapes, rtol=1e-6, atol=1e-6 * scale)
        np.testing.assert_allclose(batched.rotations[t], one.rotations, atol=1e-6)


def test_failing_trial_does_not_poison_batch():
    seqs = jax.vmap(lambda key: nr.bregler_sequence(key, k=1, n_frames=10, n_points=12, noise=0.5))(
        jax.random.split(jax.random.key(2), 4)
    )

    def run(W):
        return jax.vmap(lambda W, v: nr.reconstruct_prepared(W, v, k=1, complete=True, **DEFAULT_DIRECT))(
            W, seqs.visible
        )

    # A NaN that slipped past validation (the prepared entry point trusts its input):
    # trial 1 reports it, the others are untouched.
    recs, clean = run(seqs.W.at[1, 3, 4].set(jnp.nan)), run(seqs.W)
    assert list(recs.status == nr.Status.nonfinite) == [False, True, False, False]
    others = jnp.array([0, 2, 3])
    np.testing.assert_array_equal(recs.W_hat[others], clean.W_hat[others])
    np.testing.assert_array_equal(recs.shapes[others], clean.shapes[others])


def test_pipeline_traces_under_jit():
    seq = nr.bregler_sequence(jax.random.key(1), k=2, n_frames=20, n_points=20, noise=0.5, missing_ratio=0.1)
    eager = nr.reconstruct(seq.W, seq.visible, k=2, **PAPER)
    jitted = jax.jit(lambda W, v: nr.reconstruct(W, v, k=2, **PAPER))(seq.W, seq.visible)
    scale = float(jnp.abs(eager.shapes).max())
    np.testing.assert_allclose(jitted.W_hat, eager.W_hat, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(jitted.shapes, eager.shapes, rtol=1e-6, atol=1e-6 * scale)
    # Tracks that are constants of the caller's program: the call is still staged into it
    # (a single call's own compiler options, pipeline.ONE_CALL_OPTIONS, may not be nested).
    closed = jax.jit(lambda: nr.reconstruct(seq.W, seq.visible, k=2, **PAPER))()
    np.testing.assert_allclose(closed.W_hat, eager.W_hat, rtol=1e-9, atol=1e-9 * scale)


def test_float32(key):
    seq = nr.deformable_cube(key, noise=2.0, dtype=jnp.float32)
    rec = nr.reconstruct(seq.W, k=4, **PAPER)
    assert rec.shapes.dtype == jnp.float32 and rec.W_hat.dtype == jnp.float32
    assert bool(rec.status == nr.Status.success)
    err = nr.rms_error(seq.W_clean, rec.W_hat, jnp.ones((100, 252), bool))
    assert float(err) < 1.1 * float(nr.statistical_floor(2.0, 100, 252, 13))
    assert float(nr.e3d(rec.shapes, seq.shapes)) < 0.05


def test_als_half_sweeps_solve_their_weighted_normal_equations():
    # masked_als's two half-sweeps (one normal matrix per frame, shared by its two rows,
    # and one per point, formed from their distinct entries) against each row's and each
    # column's weighted least-squares solution, with real weights and missing entries.
    rng = np.random.default_rng(0)
    m, n, r = 7, 11, 5
    W, M, S = (jnp.asarray(rng.standard_normal(shape)) for shape in [(2 * m, n), (2 * m, r), (r, n)])
    weights = jnp.asarray(rng.random((m, n)) * (rng.random((m, n)) > 0.2))
    c = np.repeat(np.asarray(weights), 2, axis=0)
    rows = [np.linalg.solve((S * c[i]) @ S.T, S @ (c[i] * W[i])) for i in range(2 * m)]
    columns = [np.linalg.solve((M.T * c[:, j]) @ M, M.T @ (c[:, j] * W[:, j])) for j in range(n)]
    # The solves add a relative ridge of 1e-12 (linalg.add_ridge).
    weighted = jnp.asarray(c) * W
    np.testing.assert_allclose(motion_given_structure(weighted, weights, S, 0.0), np.stack(rows), atol=1e-9)
    np.testing.assert_allclose(structure_given_motion(weighted, weights, M, 0.0), np.stack(columns, axis=1), atol=1e-9)


def test_als_with_unused_columns_is_the_lower_rank_fit():
    # masked_als's ``active``: a rank-3 start in 5 columns (two zero) fits as the rank-3 start
    # in 3, its unused columns of M and rows of S exactly zero (robust.wang's passes of several
    # ranks share one loop this way), with real weights and missing entries.
    rng = np.random.default_rng(1)
    m, n = 9, 14
    W = jnp.asarray(
        rng.standard_normal((2 * m, 3)) @ rng.standard_normal((3, n)) + 0.1 * rng.standard_normal((2 * m, n))
    )
    weights = jnp.asarray(rng.random((m, n)) * (rng.random((m, n)) > 0.2))
    M0 = jnp.asarray(rng.standard_normal((2 * m, 3)))
    M3, S3, steps3, _ = masked_als(W, weights, M0, rtol=1e-12)
    padded = jnp.pad(M0, ((0, 0), (0, 2)))
    M5, S5, steps5, _ = masked_als(W, weights, padded, rtol=1e-12, active=jnp.arange(5) < 3)
    assert int(steps5) == int(steps3) > 2
    assert not jnp.any(M5[:, 3:]) and not jnp.any(S5[3:])
    # The same fit but for the solves' ridge (linalg.add_ridge: 1e-12 of the mean diagonal,
    # here over five columns instead of three).
    np.testing.assert_allclose(M5[:, :3] @ S5[:3], M3 @ S3, rtol=0, atol=1e-9)
