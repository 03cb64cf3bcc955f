"""Metric upgrade: from an affine factorization to Euclidean rotations, weights, bases
and per-frame shapes (the paper's steps 6 and 7).

The factorization ``W = M S`` is defined up to an invertible ``H``. In the Bregler
model the Euclidean motion has the form ``M_i H = [w_i1 R_i, ..., w_ik R_i]`` (a 2x3k
block per frame, ``R_i`` the first two rows of a rotation). The upgrade proceeds as:

1. **Translations** (augmented form only): find the row combination of ``S`` closest to
   the ones row and change basis so that ``S``'s last row is it and the other rows are
   centred; ``M``'s last column is then the translations. ``M S`` is unchanged.
2. **Rotations from one column triple.** Any triple ``g = sum_l c_l g_l`` of true
   triples maps every frame to a scaled rotation, ``M_i g = (c . w_i) R_i``. Such a ``g``
   is found by Gauss--Newton (optimistix) on the rotation (orthonormality)
   constraints of Brand, Bregler and Torresani, ``|a_i|^2 = |b_i|^2`` and
   ``a_i . b_i = 0`` for ``[a_i; b_i] = M_i g``, from several starts; each ``R_i`` is the
   nearest pair of orthonormal rows (polar decomposition). This is the first step of
   Dai, Li & He's prior-free method (2012): one triple suffices for the rotations.
3. **All triples and weights, linearly.** Given the rotations, ``M_i h = w_il R_i`` is
   linear in ``(h, w)``; eliminating ``w`` leaves a ``9k x 9k`` quadratic form whose
   ``k``-dimensional null space holds exactly the true triples (up to a ``k x k`` mixing
   that leaves every shape ``sum_l w_il B_l`` unchanged). This replaces Xiao et al.'s
   basis constraints, which need ``k`` frames with independent shapes to be chosen.
   The rotations are then re-read from the dominant combination of the triples (one
   that no frame's weights nearly cancel) and the triples solved once more.
4. **Shapes.** ``B = H^-1 S``, ``S_i = sum_l w_il B_l``. The Bregler model cannot tell
   ``(w_i, R_i)`` from ``(-w_i, diag(-1,-1,1) R_i)`` (a per-frame point reflection of
   the shape); `frame_signs` picks the signs under which one rigid shape explains
   the tracks best. (Deciding them on the shapes ``w_i B`` fails on real data: ``H^-1``
   amplifies the errors of ``H``: on the Akhter drink sequence a third of the frames came
   out reflected, and e3D with `jaxnrsfm.refine`'s shapes was 1.26 instead of 0.039
   for the same rotations.) Finally the
   reconstruction is put in a canonical gauge: the world frame is the first camera's
   (``R_0 = I``), the mirror image with positive depth skewness in frame 0, and the
   bases are the principal shapes in order of energy, with unit-RMS weights.

For ``k = 1`` this is the Tomasi--Kanade rigid upgrade (the weights are the per-frame
camera scales). All functions are pure and jit-compiled.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float

from .linalg import RidgeCholesky, lowest_eigenvectors, polar_rows, truncated_svd
from .tracks import to_frames


class Euclidean(eqx.Module):
    """A Euclidean reconstruction in Bregler's model."""

    rotations: Float[Array, "m 3 3"]
    """Camera rotations; the orthographic camera of frame ``i`` is ``rotations[i, :2]``."""
    weights: Float[Array, "m k"]
    """Deformation weights (canonical gauge: principal shapes, unit-RMS weights)."""
    bases: Float[Array, "k 3 n"]
    """Shape bases, each centred on the origin."""
    shapes: Float[Array, "m 3 n"]
    """Per-frame 3-D shapes ``sum_l weights[i, l] bases[l]``, centred."""
    translations: Float[Array, "m 2"]
    """Image of each frame's shape centroid."""
    metric_residual: Float[Array, ""]
    """Relative misfit of ``M H`` to the Bregler form ``w_i (x) R_i`` (0 when exact)."""


