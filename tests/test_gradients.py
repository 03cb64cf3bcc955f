"""Gradients through the whole pipeline against central finite differences (float64).

Each case differentiates a vector of gauge-invariant outputs -- the fitted tracks, the
shapes aligned to a reference, e3D against a given truth, the Huber loss -- in forward
mode (``jvp``) and reverse mode (``vjp``) along random directions, and compares both with
central differences to 1e-5 relative. The "truth" is the true shapes slightly perturbed,
so that e3D is not at its kink (zero) on noise-free data. The forward solvers run to a
tight tolerance: a difference quotient is only as good as the solution it differences.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxnrsfm as nr
from jaxnrsfm.factorize import initial_fit, least_squares_fit, masked_als
from jaxnrsfm.implicit import attach
from jaxnrsfm.objective import huber_loss
from jaxnrsfm.tracks import row_mask

K = 2
SOLVE = dict(rtol=1e-14, max_steps=5000)
"""A tight forward solve."""
TIGHT = dict(solver=nr.MaskedALS(**SOLVE), shapes="upgrade")
"""... of the paper's pipeline (metric-upgrade shapes): the gradients of the nuclear-norm
shape step (the default, ``shapes="nuclear"``) are not verified here."""


def _cube(noise, missing=0.0, outliers=0.0, seed=0):
    seq = nr.deformable_cube(
        jax.random.key(seed), noise=noise, missing_ratio=missing, outlier_ratio=outliers, n_frames=12
    )
    W = jnp.where(row_mask(seq.visible), seq.W, 0.0)
    truth = seq.shapes + 0.05 * jax.random.normal(jax.random.key(seed + 1), seq.shapes.shape)
    return seq, W, truth


def _visible(seq):
    # The mask as an argument of the compiled derivatives; None where every entry is
    # visible, so that the pipeline takes its complete-data path (decided on a concrete mask).
    return None if bool(seq.visible.all()) else seq.visible


def _outputs(rec, truth, probe):
    aligned = nr.align_shapes(rec.shapes, truth)
    return jnp.stack([jnp.sum(rec.W_hat * probe), jnp.sum(aligned * truth) / truth.size, nr.e3d(rec.shapes, truth)])


@functools.cache
def _derivatives(f):
    """The jitted jvp of ``f(x, *args)`` in ``x`` (whose primal output gives the differences)
    and its vjp rows, one pair per ``f``: the cases of a test share their compiled programs
    (their data are arguments, not constants)."""
    jvp = jax.jit(lambda x, dx, args: jax.jvp(lambda x: f(x, *args), (x,), (dx,)))
    rows = jax.jit(lambda x, cts, args: jax.vmap(jax.vjp(lambda x: f(x, *args), x)[1])(cts)[0])
    return jvp, rows


def _check(f, x, args, directions, h):
    """jvp and vjp of the vector function ``f(x, *args)`` in ``x`` (a pytree) along each
    direction against central differences of step ``h``; returns the largest relative
    discrepancy. The vjp runs once, for every output at once (its rows of the Jacobian),
    and is dotted with each direction."""
    jvp, rows = _derivatives(f)
    jacobian = None
    worst = 0.0
    for dx in directions:
        fd = (jvp(_step(x, dx, h), dx, args)[0] - jvp(_step(x, dx, -h), dx, args)[0]) / (2 * h)
        forward = jvp(x, dx, args)[1]
        if jacobian is None:
            jacobian = rows(x, jnp.eye(fd.shape[0], dtype=fd.dtype), args)
        reverse = sum(
            jnp.tensordot(r, d, axes=d.ndim)
            for r, d in zip(jax.tree.leaves(jacobian), jax.tree.leaves(dx), strict=True)
        )
        assert bool(jnp.all(jnp.isfinite(forward))) and bool(jnp.all(jnp.isfinite(reverse)))
        error = jnp.maximum(jnp.abs(forward - fd), jnp.abs(reverse - fd)) / jnp.abs(fd)
        worst = max(worst, float(jnp.max(error)))
    return worst


def _step(x, dx, h):
    return jax.tree.map(lambda a, d: a + h * d, x, dx)


def _direction(seq, W, seed=7):
    return jnp.where(row_mask(seq.visible), jax.random.normal(jax.random.key(seed), W.shape), 0.0)


@pytest.mark.parametrize(("noise", "missing"), [(0.0, 0.0), (1.0, 0.3), (0.0, 0.3)])
def test_direct_pipeline_matches_finite_differences(noise, missing):
    # Noise-free data has (numerically) zero singular values below the rank: the
    # gradients must still be finite and right (truncated SVD, implicit ALS).
    seq, W, truth = _cube(noise, missing)
    probe = jax.random.normal(jax.random.key(3), W.shape)
    args = (_visible(seq), truth, probe)
    assert _check(_direct_outputs, W, args, [_direction(seq, W)], 1e-4 if noise else 1e-5) < 1e-5


def _direct_outputs(W, visible, truth, probe):
    return _outputs(nr.reconstruct(W, visible, k=K, method="direct", **TIGHT), truth, probe)


@pytest.mark.parametrize(("noise", "h"), [(1.0, 1e-5), (0.0, 1e-4)])
def test_huber_matches_finite_differences_in_tracks_and_delta(noise, h):
    # The Huber fit's scale comes from the least-squares fit and its solution is
    # re-attached by the implicit function theorem: both carry gradients, in W and delta.
    # Noise-free tracks with outliers too: the scale is floored at the tracks' precision.
    # There the forward solve's round-off left differences of step 1e-5 at 7.9e-6 to
    # 1.1e-5 relative from the derivatives (with the tests' XLA flags or without, LU or
    # Cholesky normal equations in ALS); step 1e-4 agrees to 3.8e-7, 1e-3 to 2.2e-6.
    seq, W, truth = _cube(noise, outliers=0.1)
    probe = jax.random.normal(jax.random.key(3), W.shape)
    x = (W, jnp.array(0.8))
    directions = [(_direction(seq, W), jnp.array(0.0)), (jnp.zeros_like(W), jnp.array(1.0))]
    assert _check(_huber_outputs, x, (_visible(seq), truth, probe), directions, h) < 1e-5


def _huber_outputs(x, visible, truth, probe):
    W, delta = x
    # k = 1: on 12 frames a k = 2 Huber fit takes Levenberg--Marquardt ~450 steps.
    rec = nr.reconstruct(W, visible, k=1, method=nr.Huber(delta=delta), **TIGHT)
    mask = jnp.ones(rec.inliers.shape, bool) if visible is None else visible
    loss = huber_loss(W - rec.W_hat, mask, 1.0)
    return jnp.concatenate([_outputs(rec, truth, probe), loss[None]])


@pytest.mark.parametrize(("noise", "steps"), [(1.0, (1e-4,)), (0.0, (3e-4, 1e-3))])
def test_wang_matches_finite_differences(noise, steps):
    # The default robust method, outliers present: its inlier set is a hard decision (a
    # constant to the gradient); step 5's weights are functions of the inliers'
    # least-squares fit and are differentiated. On noise-free tracks the forward solve
    # is only reproducible to ~1e-9 relative (the anchored outliers barely constrain ALS),
    # so the difference step is larger there, and the window between that noise and the
    # steps at which the inlier set changes (3e-3: errors up to order 1) is narrow and moves
    # with the tracks' last bits: on three 12-frame cubes, each drawn op by op and compiled
    # as one program (six sets of tracks), step 3e-4 agreed to 4e-8 - 7e-5 and 1e-3 to
    # 1e-7 - 7e-5, one of the two below 1e-5 in all six (at most 3.5e-7). The derivative
    # must agree with the difference quotient of one of the steps.
    seq, W, truth = _cube(noise, outliers=0.1)
    probe = jax.random.normal(jax.random.key(3), W.shape)
    args = (_visible(seq), truth, probe)
    assert min(_check(_wang_outputs, W, args, [_direction(seq, W)], h) for h in steps) < 1e-5


def _wang_outputs(W, visible, truth, probe):
    return _outputs(nr.reconstruct(W, visible, k=K, method="wang", **TIGHT), truth, probe)


def test_weights_match_finite_differences():
    # Per-entry weights of the least-squares fit (the oracle's, or a user's) are a
    # differentiable input too.
    seq, W, _ = _cube(1.0, missing=0.2)
    probe = jax.random.normal(jax.random.key(3), W.shape)
    base = jax.random.uniform(jax.random.key(4), seq.visible.shape, minval=0.5, maxval=2.0) * seq.visible

    def f(weights, W, probe):
        M, S, _, _ = least_squares_fit(W, weights, 3 * K + 1, complete=False, **SOLVE)
        return jnp.sum((M @ S) * probe)[None]

    dw = jax.random.normal(jax.random.key(5), base.shape) * seq.visible
    assert _check(f, base, (W, probe), [dw], 1e-5) < 1e-5


def test_vmap_of_grad_equals_loop_of_grad():
    keys = jax.random.split(jax.random.key(11), 4)
    seqs = jax.vmap(lambda key: nr.deformable_cube(key, noise=1.0, outlier_ratio=0.1, n_frames=8))(keys)

    def error(delta, W, visible, clean, outliers):
        rec = nr.reconstruct(W, visible, k=1, method=nr.Huber(delta=delta), shapes="upgrade")
        return nr.rms_error(clean, rec.W_hat, visible & ~outliers)

    grad = jax.grad(error, argnums=(0, 1))
    args = (seqs.W, seqs.visible, seqs.W_clean, seqs.outliers)
    batched = jax.jit(jax.vmap(grad, in_axes=(None, 0, 0, 0, 0)))(1.0, *args)
    single = jax.jit(grad)
    looped = [single(1.0, *(a[t] for a in args)) for t in range(len(keys))]
    np.testing.assert_allclose(batched[0], jnp.stack([g[0] for g in looped]), rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(batched[1], jnp.stack([g[1] for g in looped]), rtol=1e-8, atol=1e-10)
    assert bool(jnp.all(batched[0] != 0))


def test_float32_gradients_are_finite():
    seq, W, truth = _cube(1.0, missing=0.2)
    W32 = W.astype(jnp.float32)
    grad = jax.jit(
        jax.grad(lambda W: nr.e3d(nr.reconstruct(W, seq.visible, k=K, method="direct", shapes="upgrade").shapes, truth))
    )(W32)
    assert grad.dtype == jnp.float32
    assert bool(jnp.all(jnp.isfinite(grad))) and bool(jnp.any(grad != 0))


def test_polish_runs_only_where_differentiated():
    # implicit.attach polishes a loosely converged fit (Newton steps on its stationarity)
    # only where the result is differentiated: the differentiated value is the exact
    # least-squares optimum, the undifferentiated one stays at the solver's tolerance.
    seq, W, _ = _cube(1.0, missing=0.3)
    rank = 3 * K + 1
    # ALS stopped at rtol 1e-8: 4.9e-5 (largest entry, relative) from the optimum; one
    # Newton step takes it to 6.6e-8 (at the default 1e-10: 4.5e-6 and 5.0e-8).
    M0, _, _, _ = initial_fit(W, seq.visible, rank, complete=False, max_steps=3)
    M, S, _, _ = masked_als(W, seq.visible, M0, rtol=1e-8)
    tight_M, tight_S, _, _ = masked_als(W, seq.visible, M, **SOLVE)
    optimum = tight_M @ tight_S

    def fit(W):
        return attach(W, seq.visible, M, S, rank)[0]

    plain = fit(W)
    polished, _ = jax.jvp(fit, (W,), (jnp.zeros_like(W),))
    size = float(jnp.max(jnp.abs(optimum)))
    assert float(jnp.max(jnp.abs(polished - optimum))) < 1e-6 * size
    assert float(jnp.max(jnp.abs(plain - optimum))) > 1e-5 * size
