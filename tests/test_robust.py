"""Outlier handling: detection and accuracy against the truth and the oracle on the
paper's cube, the baselines' ordering, the Huber/L1 solver, statuses and option errors."""

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest

import jaxnrsfm as nr
from jaxnrsfm import residuals, robust
from jaxnrsfm.factorize import svd_factors
from jaxnrsfm.objective import (
    STALL_STEPS,
    StallingLevenbergMarquardt,
    _block_inverse,
    huber_loss,
    huber_residuals,
    robust_factorize,
)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(method="robust"), "unknown method 'robust'"),
        (dict(method="oracle"), "needs the true outliers"),
        (dict(method=nr.Oracle(np.zeros((5, 20), bool))), "must have shape"),
        (dict(method="wang", form="registered"), "supports only the direct fit"),
        (dict(shapes="bmm"), "unknown shape step 'bmm'"),
        (dict(rotations="high_rank", shapes="upgrade"), "need its rotations"),
        (dict(rotations=nr.HighRankRotations(rank=20)), "exceeds"),
        (dict(solver="als"), "solver must be a MaskedALS"),
    ],
)
def test_option_errors(kwargs, message):
    W = np.random.default_rng(0).normal(size=(12, 20))
    with pytest.raises(ValueError, match=message):
        nr.reconstruct(W, k=1, **kwargs)


@pytest.mark.parametrize(
    "make, message",
    [
        (lambda: nr.Wang(threshold=0.0), "threshold must be > 0"),
        (lambda: nr.Wang(passes=0), "passes"),
        (lambda: nr.Huber(delta=0.0), "delta must be > 0"),
        (lambda: nr.Huber(delta=-1.0), "delta must be > 0"),
        (lambda: nr.Huynh(iterations=0), "iterations"),
        (lambda: nr.HighRankRotations(rank=0), "rank must be"),
        (lambda: nr.HighRankRotations(held_out=1.0), "held_out must be in"),
        (lambda: nr.TraceNormRotations(weight=0.0), "weight must be > 0"),
        (lambda: nr.NuclearShapes(steps=0), "steps must be"),
        (lambda: nr.NuclearShapes(denoise=1), "denoise must be True or False"),
        (lambda: nr.MaskedALS(varpro="sometimes"), "varpro must be one of"),
    ],
)
def test_stage_option_errors(make, message):
    # A stage's options are checked when it is made, before any tracks are seen.
    with pytest.raises(ValueError, match=message):
        make()


def _evaluate(seqs, method):
    """Error, precision, recall and success of ``method`` on each trial of ``seqs``: the
    2-D fit and its detection only (the shape step does not change them). Through
    `jaxnrsfm.reconstruct_batch`, whose loop over the compiled single trial is faster on a
    CPU than a vmapped program and compiles the program the other full-cube tests load
    again (the session's compilation cache)."""
    method = nr.Oracle(seqs.outliers) if method == "oracle" else method
    recs = nr.reconstruct_batch(seqs.W, seqs.visible, k=4, method=method, shapes="upgrade")

    def score(seq, rec):
        precision, recall = nr.outlier_precision_recall(seq.visible & ~rec.inliers, seq.outliers, seq.visible)
        error = nr.rms_error(seq.W_clean, rec.W_hat, seq.visible & ~seq.outliers)
        return error, precision, recall, rec.status == nr.Status.success

    return tuple(np.asarray(x) for x in jax.vmap(score)(seqs, recs))


@pytest.fixture(scope="module")
def cube_trials():
    """Three cube trials at the issue's setting: sigma = 2, 10% outliers (20 to 100
    units, all beyond 6 sigma, so recall counts every outlier)."""
    keys = jax.random.split(jax.random.key(11), 3)
    return jax.vmap(partial(nr.deformable_cube, noise=2.0, outlier_ratio=0.1))(keys)


PAPER_METHODS = ("direct", "huynh", "ke_kanade", "wang", "oracle")


@pytest.fixture(scope="module")
def cube_results(cube_trials):
    """Error, precision, recall and success of every method of the paper's comparison on
    the three trials (each method compiled once for the module)."""
    return {m: _evaluate(cube_trials, m) for m in PAPER_METHODS}