def split_translation(
    M: Float[Array, "2m r"], S: Float[Array, "r n"]
) -> tuple[Float[Array, "2m r-1"], Float[Array, "r-1 n"], Float[Array, "m 2"], Float[Array, ""]]:
    """Separate the translation column of an augmented (rank ``3k + 1``) factorization.

    Returns ``(M', S', t, ones_error)`` with ``M S = M' S' + t 1^T`` up to
    ``ones_error``, the RMS distance of the closest row combination of ``S`` to the
    ones row (zero for noise-free data); the rows of ``S'`` are centred.
    """
    n = S.shape[1]
    ones = jnp.ones(n, S.dtype)
    v = jnp.linalg.lstsq(S.T, ones)[0]
    U = truncated_svd(S - S.mean(axis=1, keepdims=True), S.shape[0] - 1)[0]
    u0 = U.T @ S.mean(axis=1)
    T = jnp.concatenate([U.T - u0[:, None] * v[None, :], v[None, :]], axis=0)
    S_t = T @ S
    M_t = jnp.linalg.solve(T.T, M.T).T
    ones_error = jnp.sqrt(jnp.mean((S_t[-1] - ones) ** 2))
    return M_t[:, :-1], S_t[:-1], M_t[:, -1].reshape(-1, 2), ones_error


def center_structure(
    M: Float[Array, "2m r"], S: Float[Array, "r n"], t: Float[Array, "m 2"]
) -> tuple[Float[Array, "r n"], Float[Array, "m 2"]]:
    """Move the centroid of ``S`` into the translations: ``M S + t = M S_c + t'``."""
    mean = S.mean(axis=1)
    return S - mean[:, None], t + (M @ mean).reshape(-1, 2)


def _rotation_residuals(g: Float[Array, "3k 3"], Mn: Float[Array, "2m 3k"]) -> Float[Array, " 2m+1"]:
    # Each frame's pair M_i g as columns (3 x m): the sums over the triple's 3 columns run
    # over the leading axis, whole rows of frames at a time (summed over a trailing axis of
    # 3, the vmapped Gauss--Newton's Jacobian products ran several times slower).
    a, b = g.T @ Mn[0::2].T, g.T @ Mn[1::2].T
    aa, bb, ab = jnp.sum(a * a, 0), jnp.sum(b * b, 0), jnp.sum(a * b, 0)
    # Rotation constraints are homogeneous in g; the last residual fixes the scale.
    scale = jnp.mean(aa + bb) / 2 - 1
    return jnp.concatenate([aa - bb, 2 * ab, jnp.sqrt(Mn.shape[0] / 2.0) * scale[None]])


FINISH_STEPS = 4
"""Minimum-norm Gauss--Newton steps that finish `rotation_triple`'s winning start."""


def random_starts(starts: int, rank: int, dtype) -> Float[Array, "starts rank 3"]:
    """``starts`` random triples (standard normal, a fixed key) for `rotation_triple`.

    Drawn when the caller is traced and embedded in its program as a constant: drawn inside
    it, the random number generator took 6% of the compiled default pipeline."""
    with jax.ensure_compile_time_eval():
        return jax.random.normal(jax.random.key(0), (starts, rank, 3), dtype)


