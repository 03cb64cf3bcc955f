"""Temporal agreement: a second, independent witness for the entries that the low-rank model
rejects, keeps or cannot see.

Three uses, each only where the tracks are smooth in time: rejected entries that continue
their track are taken back (`take_back`), kept entries that jump off it are rejected
(`reject_jumps`), and rejected or missing entries are interpolated along it for the
rotation step (`interpolate`). The first is the reasoning below.

A rank-``3k + 1`` model rejects what it does not explain. On motion capture that includes
clean entries: a limb's end at the extreme of a movement, which no combination of the
model's few bases reaches. Measured with `jaxnrsfm.robust.wang` at the default ``k``
(Akhter's clean sequences): 71 entries of yoga, 13 of stretch, clustered on a few points
over a few dozen frames, 9.5--17.5 residual scales off the fit -- where the injected
outliers of ``benchmarks/real_sequences.py`` lie too (14--69 scales). Their residuals
cannot tell them apart. Their tracks can: a clean entry continues its track, an outlier
jumps off it. Measured with the linear predictions below, in units of each sequence's
median prediction error, the clean entries wang rejected were at most 2.8 off their
track, the injected outliers at least 13.9 (yoga, pickup, stretch).

So an entry the model rejected is taken back when its track predicts it within the
model's own inlier boundary (no new threshold): by linear interpolation between its two
neighbouring frames, or by linear extrapolation from the two frames on either side, using
only neighbours that are themselves inliers (or taken back). The rounds repeat until
nothing changes, so a clean run of rejected entries is taken back from its ends inwards,
while a run displaced by a jump is not (its ends do not continue the track).

It is used only where the tracks are smooth in time (`smooth`): where they predict
their inliers at least as well as the low-rank model does. On the Akhter sequences their
median prediction error is 0.0003--0.0007 (in the tracks' units) against a residual
boundary of 0.03--0.09; on the
paper's cube, whose every frame has a random rotation and translation, it is 159 units
against a boundary of 4--17, and there a chance agreement (0.1% of the cube's entries lie
within 3--6 units of a prediction) would take outliers back. Frames out of temporal order
are not smooth either: nothing is taken back, and the robust method is unchanged.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from . import residuals
from .tracks import from_frames, row_mask, to_frames


def _shift(x: Array, by: Int[Array, ""] | int, fill) -> Array:
    # x[i - by] at frame i (frames on axis 0), ``fill`` where that frame does not exist.
    # A fixed offset by slices; a traced one (`stencil_errors` under a scan) by a roll and a
    # mask, which for fixed offsets compiled slower (take_back 0.074 -> 0.123 s alone
    # under the tests' flags).
    m = x.shape[0]
    if isinstance(by, int):
        pad = jnp.full((abs(by), *x.shape[1:]), fill, x.dtype)
        return jnp.concatenate([pad, x[:-by]]) if by > 0 else jnp.concatenate([x[-by:], pad])
    frame = jnp.arange(m).reshape(m, *([1] * (x.ndim - 1)))
    return jnp.where((frame - by >= 0) & (frame - by < m), jnp.roll(x, by, axis=0), fill)


def prediction_errors(W: Float[Array, "2m n"], trusted: Bool[Array, "m n"]) -> Float[Array, "m n"]:
    """The distance of each entry from the nearest of its track's three linear predictions
    from trusted neighbours in time: ``(x[i-1] + x[i+1]) / 2``, ``2 x[i-1] - x[i-2]``,
    ``2 x[i+1] - x[i+2]``; ``inf`` where no prediction has both its frames trusted."""
    X = to_frames(W)  # (m, 2, n)

    def at(by):
        return _shift(X, by, 0.0), _shift(trusted, by, False)

    (x1, t1), (x2, t2), (y1, s1), (y2, s2) = at(1), at(2), at(-1), at(-2)
    predictions = [((x1 + y1) / 2, t1 & s1), (2 * x1 - x2, t1 & t2), (2 * y1 - y2, s1 & s2)]
    errors = [jnp.where(ok, jnp.sqrt(jnp.sum((X - p) ** 2, axis=1)), jnp.inf) for p, ok in predictions]
    return jnp.minimum(jnp.minimum(errors[0], errors[1]), errors[2])


def smooth(W: Float[Array, "2m n"], inliers: Bool[Array, "m n"], scale: Float[Array, ""]) -> Bool[Array, ""]:
    """Whether the tracks are smooth in time: their inliers' median prediction error
    (`prediction_errors`) is at most ``scale``, the low-rank model's residual scale
    -- the tracks predict a typical inlier at least as well as the model does."""
    errors = prediction_errors(W, inliers)
    return residuals.masked_median(errors, inliers & jnp.isfinite(errors)) <= scale


def _in_rounds(
    update, W: Float[Array, "2m n"], inliers: Bool[Array, "m n"], scale: Float[Array, ""]
) -> Bool[Array, "m n"]:
    # ``update`` (inliers -> inliers) applied until nothing changes, each change altering
    # the predictions of its neighbours; not at all unless the tracks are `smooth` at the
    # low-rank model's residual ``scale``.
    def round_(carry):
        inliers, _ = carry
        new = update(inliers)
        return new, jnp.any(new != inliers)

    return jax.lax.while_loop(lambda carry: carry[1], round_, (inliers, smooth(W, inliers, scale)))[0]


def take_back(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    inliers: Bool[Array, "m n"],
    bound: Float[Array, ""],
    scale: Float[Array, ""],
) -> Bool[Array, "m n"]:
    """``inliers`` with every rejected observed entry that its track's trusted neighbours
    predict within ``bound`` (the residual model's inlier boundary) taken back, in rounds
    until nothing changes (module docstring); unchanged unless the tracks are
    `smooth` at the model's residual ``scale``. The decision is discrete: a constant
    to the gradient."""
    W, bound, scale = jax.lax.stop_gradient((W, bound, scale))
    return _in_rounds(lambda inliers: inliers | (visible & (prediction_errors(W, inliers) <= bound)), W, inliers, scale)


SPACINGS = (1, 2, 4, 8, 16, 32)
"""Spacings ``h`` of the uniform stencils ``i -+ h, i -+ 2h`` on which `interpolate`
measures how well the tracks' cubic interpolation predicts their trusted entries."""


def _neighbours(trusted: Bool[Array, "m n"]) -> tuple[Int[Array, "4 m n"], Bool[Array, "4 m n"]]:
    # For every entry, the frames of the two trusted entries of its track before it and the
    # two after it (strictly), and whether each exists.
    m = trusted.shape[0]
    frame = jnp.arange(m)[:, None]
    last = jax.lax.cummax(jnp.where(trusted, frame, -1), axis=0)  # last trusted at or before i
    first = jax.lax.cummin(jnp.where(trusted, frame, m), axis=0, reverse=True)  # first at or after
    before = _shift(last, 1, -1)
    after = _shift(first, -1, m)
    before2 = jnp.where(before >= 0, jnp.take_along_axis(before, jnp.maximum(before, 0), axis=0), -1)
    after2 = jnp.where(after < m, jnp.take_along_axis(after, jnp.minimum(after, m - 1), axis=0), m)
    nodes = jnp.stack([before2, before, after, after2])
    return nodes, (nodes >= 0) & (nodes < m)


def _lagrange(
    X: Float[Array, "m 2 n"], nodes: Int[Array, "4 m n"], valid: Bool[Array, "4 m n"]
) -> Float[Array, "m 2 n"]:
    # Each entry's value by Lagrange interpolation at its own frame through the valid nodes
    # of its track (2 to 4 of them).
    m = X.shape[0]
    t = jnp.arange(m, dtype=X.dtype)[:, None]
    at = nodes.astype(X.dtype)
    weights = []
    for a in range(4):
        w = jnp.ones_like(t * at[a])
        for b in range(4):
            if b != a:
                gap = jnp.where(valid[b], at[a] - at[b], 1.0)
                w = w * jnp.where(valid[b], (t - at[b]) / gap, 1.0)
        weights.append(jnp.where(valid[a], w, 0.0))
    values = jnp.take_along_axis(X[None], jnp.clip(nodes, 0, m - 1)[:, :, None, :], axis=1)  # (4, m, 2, n)
    return jnp.einsum("amn,amcn->mcn", jnp.stack(weights), values)


def stencil_errors(
    W: Float[Array, "2m n"], trusted: Bool[Array, "m n"], h: Int[Array, ""] | int
) -> Float[Array, "m n"]:
    """The distance of each entry from the cubic through its track's entries ``h`` and
    ``2h`` frames before and after it, ``(-x[i-2h] + 4 x[i-h] + 4 x[i+h] - x[i+2h]) / 6``;
    ``inf`` where one of those four is not trusted or does not exist. ``h`` may be traced."""
    X = to_frames(W)
    shifted = [(_shift(X, by, 0.0), _shift(trusted, by, False)) for by in (2 * h, h, -h, -2 * h)]
    (a, ta), (b, tb), (c, tc), (d, td) = shifted
    ok = ta & tb & tc & td
    return jnp.where(ok, jnp.sqrt(jnp.sum((X - (-a + 4 * b + 4 * c - d) / 6) ** 2, axis=1)), jnp.inf)


def interpolate(
    W: Float[Array, "2m n"], trusted: Bool[Array, "m n"], scale: Float[Array, ""]
) -> tuple[Float[Array, "2m n"], Bool[Array, "m n"]]:
    """The tracks' untrusted entries interpolated in time from their trusted neighbours,
    where the tracks predict better than ``scale`` (the low-rank model's typical residual).

    Each untrusted entry between two trusted entries of its track gets the cubic
    (quadratic, linear where fewer exist) through the two trusted entries before it and the
    two after. Its span, the frames between its nearest trusted neighbours, decides
    whether it is used: the stencils of `SPACINGS` measure, on the trusted entries, the
    median error of a cubic whose neighbours lie ``h`` frames away (a span of ``2h``); the
    interpolation is used up to the largest span whose error, and every shorter one's, is
    at most ``scale``. On tracks that are not smooth in time (the paper's cube, whose
    cameras jump from frame to frame) no span qualifies and nothing is interpolated.

    **Returns:** the tracks with the interpolated entries filled in (others unchanged),
    and the mask of the interpolated entries. The decision is discrete: a constant to the
    gradient; the values are differentiable."""
    m = trusted.shape[0]
    nodes, valid = _neighbours(trusted)
    values = from_frames(_lagrange(to_frames(W), nodes, valid))
    span = jnp.where(valid[1] & valid[2], nodes[2] - nodes[1], m + 1)
    fixed = jax.lax.stop_gradient(W)

    def longer(carry, h):
        # A scan, not a Python loop: one copy of the stencil and its median in the program
        # (the interpolation compiled in 0.22 s with a copy per spacing under the tests' flags).
        fine, longest = carry
        errors = stencil_errors(fixed, trusted, h)
        fine = fine & (residuals.masked_median(errors, jnp.isfinite(errors)) <= scale)
        return (fine, jnp.where(fine, 2 * h, longest)), None

    spacings = jnp.array([h for h in SPACINGS if 2 * h < m])
    (_, longest), _ = jax.lax.scan(longer, (jnp.array(True), jnp.array(0)), spacings)
    filled = ~trusted & (span <= longest)
    return jnp.where(row_mask(filled), values, W), filled


def _local_peak(errors: Float[Array, "m n"]) -> Bool[Array, "m n"]:
    # Whether each entry's error is the largest of its track's within two frames, rejected
    # entries included: an outlier at frame i also spoils the predictions of its neighbours
    # that pass through it, by half its jump where `prediction_errors` has a better one than
    # an extrapolation through it; and a clean entry beside a rejected outlier has only
    # extrapolations left, less accurate than the interpolations elsewhere. (Compared among
    # the inliers alone, the clean entries rejected with 10% outliers rose from 0.03-0.53%
    # to 0.19-2.3% of the Akhter sequences'.)
    finite = jnp.where(jnp.isfinite(errors), errors, -jnp.inf)
    peak = jnp.ones(errors.shape, bool)
    for by in (1, 2, -1, -2):
        peak = peak & (finite >= _shift(finite, by, -jnp.inf))
    return peak


def reject_jumps(
    W: Float[Array, "2m n"],
    inliers: Bool[Array, "m n"],
    scale: Float[Array, ""],
    ratio: Float[Array, ""],
    floor: Float[Array, ""],
) -> Bool[Array, "m n"]:
    """``inliers`` without the entries that jump off their own track: an outlier small
    enough for the low-rank model to keep is far off the line through its neighbours in
    time. A jump is an inlier whose `prediction_errors` is beyond ``ratio`` times their
    median scale (`jaxnrsfm.residuals.median_scale`, at least ``floor``) -- the low-rank
    model's own boundary in units of its scale -- and the largest of its track's within
    two frames; jumps are rejected in rounds until none is left, since a rejection changes
    its neighbours' predictions. Unchanged unless the tracks are `smooth` at the low-rank
    model's residual ``scale``. Discrete: a constant to the gradient. In a track's first or
    last two frames, where an extrapolation through a jump is a clean neighbour's only
    prediction, the jump can take that neighbour with it.

    Measured (``benchmarks/real_sequences.py``, 10% outliers): the low-rank model kept
    0.6--1.7% of the outliers of the Akhter sequences, 43--109 median prediction errors off
    their tracks, where their clean entries are at most 7--52. With these rejected the
    recall was 0.993--0.998 (0.983--0.994 without). A residual model fitted to the
    prediction errors themselves (`jaxnrsfm.residuals.fit`) found the same outliers, but
    compiled into every robust pipeline at ~6% more compile time of ``tests/test_robust.py``."""
    W, scale, ratio, floor = jax.lax.stop_gradient((W, scale, ratio, floor))
    errors = prediction_errors(W, inliers)
    boundary = ratio * residuals.median_scale(errors, inliers & jnp.isfinite(errors), floor)

    def drop(inliers):
        errors = prediction_errors(W, inliers)
        return inliers & ~(jnp.isfinite(errors) & (errors > boundary) & _local_peak(errors))

    return _in_rounds(drop, W, inliers, scale)
