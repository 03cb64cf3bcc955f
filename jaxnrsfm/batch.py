"""Many sequences at once: the single-sequence pipeline mapped over a leading trial axis.

There is no batched algorithm here, only a choice of how to map
`jaxnrsfm.pipeline.reconstruct_prepared`:

- ``"loop"`` (the default): a Python loop over the jit-compiled single trial. On a
  2-core CPU it is the fastest for the robust method with its compilation counted
  (``benchmarks/speed.py``, 20 paper-size cube trials of ``wang``, README run 13: loop
  82.0 ms a trial and 9.3 s to compile, map 75.2 ms and 11.6 s, vmap 2 at a time 117.7 ms
  and 12.3 s); ``"map"`` runs faster once compiled, and pays for larger batches;
- ``"map"``: ``jax.lax.map``, one trial after another inside one compiled program (what
  a sweep sharded over devices runs on each device);
- ``"vmap"``: trials in lockstep, ``batch_size`` at a time (``jax.lax.map`` over batches of
  a ``jax.vmap``): the solvers are while loops, so every trial of a batch runs as many
  steps as its slowest. On a CPU a batch's time per trial grows with its size (20 cube
  trials of ``wang``, paper size, 2-core CPU, one run, per trial against a loop: batches
  of 2: 0.98x, 4: 1.14x, 5: 1.21x, 10: 1.29x, all 20 at once: 1.79x; another day, side by
  side, batches of 2: 1.51x, of 4: 1.67x; the working set of the batch, not only the
  lockstep), so there the default batch is `CPU_BATCH`; on an accelerator, with spare
  width, all trials at once.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .pipeline import Reconstruction, check_stages, reconstruct_prepared, resolve_stages
from .stages import MaskedALS, OutlierStrategy, RotationRecovery, ShapeStep
from .threads import compute_single_threaded
from .tracks import prepare_tracks

STRATEGIES = ("map", "vmap", "loop")

CPU_BATCH = 2
"""Trials per vmapped batch on a CPU when ``batch_size`` is not given (module docstring)."""


def default_batch_size(trials: int) -> int:
    """The ``"vmap"`` strategy's trials at a time when ``batch_size`` is not given:
    `CPU_BATCH` (at most ``trials``) on a CPU, all ``trials`` on an accelerator (module
    docstring)."""
    return min(CPU_BATCH, trials) if jax.default_backend() == "cpu" else trials


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
    batch_size: int | None = None,
) -> Reconstruction:
    """`jaxnrsfm.reconstruct` for ``T`` sequences of equal size: ``W`` is
    ``(T, 2m, n)``, ``visible`` ``(T, m, n)``; the stages as for one sequence, except that
    their array fields are per trial, with a leading ``T`` axis (``Oracle(outliers)`` with
    ``outliers`` ``(T, m, n)``). Every trial is validated (before anything is compiled)
    like a single sequence; the result has a leading ``T`` axis and a ``status`` per
    trial, so a trial that fails does not stop the others. ``batch_size`` (``"vmap"``
    only): trials in lockstep at a time; ``None``: `default_batch_size`."""
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown strategy {strategy!r}; choose one of {', '.join(STRATEGIES)}")
    if batch_size is not None and (strategy != "vmap" or not isinstance(batch_size, int) or batch_size < 1):
        raise ValueError(f"batch_size must be a positive integer, with strategy='vmap'; got {batch_size!r}")
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
    return compute_single_threaded(_run, strategy, W0, vis, dynamic, static, trials, batch_size, statics)


def _run(
    strategy: str,
    W0: Float[Array, "T 2m n"],
    vis: Bool[Array, "T m n"],
    dynamic: dict,
    static: dict,
    trials: int,
    batch_size: int | None,
    statics: dict,
) -> Reconstruction:
    # The trials by the strategy (module docstring); dispatched, not yet computed.
    if strategy == "loop":
        results = [
            reconstruct_prepared(
                W0[t], vis[t], **eqx.combine(jax.tree.map(lambda x, t=t: x[t], dynamic), static), **statics
            )
            for t in range(trials)
        ]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *results)
    if strategy == "map":
        return _mapped(W0, vis, dynamic, static, batch_size=None, **statics)
    batch_size = min(default_batch_size(trials) if batch_size is None else batch_size, trials)
    # Whole batches only, the last padded with copies of the last trial (dropped after):
    # jax.lax.map would vmap a shorter remainder as a second compiled copy of the pipeline.
    pad = -trials % batch_size
    W0, vis, dynamic = jax.tree.map(lambda x: jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)]), (W0, vis, dynamic))
    result = _mapped(W0, vis, dynamic, static, batch_size=batch_size, **statics)
    return jax.tree.map(lambda x: x[:trials], result)


@eqx.filter_jit
def _mapped(
    W: Float[Array, "T 2m n"],
    visible: Bool[Array, "T m n"],
    dynamic: dict,
    static: dict,
    *,
    batch_size: int | None,
    **statics,
) -> Reconstruction:
    # One trial after another (batch_size None), or a vmap over batch_size trials at a time.
    def run(args):
        W, visible, dynamic = args
        return reconstruct_prepared(W, visible, **eqx.combine(dynamic, static), **statics)

    return jax.lax.map(run, (W, visible, dynamic), batch_size=batch_size)