def test_wang_detects_outliers_and_matches_oracle(cube_results):
    error, precision, recall, ok = cube_results["wang"]
    assert ok.all()
    assert (precision >= 0.95).all() and (recall >= 0.95).all(), (precision, recall)
    np.testing.assert_array_less(error, 1.05 * cube_results["oracle"][0])


def test_fig5_ordering_and_baselines_accuracy(cube_results):
    """The paper's Fig. 5 claim at one setting: the robust method beats the three
    baselines (``benchmarks/fig5.py`` runs the full protocol); and each baseline reaches
    the accuracy documented for it on that protocol (README, 5 trials a setting: at sigma 2
    Huynh et al. 1.19 and 2.39 times the oracle at 5% and 20% outliers, Ke & Kanade 1.38
    and 1.57), here at 10%."""
    errors = {m: r[0] for m, r in cube_results.items()}
    for baseline in ("direct", "huynh", "ke_kanade"):
        np.testing.assert_array_less(errors["wang"], errors[baseline])
        # A baseline's status is its own iteration's convergence (fits_every_entry), not
        # the robust method's residual tests: Huynh's corrections and Ke & Kanade's L1
        # sweeps reach their stopping rules here, and report success.
        assert cube_results[baseline][3].all(), baseline
    ratio = {m: errors[m] / errors["oracle"] for m in ("huynh", "ke_kanade", "direct")}
    assert (ratio["huynh"] < 2.4).all() and (ratio["ke_kanade"] < 1.6).all(), ratio
    assert (ratio["direct"] > 3).all(), ratio  # ignoring the outliers costs far more


@pytest.mark.parametrize("ratio", [0.4, 0.6])
def test_heavy_contamination_is_reported(ratio):
    """40% outliers: found, yet the fit fails (error 7 against the oracle's 0.9) with
    residuals that look like noise; 60%: the median scale breaks down. Both must be
    reported, not returned as successes."""
    seq = nr.deformable_cube(jax.random.key(1), noise=2.0, outlier_ratio=ratio)
    rec = nr.reconstruct(seq.W, seq.visible, k=4, method="wang", shapes="upgrade")
    assert rec.status == nr.Status.too_many_outliers


def test_failing_trial_does_not_poison_batch():
    """A trial whose every entry of one frame is an outlier is reported; the others
    in the same vmapped batch are unaffected."""
    seqs = jax.vmap(lambda key: nr.bregler_sequence(key, k=1, n_frames=20, n_points=30, noise=0.5, outlier_ratio=0.05))(
        jax.random.split(jax.random.key(4), 3)
    )
    W = seqs.W.at[1, 4:6].add(300.0 * jnp.sign(jnp.sin(jnp.arange(30.0)) + 0.1))
    batched = jax.vmap(lambda W, v: nr.reconstruct(W, v, k=1, method="wang", shapes="upgrade"))(W, seqs.visible)
    ok = batched.status == nr.Status.success
    assert list(ok) == [True, False, True]
    for t in (0, 2):
        one = nr.reconstruct(W[t], seqs.visible[t], k=1, method="wang", shapes="upgrade")
        np.testing.assert_array_equal(batched.inliers[t], one.inliers)
        np.testing.assert_allclose(batched.W_hat[t], one.W_hat, rtol=1e-7, atol=1e-7)


def test_huber_with_huge_delta_is_least_squares():
    seq = nr.bregler_sequence(jax.random.key(2), k=1, n_frames=12, n_points=25, noise=1.0)
    W = seq.W
    M, S = svd_factors(W, 4)
    start = svd_factors(W + jax.random.normal(jax.random.key(0), W.shape), 4)
    M1, S1, _, ok = robust_factorize(W, seq.visible, *start, jnp.array(1e6))
    assert ok
    best = jnp.sum((W - M @ S) ** 2)
    np.testing.assert_allclose(jnp.sum((W - M1 @ S1) ** 2), best, rtol=1e-6)


def test_levenberg_marquardt_stops_after_rejected_steps():
    # optimistix tests convergence only on an accepted step; at a minimum that the inexact
    # CG steps cannot improve on, every step is rejected (objective.StallingLevenbergMarquardt).
    # The robust solver's then stops after STALL_STEPS of them; optimistix's would not.
    def fn(y, _):
        return y - 1.0, None

    y = jnp.zeros(2)
    ours, plain = StallingLevenbergMarquardt(rtol=1e-8, atol=1e-8), optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)
    state = ours.init(fn, y, None, {}, jax.ShapeDtypeStruct(y.shape, y.dtype), None, frozenset())
    for rejected, stop in ((STALL_STEPS - 1, False), (STALL_STEPS, True)):
        stalled = eqx.tree_at(lambda s: s.num_steps_since_acceptance, state, jnp.array(rejected))
        terminate, result = ours.terminate(fn, y, None, {}, stalled, frozenset())
        assert bool(terminate) == stop and result == optx.RESULTS.successful
        assert not bool(plain.terminate(fn, y, None, {}, stalled, frozenset())[0])


