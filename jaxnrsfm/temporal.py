"""Temporal agreement: a second, independent witness for the entries that the low-rank model
rejects.

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
from jaxtyping import Array, Bool, Float

from . import residuals
from .tracks import to_frames


def _shift(x: Array, by: int, fill) -> Array:
    # x[i - by] at frame i (frames on axis 0), ``fill`` where that frame does not exist.
    pad = jnp.full((abs(by), *x.shape[1:]), fill, x.dtype)
    return jnp.concatenate([pad, x[:-by]]) if by > 0 else jnp.concatenate([x[-by:], pad])


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

    def grow(carry):
        inliers, _ = carry
        more = inliers | (visible & (prediction_errors(W, inliers) <= bound))
        return more, jnp.any(more != inliers)

    start = (inliers, smooth(W, inliers, scale))
    return jax.lax.while_loop(lambda carry: carry[1], grow, start)[0]
