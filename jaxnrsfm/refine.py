"""Low-rank shape recovery given the rotations: the shape step of Dai, Li & He's prior-free
block matrix method (BMM; "A simple prior-free method for non-rigid structure-from-motion
factorization", CVPR 2012 / IJCV 2014).

The metric upgrade (`jaxnrsfm.upgrade`) reads the shapes off the triples ``H`` of the
affine factorization, ``B = H^-1 S``. That step amplifies every error of ``H`` (Xiao et
al.'s basis ambiguity) and is what made the upgrade "only adequate" on real data: on the
Akhter motion-capture sequences its e3D was 0.13--20 for k = 2..8. BMM keeps the rotations
and recovers the shapes directly from the tracks:

    minimise ||S# - 1 mu^T||_*   subject to   R_i[:2] S_i = W_i  for every frame i,

where ``S# = [vec S_1; ...; vec S_m]`` (m x 3n) is the shape matrix, whose rank is k in
Bregler's model, ``mu`` the mean shape (free), and ``||.||_*`` (the nuclear norm) the
convex surrogate of the rank of the deformations from it. (BMM penalises ``||S#||_*``
itself, which also shrinks the mean shape, the dominant singular direction; leaving it
unpenalised lowered e3D with the same rotations on all five Akhter sequences: drink
0.0271 -> 0.0261, pickup 0.1551 -> 0.1545, yoga 0.0967 -> 0.0960, stretch 0.1055 ->
0.1047, dance 0.1812 -> 0.1739 in the camera frame; with the true rotations drink 0.0251
-> 0.0238, pickup 0.0513 -> 0.0408, yoga 0.0331 -> 0.0315.) The in-plane
part of each shape is fixed by the tracks, ``S_i = R_i[:2]^T W_i + r_i z_i^T`` with ``r_i``
the viewing direction, so only the depths ``z`` (m x n) are unknown. ADMM on
``L = S#(z)`` alternates singular-value thresholding of ``L`` with a closed-form depth
update (``|r_i| = 1``).

Measured (benchmarks/real_sequences.py, shared/data/akhter): with the TRUE rotations this
step alone gives e3D 0.03--0.05 on pickup, yoga and stretch, so the shape step is not the
bottleneck; the rotations are. Three rotation sources are offered: the metric upgrade's
(Gauss--Newton on the rotation constraints), Dai et al.'s trace-norm relaxation
(`trace_norm_triple`) and the same constraints in a high-rank factorization of the
tracks (`high_rank_rotations`). None is uniformly better on the five sequences.

What did NOT help, and is therefore not here: a joint Gauss--Newton refinement of
rotations, weights and bases on the reprojection error. Started from the TRUE rotations and
the rank-k truncation of the true shapes (k = 4, stretch), it lowered the reprojection cost
from 3.47 to 2.93 while the rotation error grew from 0.036 to 0.147 and e3D from 0.07 to
0.25: a per-frame rotation error is absorbed by the bases, so the reprojection error does
not determine the rotations on these sequences. Alternating rotations with the nuclear-norm
shapes drifted in the same way (the nuclear norm is flat in the rotations: 107.45 at the
truth, 107.33 at the upgrade's rotations, stretch).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .linalg import truncated_svd
from .tracks import from_frames, to_frames
from .upgrade import flip_frames, frame_signs, nearest_rotations, random_starts, rotation_triple


def _svt(X: Float[Array, "m p"], tau: Float[Array, ""]) -> Float[Array, "m p"]:
    # The proximal map of tau ||X - 1 mu^T||_* over X and the mean shape mu: mu is the
    # mean row, and the deviations are singular-value thresholded -- through the
    # eigendecomposition of their smaller Gram matrix (3n x 3n or m x m): faster than an
    # SVD of the m x 3n matrix (ALGORITHMS.md), and accurate enough in float64 because
    # only singular values above tau survive. (The deviations' columns are orthogonal to the
    # ones vector, so thresholding keeps their mean zero: mu and the thresholded
    # deviations are the joint minimiser.)
    mean = X.mean(axis=0, keepdims=True)
    D = X - mean
    tall = D.shape[0] >= D.shape[1]
    ev, V = jnp.linalg.eigh(D.T @ D if tall else D @ D.T)
    s = jnp.sqrt(jnp.maximum(ev, 0.0))
    keep = s > tau
    shrink = jnp.where(keep, 1.0 - tau / jnp.where(keep, s, 1.0), 0.0)
    P = (V * shrink) @ V.T
    return mean + (D @ P if tall else P @ D)


def nuclear_shapes(
    tracks: Float[Array, "m 2 n"],
    rotations: Float[Array, "m 3 3"],
    observed: Bool[Array, "m n"] | None = None,
    *,
    steps: int = 500,
    rho: float = 1.0,
) -> Float[Array, "m 3 n"]:
    """The shapes of least nuclear norm (of their deviations from the mean shape) that
    project exactly onto the observed tracks (BMM's shape step; module docstring).

    **Arguments:**

    - `tracks`: centred image points per frame, ``(m, 2, n)``; where not ``observed``,
      any finite values (they only enter the frame's centroid).
    - `rotations`: ``(m, 3, 3)``; frame ``i`` projects with ``rotations[i, :2]``.
    - `observed`: optional ``(m, n)`` mask. Where it is False the point's shape column is
      free (all three coordinates, not only the depth) and is filled in by the low-rank
      prior alone; default: every entry observed.
    - `steps`: ADMM iterations (a fixed count: jit- and vmap-friendly).
    - `rho`: ADMM penalty, relative to the tracks normalised to unit RMS.

    **Returns:** per-frame shapes ``(m, 3, n)`` with
    ``rotations[i, :2] @ shapes[i] == tracks[i] - mean(tracks[i])`` on the observed
    entries, centred along the viewing direction; fully centred when all are observed.
    """
    scale = jnp.sqrt(jnp.mean(tracks**2))
    W = tracks / scale
    W = W - W.mean(axis=2, keepdims=True)
    A = jnp.einsum("iab,ian->ibn", rotations[:, :2], W)  # in-plane back-projection
    r = rotations[:, 2]
    m, _, n = A.shape
    free = jnp.zeros((m, 1, n), bool) if observed is None else ~observed[:, None, :]

    def feasible(T):
        # argmin_S |S - T|^2 over the shapes that project onto the observed tracks: A is
        # orthogonal to r and |r| = 1, so only the depth along r is kept where observed.
        return jnp.where(free, T, A + r[:, :, None] * jnp.einsum("ia,ian->in", r, T)[:, None, :])

    def step(_, carry):
        S, Y = carry
        L = _svt(S.reshape(m, 3 * n) + Y / rho, jnp.asarray(1.0 / rho, W.dtype))
        S = feasible(L.reshape(m, 3, n) - Y.reshape(m, 3, n) / rho)
        return S, Y + rho * (S.reshape(m, 3 * n) - L)

    zero = jnp.zeros((m, 3, n), W.dtype)
    shapes, _ = jax.lax.fori_loop(0, steps, step, (feasible(zero), jnp.zeros((m, 3 * n), W.dtype)))
    # A depth offset along r_i does not change the projection: remove it. The in-plane
    # centroid is that of the tracks where all are observed; where some are not, it is
    # the shapes', and moving it would break the projection onto the observed tracks.
    depth = jnp.einsum("ia,ian->i", r, shapes) / n
    return scale * (shapes - r[:, :, None] * depth[:, None, None])


def trace_norm_triple(
    M: Float[Array, "2m 3k"], *, weight: float = 0.1, rho: float = 1.0, steps: int = 1000
) -> Float[Array, "3k 3"]:
    """A rotation triple by Dai et al.'s trace-norm relaxation of the rotation constraints.

    With ``Q = g g^T`` (3k x 3k, positive semidefinite, rank 3 at the truth) the rotation
    constraints ``|a_i|^2 = |b_i|^2``, ``a_i . b_i = 0`` for ``[a_i; b_i] = M_i g`` are
    linear in ``Q``. Solved, on ``M`` scaled to unit RMS, by ADMM:

        minimise  1/(2m) |A vec Q|^2 + weight tr Q   s.t.  Q >= 0,  mean_i (|a_i|^2 + |b_i|^2)/2 = 1

    (``tr Q`` is the nuclear norm on the PSD cone). The triple is the top-3 factor of ``Q``.
    """
    Mn = M / jnp.sqrt(jnp.mean(M**2))
    m, d = Mn.shape[0] // 2, Mn.shape[1]
    a, b = Mn[0::2], Mn[1::2]
    rows = jnp.concatenate(
        [
            jnp.einsum("ip,iq->ipq", a, a) - jnp.einsum("ip,iq->ipq", b, b),
            jnp.einsum("ip,iq->ipq", a, b) + jnp.einsum("ip,iq->ipq", b, a),
        ]
    ).reshape(2 * m, d * d)
    normal = (Mn.T @ Mn / (2 * m)).reshape(-1)
    K = jnp.linalg.inv(rows.T @ rows / m + rho * jnp.eye(d * d, dtype=M.dtype))
    Kn = K @ normal
    eye = jnp.eye(d, dtype=M.dtype).reshape(-1)

    def step(_, carry):
        Z, U = carry
        q = K @ (rho * (Z - U) - weight * eye)
        q = q - (normal @ q - 1.0) / (normal @ Kn) * Kn  # the scale constraint (Lagrange)
        X = (q + U).reshape(d, d)
        ev, V = jnp.linalg.eigh((X + X.T) / 2)
        Z = ((V * jnp.maximum(ev, 0.0)) @ V.T).reshape(-1)
        return Z, U + q - Z

    zero = jnp.zeros(d * d, M.dtype)
    Z, _ = jax.lax.fori_loop(0, steps, step, (zero, zero))
    ev, V = jnp.linalg.eigh(Z.reshape(d, d))
    return V[:, -3:] * jnp.sqrt(jnp.maximum(ev[-3:], 0.0))


MIN_SCALE = 0.5
"""Smallest frame scale ``|M_i g|``, relative to the median frame's, of a high-rank
rotation triple (`jaxnrsfm.upgrade.rotation_triple`). A camera's rigid part
projects at a steady scale; the degenerate minima vanish in some frames (measured on the
halves of the Akhter sequences: 0.02--0.08 for the degenerate ones, 0.94--0.98 for the others)."""


STEPS = 20
"""Gauss--Newton steps of each start of a high-rank rotation triple
(`jaxnrsfm.upgrade.rotation_triple`; its default is 40). The starts run in lockstep
(vmapped) until the last stops, and the starts that crawl towards a poor minimum never
meet the termination test: they set the time. The winning start had converged by 15 steps
on every Akhter sequence and each of its halves (15 cases): the same e3D to 4 digits at 15,
20 and 40 steps."""


GAP = 100.0
"""Ratio of neighbouring singular values that `above_noise` takes for the end of the
signal: exact low-rank tracks filled in by a fit, or with noise far below the signal (the
cube at sigma 0, 1e-6, 1e-3: 6e7, 7e6, 7e3 at its rank 12; at sigma 2: 3.6)."""


def above_noise(s: Float[Array, " b"], shape: tuple[int, int]) -> Bool[Array, " b"]:
    """Which singular values of a ``shape`` matrix (``s``: its ``b = min(shape)`` nonzero
    ones) stand above the noise: beyond the Marchenko--Pastur upper edge
    ``sigma (sqrt(p) + sqrt(q))`` of a ``p x q`` noise matrix, with ``sigma`` estimated from
    the smallest, ``s_b = sigma (sqrt(p) - sqrt(q))`` (the lower edge), which any signal
    only raises. On the paper's cube and on random Bregler sequences (sigma 0.5--5) this
    keeps exactly the ``3k`` directions of the shapes; on the exact projections of motion
    capture it keeps all but those within a factor 1.3--1.7 of the smallest (34--39 of 40
    on the Akhter sequences and their halves, 65--66 of 74 on dance). Never kept: values
    below round-off (``eps p s_1``, NumPy's rank tolerance) or below a gap (`GAP`)."""
    p, q = max(shape), min(shape)
    eps = jnp.finfo(s.dtype).eps
    edge = s[-1] * (jnp.sqrt(p) + jnp.sqrt(q)) / jnp.maximum(jnp.sqrt(p) - jnp.sqrt(q), eps)
    # Exact low-rank tracks filled in by a fit (rejected or missing entries) have a tail of
    # the fit's error, 1e-8 of the tracks on the cube, spread over decades: no noise, and
    # not separated from its smallest value by the edge. It sits below a gap that motion
    # capture's smooth spectrum never shows (at most 4.3 between neighbours on the Akhter
    # sequences and their halves): everything below a neighbour GAP times stronger is cut.
    ratio = s[:-1] / jnp.maximum(s[1:], jnp.finfo(s.dtype).tiny)
    below_gap = jnp.concatenate([jnp.zeros(1, bool), jnp.cumsum(ratio > GAP) > 0])
    return (s > jnp.maximum(edge, eps * p * s[0])) & ~below_gap


def _directions(
    frames: Float[Array, "m 2 n"], rank: int | None, min_rank: int
) -> tuple[Float[Array, "2m r"], Float[Array, " r"], Float[Array, "r n"]]:
    # The leading singular triplets of the centred tracks: rank None, every direction (rank
    # n - 1 at most) above the noise, and at least min_rank; the others' singular values
    # are zeroed (shapes stay static under jit).
    m, _, n = frames.shape
    width = min(2 * m, n - 1) if rank is None else rank
    U, s, Vt = truncated_svd(from_frames(frames), width)
    if rank is None:
        s = jnp.where(above_noise(s, (2 * m, n - 1)) | (jnp.arange(width) < min_rank), s, 0.0)
    return U, s, Vt


def above_noise_part(frames: Float[Array, "m 2 n"], min_rank: int) -> Float[Array, "m 2 n"]:
    """The centred tracks' part in their directions above the noise (`above_noise`, at
    least ``min_rank``): the tracks without the noise that no shape explains.

    On exact projections (motion capture) it keeps nearly every direction and changes
    little; on noisy tracks it keeps the ``3k`` directions of the shapes, which then
    fit the signal instead of reprojecting onto the noise."""
    U, s, Vt = _directions(frames, None, min_rank)
    return to_frames((U * s) @ Vt)


def _rotations_at_rank(
    frames: Float[Array, "m 2 n"], rank: int | None, starts: int, min_rank: int
) -> tuple[Float[Array, "m 3 3"], Int[Array, ""]]:
    # The rotations, and how many directions they were solved in.
    U, s, _ = _directions(frames, rank, min_rank)
    width = s.shape[0]
    M = U * s
    g0 = random_starts(starts, width, M.dtype)
    used = jnp.sum(s > 0)

    def narrow(_):
        # Only the leading min_rank directions are nonzero (noisy tracks: the shapes' 3k):
        # the same constraints in those columns alone, at a fraction of the cost of every
        # direction (the cube's 100 x 252 tracks: 12 columns instead of 200). rotation_triple
        # scales M to unit RMS, so the starts are scaled as the wide problem sees them. The
        # iterates still differ (its steps come from J^T J here, J J^T there); measured on
        # 7 noisy cube and Bregler sequences, the same e3D to 4 digits.
        ratio = jnp.sqrt(jnp.asarray(width / min_rank, M.dtype))
        g = rotation_triple(M[:, :min_rank], g0[:, :min_rank] * ratio, max_steps=STEPS, min_scale=MIN_SCALE)
        return jnp.concatenate([g / ratio, jnp.zeros((width - min_rank, 3), M.dtype)])

    def wide(_):
        return rotation_triple(M, g0, max_steps=STEPS, min_scale=MIN_SCALE)

    # Only the noise rule (rank None) zeroes directions: a given rank is solved as it is.
    narrowable = rank is None and width > min_rank
    g = jax.lax.cond(used <= min_rank, narrow, wide, None) if narrowable else wide(None)
    R = nearest_rotations(to_frames(M) @ g)
    return flip_frames(R, frame_signs(R, frames)), used


def high_rank_rotations(
    tracks: Float[Array, "m 2 n"],
    rank: int | None = None,
    observed: Bool[Array, "m n"] | None = None,
    *,
    min_rank: int = 3,
    starts: int = 16,
    refills: int = 2,
    steps: int = 500,
) -> Float[Array, "m 3 3"]:
    """Rotations from the rotation constraints on a rank-``rank`` factorization of the
    centred tracks, ``rank`` well above ``3k``; ``None`` (the default): every direction
    that stands above the noise (`above_noise`), at least ``min_rank``.

    The rule. On noisy synthetic tracks the directions beyond the shapes' ``3k`` carry
    only noise and spoil the triple (the cube with sigma 2: rotations 0.49 degrees off at
    rank 12, 0.99 at rank 40, 7.6 at 66); on motion capture, exact projections, they are
    the deformation's tail and carry the rigid combination the constraints look for. The
    noise edge keeps 12 on the cube and 34--39 of 40 on the Akhter sequences. Measured with
    the nuclear-norm shapes at ranks 15--40 on the five sequences and their halves (15 sets),
    e3D varies by up to 30% between neighbouring ranks; the sum over the 15 was 1.646 at
    ``n - 2`` and 1.641 at ``n - 1``, and the degenerate triples of the halves are removed by
    `MIN_SCALE`.

    The metric upgrade's triple ``g`` lives in the rank-``3k`` motion space, which leaks
    the deformation that ``k`` bases do not explain into every block ``M_i g``; a wrong
    ``g`` cancels that leak's non-orthonormal part better than the right one, and the
    rotations come out 1--5 degrees off on motion capture. In a high-rank space
    ``M_i g = W_i X`` for a combination ``X`` of the points, and the constraints can pick
    one that deformation barely moves (the rigid part). Measured on the Akhter sequences
    (41 points), with the nuclear-norm shapes: e3D 0.0271 / 0.1551 / 0.0967 / 0.1055 at
    rank 39 against 0.0392 / 0.1974 / 0.1960 / 0.1603 at rank ``3k`` (drink, pickup, yoga,
    stretch); rank 40, every direction of the centred tracks, gave a spurious triple on yoga,
    and yoga's 0.0967 is the best of its ranks (31--38 gave 0.126--0.138; drink, pickup and
    stretch vary by 0.001, 0.03 and 0.02 over ranks 31--39).

    A high-rank factorization needs every entry, and a rank-``3k + 1`` fill-in of the
    missing ones hides exactly the deformation this relies on. With ``observed``, the
    unobserved entries are refilled ``refills`` times with the projections of the
    nuclear-norm shapes (`nuclear_shapes`, which leaves them free) given the current
    rotations, and the rotations are solved again. Measured with ``method="wang"`` and 30%
    of the entries missing (drink, stretch): e3D 0.0337 / 0.1433 after the first solve on
    the rank-``3k + 1`` fill-in, 0.0310 / 0.1353 after two refills (0.0271 / 0.1055 on
    the complete tracks); a third changed them by under 0.3%. No refill where the rotations
    used only ``min_rank`` directions (noisy or exact low-rank tracks: the fit's values
    already lie in them), and then the triple is solved in those directions alone.
    """
    frames = tracks - tracks.mean(axis=2, keepdims=True)
    if observed is None:
        return _rotations_at_rank(frames, rank, starts, min_rank)[0]
    seen = observed[:, None, :]

    def refilled(R):
        shapes = nuclear_shapes(frames, R, observed, steps=steps)
        filled = jnp.where(seen, frames, jnp.einsum("iab,ibn->ian", R[:, :2], shapes))
        return filled - filled.mean(axis=2, keepdims=True)

    def solve(i, carry):
        # Solve 0 on the tracks as given, solve i > 0 on the tracks refilled from solve
        # i - 1: one loop, so that the compiled program holds one copy of the rotation
        # solve, not two (with refills it compiled in 1.03 s instead of 2.09 s under the
        # tests' XLA flags). The loop index is never batched, so the first cond stays a
        # cond under vmap.
        R, used = carry

        def again(R):
            return _rotations_at_rank(jax.lax.cond(i == 0, lambda R: frames, refilled, R), rank, starts, min_rank)

        # The refills are skipped (under vmap, where this cond becomes a select, both run)
        # where every entry is observed (a robust method that rejected nothing), and where
        # the rotations used no direction beyond the shapes' min_rank: the low-rank fit's
        # values in the unobserved entries already lie in that space, and the shapes'
        # refill adds its own error. With 10% outliers, skipped against refilled: exact
        # tracks (the 40-frame cube, a Bregler k = 2 sequence) e3D 1.9e-5 and 2.8e-5
        # against 1.5e-3 and 2.6e-3; 7 noisy cube and Bregler sequences 0.0425 against
        # 0.0434 on average (lower on 3 of them).
        skip = (i > 0) & (jnp.all(observed) | (used <= min_rank))
        R, now = jax.lax.cond(skip, lambda R: (R, used), again, R)
        return R, jnp.where(i == 0, now, used)

    start = (jnp.zeros((frames.shape[0], 3, 3), frames.dtype), jnp.array(0))
    return jax.lax.fori_loop(0, 1 + refills, solve, start)[0]
