"""Monte Carlo sweeps: the paper's Fig. 5 protocol, with every trial recorded.

A sweep draws independent cube trials for every (noise, outlier ratio) setting, runs each
method on them as `jaxnrsfm.batch.reconstruct_batch` (the single-sequence pipeline
mapped over trials, never a second implementation) and records, per trial, the error
against the noise-free tracks on the true inliers, outlier precision and recall, and the
status. Trials are split across all ``jax.devices()`` by a one-axis mesh over the trial
axis (``NamedSharding`` of a device axis that each device maps over): one CPU, several GPUs, or several hosts after
``jax.distributed.initialize()``, with the same numbers (trial ``t``'s data depend only on
the seed and ``t``).
"""

import dataclasses
import time
from collections.abc import Callable, Sequence
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from .metrics import outlier_precision_recall, rms_error, statistical_floor
from .pipeline import reconstruct_prepared
from .stages import STRATEGIES, MaskedALS, Oracle, UpgradeRotations, UpgradeShapes
from .status import Status
from .synthetic import deformable_cube
from .threads import compute_single_threaded

PAPER_METHODS = ("direct", "huynh", "ke_kanade", "wang", "oracle")
K = 4
"""Shape bases of the cube (rigid part plus three moving sets)."""


@dataclasses.dataclass(frozen=True)
class SweepSettings:
    noise: tuple[float, ...] = (1.0, 2.0, 3.0, 4.0, 5.0)
    outliers: tuple[float, ...] = (0.05, 0.2)
    missing: float = 0.0
    trials: int = 100
    frames: int = 100
    methods: tuple[str, ...] = PAPER_METHODS
    k: int = K
    seed: int = 0


def trial_keys(seed: int, trials: int, first: int = 0) -> jax.Array:
    """The keys of trials ``first .. first + trials - 1``: trial ``t``'s is
    ``fold_in(key(seed), t)``, independent of how many trials run and of how they are split
    across devices or processes."""
    return jax.vmap(jax.random.fold_in, (None, 0))(jax.random.key(seed), jnp.arange(first, first + trials))


def check_methods(methods: Sequence[str]) -> None:
    """A ``ValueError`` naming the first of ``methods`` that is not a method's name."""
    if unknown := [m for m in methods if m not in STRATEGIES]:
        raise ValueError(f"unknown method {unknown[0]!r}; choose from {', '.join(STRATEGIES)}")


def _evaluate(seq, *, k, method, solver):
    """One trial: the paper's pipeline, then its error on the true inliers and its detection."""
    W = jnp.where(jnp.isnan(seq.W), 0.0, seq.W)
    strategy = Oracle(seq.outliers) if method == "oracle" else STRATEGIES[method]()
    rec = reconstruct_prepared(
        W,
        seq.visible,
        k=k,
        method=strategy,
        rotations=UpgradeRotations(),
        shapes=UpgradeShapes(),
        solver=solver,
        complete=False,
    )
    precision, recall = outlier_precision_recall(seq.visible & ~rec.inliers, seq.outliers, seq.visible)
    error = rms_error(seq.W_clean, rec.W_hat, seq.visible & ~seq.outliers)
    return error, precision, recall, rec.status == Status.success


@eqx.filter_jit
def _run_trials(keys, noise, outlier_ratio, *, frames, missing, k, method, solver):
    # One device's trials, one after another (lax.map: the solvers' step counts vary
    # between trials, and vmap would run them in lockstep).
    cube = partial(deformable_cube, n_frames=frames, noise=noise, outlier_ratio=outlier_ratio, missing_ratio=missing)
    return jax.lax.map(partial(_evaluate, k=k, method=method, solver=solver), jax.vmap(cube)(keys))