def rotation_triple(
    M: Float[Array, "2m 3k"], g0: Float[Array, "starts 3k 3"], *, max_steps: int = 40, min_scale: float = 0.0
) -> Float[Array, "3k 3"]:
    """A column triple ``g`` mapping every frame of ``M`` to a scaled rotation.

    Gauss--Newton (optimistix) on the rotation constraints from each start in ``g0``,
    vmapped, at most ``max_steps`` steps each; the lowest cost wins among the solutions
    whose every frame keeps a scale ``|M_i g|`` of at least ``min_scale`` times the median
    frame's (all of them if none does), and is finished by `FINISH_STEPS` exact steps.
    The constraints are homogeneous in each frame's ``M_i g``, so a triple that
    nearly vanishes in some frames satisfies those frames trivially: in a high-rank
    factorization such degenerate minima can have the lowest cost (half of Akhter's dance,
    rank 65: 1.8e-5 against 2.4e-5 for the triple of constant scale; the degenerate one's
    smallest frame scale was 2% of the median).
    """
    Mn = M / jnp.sqrt(jnp.mean(M**2))
    eps = jnp.finfo(M.dtype).eps
    # The minimisers form a manifold (global rotation, mixing of the true triples) where
    # the Jacobian is rank deficient: a minimum-norm Gauss--Newton step converges
    # quadratically to it, where LM's damping crawls. On noise-free data the iterates
    # then wander along the manifold at round-off level and never meet the termination
    # test, which is harmless: every point of it is a solution. So the step budget,
    # not the tolerance, ends those solves, and throw=False keeps that from erroring.
    # Every start's steps come from the normal equations of J's smaller side (J^T J, 3k
    # square, or J J^T, 2m + 1 square) by a ridged Cholesky factor (RidgeCholesky): its
    # costs equal the SVD steps' to 8 digits at a fraction of the time. The ridge keeps
    # weakly determined directions from converging to round-off (noise-free cube: e3D
    # 3e-6), so the winner is finished by minimum-norm steps from an SVD of J, which
    # also carry the implicit derivative. Measured (16 starts in 40 directions, 150
    # frames of yoga: 5.8 s -> 0.53 s; the paper's cube, 8 starts in 12: 98 -> 31 ms).
    rank_deficient = lx.AutoLinearSolver(well_posed=False)
    ridged = optx.GaussNewton(rtol=eps**0.6, atol=eps**0.75, linear_solver=lx.Normal(RidgeCholesky()))
    # The finish takes FINISH_STEPS steps whatever their size: from the ridged solve's
    # constraint residuals (1e-11 of the tracks' scale, noise-free cube) the first step is
    # below any tolerance on y, and a quadratic step or two reaches round-off (1e-13).
    exact = optx.GaussNewton(rtol=0.0, atol=0.0, linear_solver=rank_deficient)
    # The implicit derivative meets the same manifold: the minimum-norm tangent is one of
    # many, all giving the same rotations and shapes.
    adjoint = optx.ImplicitAdjoint(linear_solver=rank_deficient)
    fixed = jax.lax.stop_gradient(Mn)  # the starts only choose where the finish begins
    Mi = to_frames(fixed)

    def solve(g):
        sol = optx.least_squares(_rotation_residuals, ridged, g, fixed, max_steps=max_steps, throw=False)
        scale = jnp.sum((Mi @ sol.value) ** 2, axis=(1, 2))
        return sol.value, jnp.sum(_rotation_residuals(sol.value, fixed) ** 2), jnp.min(scale) / jnp.median(scale)

    gs, costs, smallest = jax.vmap(solve)(g0)
    costs = jnp.where(jnp.isfinite(costs), costs, jnp.inf)
    sound = smallest >= min_scale**2
    costs = jnp.where(sound | ~jnp.any(sound), costs, jnp.inf)
    best = jax.lax.stop_gradient(gs[jnp.argmin(costs)])
    finish = optx.least_squares(
        _rotation_residuals, exact, best, Mn, max_steps=FINISH_STEPS, throw=False, adjoint=adjoint
    )
    return finish.value


def _rotations_and_trust(Mi: Float[Array, "m 2 3k"], g: Float[Array, "3k 3"]):
    # A frame where the triple's combination of weights, c . w_i, is near zero gets a
    # poorly determined rotation: trust each frame by its squared scale.
    A = Mi @ g
    scale = jnp.sum(A**2, axis=(1, 2))
    return nearest_rotations(A), scale / jnp.max(scale)


def nearest_rotations(A: Float[Array, "m 2 3"]) -> Float[Array, "m 3 3"]:
    """Rotations whose first two rows are the orthonormal pair nearest to each ``A_i``."""
    R2 = polar_rows(A)
    return jnp.concatenate([R2, jnp.cross(R2[:, 0], R2[:, 1])[:, None]], axis=1)


def triples_given_rotations(
    M: Float[Array, "2m 3k"], R: Float[Array, "m 3 3"], k: int, trust: Float[Array, " m"] | None = None
) -> tuple[Float[Array, "3k 3k"], Float[Array, "m k"]]:
    """All ``k`` column triples and the weights, given the rotations (step 3).

    Minimises ``sum_i trust_i |M_i h - w_i R_i|^2`` over unit ``h`` with ``w_i`` eliminated in
    closed form (``w_i = <M_i h, R_i> / 2``): the ``k`` least eigenvectors of a ``9k x 9k``
    form. ``trust`` (default 1) down-weights frames whose rotation is less certain.
    """
    Mi = to_frames(M)
    trust = jnp.ones(Mi.shape[0], M.dtype) if trust is None else trust
    X = jnp.einsum("iab,iac->ibc", Mi, R[:, :2]).reshape(Mi.shape[0], -1)  # vec(M_i^T R_i)
    gram = jnp.einsum("i,iab,iac->bc", trust, Mi, Mi)
    G = jnp.kron(gram, jnp.eye(3, dtype=M.dtype)) - 0.5 * (trust[:, None] * X).T @ X
    vecs = lowest_eigenvectors(G, k)
    h = vecs.T.reshape(k, -1, 3)  # (k, 3k, 3)
    H = jnp.concatenate(list(h), axis=1)
    w = 0.5 * X @ vecs
    return H, w


