"""Per-trial outcome of a reconstruction: an enumeration that lives inside jit and vmap,
so a failing trial in a batch is reported instead of aborting or poisoning the others."""

import equinox as eqx


class Status(eqx.Enumeration):
    """Outcome of `jaxnrsfm.reconstruct`. Compare with ``==``, e.g.
    ``result.status == Status.success`` (an array under vmap)."""

    success = "the reconstruction succeeded"
    not_converged = "the iterative solver stopped at its step limit before reaching its tolerance"
    too_many_outliers = (
        "too many entries were rejected as outliers: a frame or point kept fewer inliers than the rank needs, "
        "more than half of the observations were rejected, or the kept residuals do not look like noise "
        "(the outliers are more than the method can handle)"
    )
    nonfinite = "the solution contains non-finite values (degenerate data)"
    implausible = (
        "the Euclidean shapes are inconsistent with the tracks: their depth spread is many times their "
        "in-plane extent, or they reproject far from the fitted tracks (an upgrade that amplified the misfit)"
    )
