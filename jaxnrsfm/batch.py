"""Many sequences at once: the single-sequence pipeline mapped over a leading trial axis.

There is no batched algorithm here, only a choice of how to map
`jaxnrsfm.pipeline.reconstruct_prepared`:

- ``"loop"`` (the default): a Python loop over the jit-compiled single trial. On a
  2-core CPU it is the fastest for the robust method (``benchmarks/speed.py``, 20 cube
  trials of ``wang``: loop 0.64 s/trial, map 0.70, vmap 1.19);
- ``"map"``: ``jax.lax.map``, one trial after another inside one compiled program (what
  a sweep sharded over devices runs on each device);
- ``"vmap"``: all trials in lockstep: the solvers are while loops, so every trial runs as
  many steps as the slowest; it can pay on an accelerator with spare width.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .pipeline import Reconstruction, check_stages, reconstruct_prepared, resolve_stages
from .stages import MaskedALS, OutlierStrategy, RotationRecovery, ShapeStep
from .tracks import prepare_tracks

STRATEGIES = ("map", "vmap", "loop")


def reconstruct_batch(
    W: ArrayLike,
    visible: ArrayLike | None = None,
    *,
    k: int,
    method: "str | OutlierStrategy" = "wang",
    rotations: "str | RotationRecovery | None" = None,
    shapes: "str | ShapeStep" = "nuclear",
    solver: MaskedALS | None = None,
    strategy: Literal["map", "vmap", "loop"] = "loop",
) -> Reconstruction:
    """`jaxnrsfm.reconstruct` for ``T`` sequences of equal size: ``W`` is
    ``(T, 2m, n)``, ``visible`` ``(T, m, n)``; the stages as for one sequence, except that
    their array fields are per trial, with a leading ``T`` axis (``Oracle(outliers)`` with
    ``outliers`` ``(T, m, n)``). Every trial is validated (before anything is compiled)
    like a single sequence; the result has a leading ``T`` axis and a ``status`` per
    trial, so a trial that fails does not stop the others."""
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}")
    W = np.asarray(W) if not isinstance(W, jax.Array) else W
    if W.ndim != 3:
        raise ValueError(f"a batch of tracks must have shape (T, 2m, n); got {W.shape}")
    rank = 3 * k + 1
    prepared = [
        prepare_tracks(W[t], None if visible is None else visible[t], rank=rank, rank_name=f"k={k} (rank {rank})")
        for t in range(W.shape[0])
    ]
    W0 = jnp.stack([w for w, _ in prepared])
    vis = jnp.stack([v for _, v in prepared])
    trials = len(prepared)
    # The stages' array fields carry one value per trial; the rest is shared by all.
    dynamic, static = eqx.partition(resolve_stages(method, rotations, shapes, solver), eqx.is_array)
    for leaf in jax.tree.leaves(dynamic):
        if leaf.shape[:1] != (trials,):
            raise ValueError(f"a stage's array field must have a leading axis of {trials} trials; got {leaf.shape}")
    check_stages(eqx.combine(jax.tree.map(lambda x: x[0], dynamic), static), vis.shape[1:], k)
    complete = bool(vis.all())
    statics = dict(k=k, complete=complete)
    if strategy == "loop":
        results = [
            reconstruct_prepared(
                W0[t], vis[t], **eqx.combine(jax.tree.map(lambda x, t=t: x[t], dynamic), static), **statics
            )
            for t in range(trials)
        ]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *results)
    return _mapped(W0, vis, dynamic, static, vectorize=strategy == "vmap", **statics)


@eqx.filter_jit
def _mapped(
    W: Float[Array, "T 2m n"],
    visible: Bool[Array, "T m n"],
    dynamic: dict,
    static: dict,
    *,
    vectorize: bool,
    **statics,
) -> Reconstruction:
    def run(args):
        W, visible, dynamic = args
        return reconstruct_prepared(W, visible, **eqx.combine(dynamic, static), **statics)

    if vectorize:
        return jax.vmap(run)((W, visible, dynamic))
    return jax.lax.map(run, (W, visible, dynamic))