def metric_upgrade(
    M: Float[Array, "2m 3k"],
    S: Float[Array, "3k n"],
    translations: Float[Array, "m 2"],
    k: int,
    *,
    starts: int = 8,
) -> Euclidean:
    """Upgrade a centred affine factorization ``W = M S + t 1^T`` to Euclidean form.

    **Arguments:**

    - `M`, `S`: motion ``(2m, 3k)`` and structure ``(3k, n)``.
    - `translations`: ``(m, 2)``; moved to the shapes' centroid if ``S`` is not centred.
    - `k`: number of shape bases.
    - `starts`: random starts for the rotation triple (step 2).
    """
    S, translations = center_structure(M, S, translations)
    Mi = to_frames(M)
    R, trust = _rotations_and_trust(Mi, rotation_triple(M, random_starts(starts, M.shape[1], M.dtype)))
    H, w = triples_given_rotations(M, R, k, trust)
    # The first triple is whichever combination of the true ones a start fell into, and
    # may nearly vanish in some frames. Now that all k triples are known, take the
    # dominant combination (largest sum_i (w_i . c)^2): every frame's rotation then comes
    # from a well-scaled triple. (Polishing it again on the rotation constraints gains
    # nothing with noise and loses digits without: those constraints are ill-conditioned
    # along the directions that Xiao et al.'s basis constraints were invented to fix.)
    c = truncated_svd(w, 1)[2][0]
    R, trust = _rotations_and_trust(Mi, jnp.einsum("blc,l->bc", H.reshape(-1, k, 3), c))
    H, w = triples_given_rotations(M, R, k, trust)
    B = jnp.linalg.solve(H, S).reshape(k, 3, -1)
    shapes = jnp.einsum("il,lan->ian", w, B)

    model = jnp.einsum("il,iac->ialc", w, R[:, :2]).reshape(Mi.shape)
    metric_residual = jnp.sqrt(jnp.sum((Mi @ H - model) ** 2) / jnp.sum((Mi @ H) ** 2))

    # After the solve above (the ``0 *`` term): frame_signs' eigendecompositions depend on
    # R alone, and two independent batched LAPACK calls that XLA's CPU runtime ran
    # concurrently have deadlocked it (README, "Known limitations").
    sign = frame_signs(R, (Mi @ S).astype(M.dtype) + 0.0 * shapes.sum())
    shapes = sign[:, None, None] * shapes
    R = flip_frames(R, sign)
    R, shapes = canonical_world(R, shapes)
    weights, bases = canonical_bases(shapes.reshape(shapes.shape[0], -1), k)
    return Euclidean(R, weights, bases.reshape(k, 3, -1), shapes, translations, metric_residual)


def frame_signs(R: Float[Array, "m 3 3"], tracks: Float[Array, "m 2 n"], *, sweeps: int = 20) -> Float[Array, " m"]:
    """Per-frame signs ``s_i = +-1`` resolving Bregler's reflection ambiguity.

    Flipping the first two rows of ``R_i`` (and the weights ``w_i``) reprojects
    identically but reflects the frame's shape through its centroid. The signs are those
    under which a single rigid shape ``X`` explains the centred tracks best,
    ``min_{s, X} sum_i |s_i R_i[:2] X - tracks_i|^2``: with ``Y_i = R_i[:2]^T tracks_i``
    (the in-plane back-projection, whose sign flips with ``s_i``) this is
    ``max_s s^T K s``, ``K_ij = <Y_i, P^+ Y_j>``, ``P = sum_i R_i[:2]^T R_i[:2]``.
    Started from the top eigenvector of ``K`` and improved by ``s <- sign(K s)``, which
    never decreases ``s^T K s`` (``K`` is positive semidefinite). The rigid part of a
    deforming object decides the signs, so it needs no accurate shapes, only rotations.
    """
    R, tracks = jax.lax.stop_gradient((R, tracks))  # signs are piecewise constant
    P2 = R[:, :2]
    Y = jnp.einsum("iab,ian->ibn", P2, tracks)
    ev, V = jnp.linalg.eigh(jnp.einsum("iab,iac->bc", P2, P2))
    # A static camera leaves P singular (no depth is seen): pseudo-inverse.
    seen = ev > 1e-8 * ev[-1]
    inv_sqrt = jnp.where(seen, 1.0 / jnp.sqrt(jnp.where(seen, ev, 1.0)), 0.0)
    Z = jnp.einsum("ab,ibn->ian", (V * inv_sqrt) @ V.T, Y).reshape(R.shape[0], -1)
    # K's top eigenvector from the smaller of Z Z^T and Z^T Z: on the paper's cube (Z 100 x
    # 756) 1.4 ms where the SVD of Z took 6.8.
    if Z.shape[0] <= Z.shape[1]:
        top = jnp.linalg.eigh(Z @ Z.T)[1][:, -1]
    else:
        top = Z @ jnp.linalg.eigh(Z.T @ Z)[1][:, -1]
    s = jnp.where(top < 0, -1.0, 1.0).astype(R.dtype)

    def sweep(_, s):
        # Z Z^T s without forming the m x m matrix K.
        return jnp.where(Z @ (Z.T @ s) < 0, -1.0, 1.0).astype(R.dtype)

    return jax.lax.fori_loop(0, sweeps, sweep, s)