@pytest.mark.parametrize("method", ["huber", "l1"])
def test_huber_and_l1_resist_outliers(method):
    seq = nr.bregler_sequence(jax.random.key(0), k=2, n_frames=30, n_points=60, noise=1.0, outlier_ratio=0.1)
    inl = seq.visible & ~seq.outliers
    direct = nr.reconstruct(seq.W, seq.visible, k=2, method="direct", shapes="upgrade")
    rec = nr.reconstruct(seq.W, seq.visible, k=2, method=method, shapes="upgrade")
    error = nr.rms_error(seq.W_clean, rec.W_hat, inl)
    assert error < 0.3 * nr.rms_error(seq.W_clean, direct.W_hat, inl)
    floor = nr.statistical_floor(1.0, 30, 60, 7)
    assert error < 3 * floor


@pytest.mark.parametrize("x64", [False, True])
@pytest.mark.parametrize("method", ["huber", "l1"])
def test_huber_and_l1_in_float32(method, x64, restore_x64):
    # float32 tracks, x64 off: Levenberg-Marquardt's CG tolerances are floored at float32's
    # precision (at float64's the first CG failed and the solve returned the least-squares
    # start, RMS 4.43 and 6.11). x64 on: optimistix damps in float64, and the solve is
    # promoted to it (it raised a structure mismatch).
    jax.config.update("jax_enable_x64", x64)
    seq = nr.bregler_sequence(
        jax.random.key(3), k=2, n_frames=30, n_points=40, noise=1.0, outlier_ratio=0.1, dtype=jnp.float32
    )
    rec = nr.reconstruct(seq.W, seq.visible, k=2, method=method, shapes="upgrade")
    assert rec.W_hat.dtype == jnp.float32 and bool(rec.status == nr.Status.success)
    precision, recall = nr.outlier_precision_recall(seq.visible & ~rec.inliers, seq.outliers, seq.visible)
    assert float(precision) > 0.95 and float(recall) == 1.0
    error = nr.rms_error(seq.W_clean, rec.W_hat, seq.visible & ~seq.outliers)
    assert float(error) < 3 * float(nr.statistical_floor(1.0, 30, 40, 7))


def test_huber_gradient_finite_at_zero_residual():
    E = jnp.zeros((4, 3))
    grad = jax.grad(huber_loss)(E, jnp.ones((2, 3), bool), 1.0)
    assert jnp.all(jnp.isfinite(grad))


EXACT_BREGLER = [
    pytest.param(partial(nr.bregler_sequence, k=k, n_frames=60, n_points=80), id=f"bregler-k{k}") for k in (1, 2)
]
"""Random Bregler sequences, k = 1 and 2, for the exact-tracks tests (the noise and outliers
are the tests'). With the 40-frame cube (k = 4) beside them they take `robust.wang`'s passes
through every case of their schedule: no growth (rank 4), and growth by two directions and by
one, into a wider loop and within one (ranks 7 and 13). k = 3 (rank 10) added no case, and
three compiled pipelines."""


def _bases(make) -> int:
    # The k a sequence maker is fitted with: the cube's 4, or the Bregler sequence's own.
    return 4 if make.func is nr.deformable_cube else make.keywords["k"]


def _assert_exact_with_outliers(seq, rec) -> None:
    # Every outlier found and nothing else, and the inliers' fit at the clean tracks to
    # 1e-6 of their scale.
    found = seq.visible & ~rec.inliers
    precision, recall = nr.outlier_precision_recall(found, seq.outliers, seq.visible)
    assert float(recall) == 1.0
    assert float(precision) == 1.0
    inliers = seq.visible & ~seq.outliers
    scale = jnp.sqrt(jnp.mean(seq.W_clean**2))
    fit = nr.entry_errors(seq.W_clean, rec.W_hat)
    assert float(jnp.max(jnp.where(inliers, fit, 0.0))) < 1e-6 * float(scale)