def _run_setting(keys, noise, outlier_ratio, *, mesh, **static):
    """Row ``d`` of ``keys`` (devices, trials per device) runs on the mesh's device ``d``;
    the results come back as arrays sharded over the mesh's trial axis.

    Each device runs the single-device program on its own trials, dispatched
    asynchronously so that the devices work at the same time, and nothing passes between
    them. (Neither ``jax.shard_map`` nor a ``vmap`` over a sharded axis serves here:
    inside ``shard_map`` lineax 0.1 rejects every linear solve -- the vector's structure
    carries the manual mesh, lineax issue #185 -- and a sharded ``vmap`` turns every
    solver's stopping test into a collective, which deadlocked on CPU devices.) The price
    is one XLA compilation per device; the trace and lowering are shared.
    """
    parts = {
        device: _run_trials(jax.device_put(row, device), noise, outlier_ratio, **static)
        for row, device in zip(keys, mesh.devices.flat, strict=True)
        if device.process_index == jax.process_index()
    }
    sharding = NamedSharding(mesh, PartitionSpec("trials"))

    def assemble(*leaves):
        return jax.make_array_from_single_device_arrays(
            (len(keys), *leaves[0].shape), sharding, [leaf[None] for leaf in leaves]
        )

    return jax.tree.map(assemble, *parts.values())


def _gather(x: jax.Array) -> np.ndarray:
    """Every trial's value on this process (after ``jax.distributed.initialize()`` the
    other hosts' trials are fetched from them)."""
    return np.asarray(x if x.is_fully_addressable else multihost_utils.process_allgather(x, tiled=True))


def run_sweep(
    settings: SweepSettings,
    *,
    solver: MaskedALS | None = None,
    devices: Sequence[jax.Device] | None = None,
    progress: Callable[[str], None] | None = None,
    first_trial: int = 0,
) -> dict:
    """Run every (outlier ratio, noise, method) cell of ``settings`` (its trials numbered
    from ``first_trial``: a share of a larger sweep, `jaxnrsfm.processes`); return a
    JSON-ready dict with the settings, and per cell the per-trial errors, precision,
    recall, status and the wall time (compilation included, reported apart). Each method
    runs by its name with its default options (``jaxnrsfm.stages.STRATEGIES``; the oracle
    told each trial's outliers) and the missing-data ``solver`` (default
    ``MaskedALS()``). The protocol scores the 2-D fit, which the rotation and shape steps
    do not change: the paper's pipeline (`jaxnrsfm.stages.UpgradeShapes`) runs."""
    check_methods(settings.methods)
    solver = MaskedALS() if solver is None else solver
    devices = list(jax.devices() if devices is None else devices)
    mesh = Mesh(np.array(devices), ("trials",))
    # Pad the trial axis to a multiple of the device count; the padding is dropped.
    padded = -(-settings.trials // len(devices)) * len(devices)
    keys = trial_keys(settings.seed, padded, first_trial).reshape(len(devices), -1)
    cells = []
    for ratio in settings.outliers:
        for noise in settings.noise:
            for method in settings.methods:
                run = partial(
                    _run_setting,
                    frames=settings.frames,
                    missing=settings.missing,
                    k=settings.k,
                    method=method,
                    solver=solver,
                    mesh=mesh,
                )
                t0 = time.perf_counter()
                out = compute_single_threaded(run, keys, jnp.asarray(noise), jnp.asarray(ratio))
                elapsed = time.perf_counter() - t0
                error, precision, recall, ok = (_gather(x).reshape(-1)[: settings.trials] for x in out)
                cells.append(
                    dict(
                        outliers=ratio,
                        noise=noise,
                        method=method,
                        error=error.tolist(),
                        precision=precision.tolist(),
                        recall=recall.tolist(),
                        success=ok.tolist(),
                        seconds=elapsed,
                        # Noise and ratio are traced: each method compiles once, in its first cell.
                        includes_compile=noise == settings.noise[0] and ratio == settings.outliers[0],
                    )
                )
                if progress is not None:
                    progress(f"{ratio:.0%} outliers, sigma {noise:g}, {method}: mean error {error.mean():.3f}")
    rank = 3 * settings.k + 1
    floors = {str(s): float(statistical_floor(s, settings.frames, 252, rank)) for s in settings.noise}
    return dict(
        settings=dataclasses.asdict(settings),
        solver=dataclasses.asdict(solver),
        devices=[str(d) for d in devices],
        dtype=str(jnp.zeros(()).dtype),
        floor=floors,
        cells=cells,
    )