def flip_frames(R: Float[Array, "m 3 3"], sign: Float[Array, " m"]) -> Float[Array, "m 3 3"]:
    """``R`` with the first two rows of frame ``i`` multiplied by ``sign[i]`` (the third,
    their cross product, is unchanged): the other member of each frame's reflection pair."""
    return R * jnp.stack([sign, sign, jnp.ones_like(sign)], axis=1)[:, :, None]


def canonical_world(
    R: Float[Array, "m 3 3"], shapes: Float[Array, "m 3 n"]
) -> tuple[Float[Array, "m 3 3"], Float[Array, "m 3 n"]]:
    """Rotations and shapes in the canonical world frame: the first camera's (``R_0 = I``),
    and of a reconstruction and its mirror image (``z -> -z`` with ``R -> D R D``,
    ``D = diag(1, 1, -1)``), which project identically, the one whose first shape has
    positive depth skewness. The result no longer depends on which random start won."""
    shapes = jnp.einsum("ab,ibn->ian", R[0], shapes)
    R = R @ R[0].T
    mirror = jnp.sum(shapes[0, 2] ** 3) < 0
    D = jnp.where(mirror, jnp.array([1.0, 1.0, -1.0], R.dtype), 1.0)
    return D[:, None] * R * D[None, :], D[:, None] * shapes


def canonical_bases(flat: Float[Array, "m 3n"], k: int) -> tuple[Float[Array, "m k"], Float[Array, "k 3n"]]:
    """Weights and bases of the best rank-``k`` approximation of the flattened shapes
    ``(m, 3n)``: the principal shapes in order of energy, unit-RMS weights, each mean weight
    non-negative."""
    m = flat.shape[0]
    U, s, Vt = truncated_svd(flat, k)
    sign = jnp.where(U.sum(axis=0) < 0, -1.0, 1.0).astype(flat.dtype)
    weights = U * sign * jnp.sqrt(m)
    bases = (sign * s)[:, None] * Vt / jnp.sqrt(m)
    return weights, bases


def euclidean_from_shapes(
    rotations: Float[Array, "m 3 3"],
    shapes: Float[Array, "m 3 n"],
    frames: Float[Array, "m 2 n"],
    k: int,
    observed: Bool[Array, "m n"] | None = None,
) -> Euclidean:
    """A `Euclidean` from per-frame rotations and shapes found by a shape step
    (`jaxnrsfm.stages.shapes`) that reproject onto the centred ``frames``.

    The translations are the frames' centroids (not the augmented factorization's ones
    row, which is undefined when the tracks are already centred), plus the image of the
    shapes' in-plane centroid where unobserved entries left it free; the result is put in
    the canonical gauge (`canonical_world`). The shapes are NOT exactly rank ``k``:
    ``weights @ bases`` is their best rank-``k`` approximation (`canonical_bases`),
    and ``metric_residual`` is that approximation's relative reprojection misfit on the
    ``observed`` entries (default: all)."""
    R = rotations
    translations = frames.mean(axis=2)
    offset = shapes.mean(axis=2)
    shapes = shapes - offset[:, :, None]
    translations = translations + jnp.einsum("iab,ib->ia", R[:, :2], offset)
    R, shapes = canonical_world(R, shapes)
    weights, bases = canonical_bases(shapes.reshape(shapes.shape[0], -1), k)
    bases = bases.reshape(k, 3, -1)
    model = jnp.einsum("iab,il,lbn->ian", R[:, :2], weights, bases)
    target = frames - translations[:, :, None]
    seen = True if observed is None else observed[:, None, :]
    misfit = jnp.sqrt(jnp.sum(jnp.where(seen, model - target, 0.0) ** 2) / jnp.sum(jnp.where(seen, target, 0.0) ** 2))
    return Euclidean(R, weights, bases, shapes, translations, misfit)