@pytest.mark.parametrize("noise", [0.0, 1e-6])
@pytest.mark.parametrize("make", [*EXACT_BREGLER, pytest.param(partial(nr.deformable_cube, n_frames=40), id="cube-k4")])
def test_wang_on_exact_tracks(make, noise):
    # Exact (or nearly exact) tracks: the residual scale is floored at the tracks'
    # precision (residuals.scale_floor), so round-off is not taken for outliers, and the
    # final inliers are judged against their own least-squares fit (robust.RECLASSIFY).
    for ratio in (0.0, 0.1):
        seq = make(jax.random.key(3), noise=noise, outlier_ratio=ratio)
        rec = nr.reconstruct(seq.W, seq.visible, k=_bases(make), method="wang", shapes="upgrade")
        if ratio == 0.0:
            assert int((seq.visible & ~rec.inliers).sum()) == 0
            assert bool(rec.status == nr.Status.success)
            continue
        _assert_exact_with_outliers(seq, rec)


@pytest.mark.parametrize("noise", [0.0, 1e-6])
def test_default_call_on_exact_tracks_with_outliers(noise):
    # The default stages (high-rank rotations, nuclear-norm shapes) on exact tracks whose
    # outliers were rejected and filled by the low-rank fit: the fill's own error (1e-8 of
    # the tracks) is no noise, and before the gap rule (refine.GAP) the rotations were solved
    # in its directions too: e3D 0.36 here (0.08 and 1.56 on the 40- and 100-frame cubes)
    # with a status of success.
    seq = nr.bregler_sequence(jax.random.key(0), k=2, n_frames=30, n_points=40, noise=noise, outlier_ratio=0.1)
    rec = nr.reconstruct(seq.W, seq.visible, k=2)
    assert bool(rec.status == nr.Status.success)
    assert float(nr.e3d(rec.shapes, seq.shapes)) < 1e-3


@pytest.mark.parametrize("method", ["ke_kanade", "l1"])
@pytest.mark.parametrize("make", [*EXACT_BREGLER, pytest.param(partial(nr.deformable_cube, n_frames=40), id="cube-k4")])
def test_l1_methods_on_exact_tracks_with_outliers(make, method):
    # The L1 minimum interpolates the inliers of exact tracks with outliers. Ke & Kanade's
    # alternation reaches it run to its tolerance (robust.ke_kanade's rtol); the L1 loss's
    # Levenberg--Marquardt once its smoothing kink is shrunk with the fit's residuals
    # (robust._l1_continuation: at its first kink the inliers' fit was 6e-4 of the RMS off).
    for noise in (0.0, 1e-6):
        seq = make(jax.random.key(3), noise=noise, outlier_ratio=0.1)
        rec = nr.reconstruct(seq.W, seq.visible, k=_bases(make), method=method, shapes="upgrade")
        _assert_exact_with_outliers(seq, rec)
        assert bool(rec.status == nr.Status.success)


@pytest.mark.parametrize("method", ["huber", "l1", "huynh", "ke_kanade"])
def test_baselines_on_exact_tracks_without_outliers(method):
    # Every robust method on exact (and nearly exact) clean tracks: nothing rejected,
    # success, the tracks reproduced. With outliers huynh and huber are not exact
    # (README); ke_kanade and l1 are (above).
    makes = [
        (partial(nr.bregler_sequence, k=2, n_frames=60, n_points=80), 2),
        (partial(nr.deformable_cube, n_frames=40), 4),
    ]
    for make, k in makes:
        for noise in (0.0, 1e-6):
            seq = make(jax.random.key(3), noise=noise)
            rec = nr.reconstruct(seq.W, seq.visible, k=k, method=method, shapes="upgrade")
            assert int((seq.visible & ~rec.inliers).sum()) == 0
            assert bool(rec.status == nr.Status.success)
            scale = jnp.sqrt(jnp.mean(seq.W_clean**2))
            assert float(jnp.max(nr.entry_errors(seq.W_clean, rec.W_hat))) < max(1e-6, 10 * noise) * float(scale)


def test_block_preconditioner_inverts_the_normal_matrix_blocks():
    # The Huber solver's CG preconditioner (objective.BlockJacobiNormal): the inverse of the
    # Gauss-Newton matrix's blocks of each frame's two rows of M and each point's column of
    # S, read off the operator by probing, against the materialised matrix.
    m, n, r = 3, 5, 2
    keys = jax.random.split(jax.random.key(0), 3)
    W, M, S = (jax.random.normal(key, shape) for key, shape in zip(keys, [(2 * m, n), (2 * m, r), (r, n)], strict=True))
    J = lx.JacobianLinearOperator(lambda p, _: huber_residuals(W - p[0] @ p[1], jnp.ones((m, n), bool), 0.5), (M, S))
    normal = J.T @ J
    matrix = np.asarray(normal.as_matrix())
    frames = [[(2 * i + c) * r + q for c in (0, 1) for q in range(r)] for i in range(m)]
    points = [[2 * m * r + q * n + j for q in range(r)] for j in range(n)]
    expected = np.zeros_like(matrix)
    for block in frames + points:
        expected[np.ix_(block, block)] = np.linalg.inv(matrix[np.ix_(block, block)])
    found = np.asarray(_block_inverse(lx.linearise(normal)).as_matrix())
    np.testing.assert_allclose(found, expected, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_lengths_sorted_and_their_median_as_numpy(dtype):
    # residuals.sorted_lengths sorts the lengths' bit patterns as integers (faster on
    # XLA:CPU): the same order as jnp.sort, and the same median as jnp.nanmedian, with
    # zeros, -0.0, inf, NaN (left out), odd and even counts, and nothing in the mask.
    @jax.jit
    def both(a, mask):
        lengths = jnp.where(mask, a, jnp.inf)
        ours = residuals.sorted_lengths(lengths), residuals.masked_median(a, mask)
        return ours, (jnp.sort(lengths.ravel()), jnp.nanmedian(jnp.where(mask, a, jnp.nan)))

    rng = np.random.default_rng(0)
    for trial in range(60):
        a = np.abs(rng.standard_normal((5, 7))) * (rng.random((5, 7)) > 0.2)
        a.flat[0] = [np.nan, np.inf, -0.0, 1.0][trial % 4]
        mask = rng.random((5, 7)) > (0.3 if trial % 9 else 1.0)
        ours, theirs = both(jnp.asarray(a, dtype), jnp.asarray(mask))
        np.testing.assert_array_equal(ours[0], theirs[0])
        np.testing.assert_array_equal(ours[1], theirs[1])


def test_residual_model_fit_converges_where_em_crawls():
    # Rayleigh residuals with lognormal per-frame and per-point scales (0.5), no outliers:
    # heavy-tailed, and the likelihood is flat in the outlier fraction, where EM alone
    # crawls (40 steps, the earlier fixed count: threshold 30.26; 80 steps: 35.24; the
    # limit 39.90). The fit must reach EM's own limit.
    rng = np.random.default_rng(1)
    m, n = 200, 100
    scales = np.exp(0.5 * rng.standard_normal((m, 1, 1)) + 0.5 * rng.standard_normal((1, n, 1)))
    a = np.linalg.norm(rng.standard_normal((m, n, 2)) * scales, axis=2)
    visible, floor = jnp.ones((m, n), bool), jnp.asarray(1e-8)
    model = residuals.fit(jnp.asarray(a), visible, floor)

    # NumPy EM at the chosen nu, run to its limit.
    nu, x, A = float(model.nu), a.ravel(), a.max()
    sigma = float(residuals.median_scale(jnp.asarray(a), visible, floor))
    eps = np.clip(np.mean(x > 6 * sigma), 1e-3, 0.5)
    for _ in range(20000):
        z = (x / sigma) ** 2
        log_in = np.log1p(-eps) + np.log(x) - 2 * np.log(sigma) - (nu + 2) / 2 * np.log1p(z / nu)
        r = 1 / (1 + np.exp(np.log(eps) - np.log(A) - log_in))
        new = np.sqrt(np.sum(r * (nu + 2) / (nu + z) * x**2) / (2 * r.sum())), np.clip(1 - r.mean(), 1e-6, 0.5)
        if np.allclose(new, (sigma, eps), rtol=1e-13, atol=0):
            break
        sigma, eps = new
    np.testing.assert_allclose([model.sigma, model.eps], [sigma, eps], rtol=1e-6)
    limit = residuals._threshold(jnp.asarray(sigma), model.nu, jnp.asarray(eps), jnp.asarray(A))
    np.testing.assert_allclose(model.threshold, limit, rtol=1e-6)

    # The gradient (implicit, at EM's fixed point): sigma scales with the residuals.
    scaled = jax.grad(lambda s: residuals.fit(s * jnp.asarray(a), visible, floor).sigma)(1.0)
    np.testing.assert_allclose(scaled, model.sigma, rtol=1e-6)


def test_residual_model_keeps_the_law_of_highest_likelihood():
    # residuals.fit visits only some of the laws (both ends, then inward while the likelihood
    # rises): it must keep the law that fitting every one of them would, on lengths drawn from
    # Rayleigh and Student-t laws of several nu, with and without uniform outliers.
    rng = np.random.default_rng(2)
    m, n = 60, 50
    visible, floor = jnp.ones((m, n), bool), jnp.asarray(1e-8)

    @jax.jit
    def every_law(a):
        # Every law fitted from the start `residuals.fit` gives its search.
        data, sigma0, eps0 = residuals._start(a, visible, floor)
        nus = jnp.asarray(residuals.NU, a.dtype)
        return jax.lax.map(lambda nu: residuals._fit_nu(data, visible, sigma0, eps0, nu)[1], nus)

    kept = set()
    for nu in (2.5, 3.5, 5.0, 12.0, np.inf):
        for outliers in (0.0, 0.15):
            g = rng.standard_normal((m, n, 2))
            if np.isfinite(nu):
                g /= np.sqrt(rng.chisquare(nu, (m, n, 1)) / nu)
            a = np.linalg.norm(g, axis=2)
            wild = rng.random((m, n)) < outliers
            a[wild] = rng.uniform(0, 40, wild.sum())
            model = residuals.fit(jnp.asarray(a), visible, floor)
            likelihoods = every_law(jnp.asarray(a))
            assert float(model.nu) == residuals.NU[int(jnp.argmax(likelihoods))], (nu, outliers, likelihoods)
            kept.add(float(model.nu))
    assert len(kept) >= 3  # the cases reach laws at both ends and inside


def _absorbed(offsets, seed=0):
    # Exact rank-4 tracks (30 frames, 40 points), point 7 displaced by ``offsets`` in 8 of its
    # 30 frames (27%), and the fit's structure of that point the least-squares fit of them,
    # which the displacements pull: its other entries get residuals too.
    rng = np.random.default_rng(seed)
    m, n, r = 30, 40, 4
    M, S = rng.standard_normal((2 * m, r)), rng.standard_normal((r, n))
    W = M @ S
    frames = rng.choice(m, 8, replace=False)
    displaced = np.zeros((m, n), bool)
    displaced[frames, 7] = True
    W[2 * frames, 7] += rng.choice([-1, 1], 8) * rng.uniform(*offsets, 8)
    S[:, 7] = np.linalg.lstsq(M, W[:, 7], rcond=None)[0]
    return jnp.asarray(W), jnp.asarray(M), jnp.asarray(S), displaced


def test_row_column_check_finds_outliers_a_point_absorbed():
    # Outliers 5-10 boundaries off: the check re-fits the point robustly given M and returns
    # exactly those 8 entries, nothing else.
    W, M, S, outliers = _absorbed((5.0, 10.0))
    visible = jnp.ones(outliers.shape, bool)
    assert float(nr.entry_errors(W, M @ S)[~outliers[:, 7], 7].max()) > 1.0  # the fit is pulled off its inliers
    rejected = robust.row_column_check(W, visible, visible, M, S, jnp.asarray(1.0), jnp.asarray(0.3))
    np.testing.assert_array_equal(rejected, outliers)


def test_row_column_check_leaves_model_misfit():
    # The same 8 entries 1.2-1.8 boundaries off (a point the model misfits in a few frames,
    # as in motion capture): the robust re-fit puts them beyond the boundary, but not
    # `ROW_COLUMN_FAR` boundaries beyond, and the check leaves them.
    W, M, S, misfit = _absorbed((1.2, 1.8))
    visible = jnp.ones(misfit.shape, bool)
    assert int((nr.entry_errors(W, M @ S) > 1.0).sum()) >= robust.ROW_COLUMN_GATE
    assert not bool(robust.row_column_check(W, visible, visible, M, S, jnp.asarray(1.0), jnp.asarray(0.3)).any())
