"""How to map the robust pipeline over Monte Carlo trials: ``jax.lax.map``, ``jax.vmap``
or a Python loop of jit-compiled single trials (``jaxnrsfm.reconstruct_batch``'s
strategies). Prints compile time apart from run time, and the run time per trial.

    python benchmarks/batching.py [--trials 20] [--method wang] [--noise 2] [--outliers 0.1]
"""

import argparse
import inspect
import time
from functools import partial

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import jaxnrsfm as nr  # noqa: E402


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=20)
    parser.add_argument("--method", default="wang")
    parser.add_argument("--noise", type=float, default=2.0)
    parser.add_argument("--outliers", type=float, default=0.1)
    args = parser.parse_args()
    keys = jax.vmap(jax.random.fold_in, (None, 0))(jax.random.key(0), jnp.arange(args.trials))
    seqs = jax.vmap(partial(nr.deformable_cube, noise=args.noise, outlier_ratio=args.outliers))(keys)
    print(
        f"{args.method} on the cube (100 x 252, k=4), sigma={args.noise}, {args.outliers:.0%} outliers, "
        f"{args.trials} trials, {jax.devices()[0].platform}"
    )
    per_trial = {}
    for strategy in nr.batch.STRATEGIES:
        run = partial(nr.reconstruct_batch, seqs.W, seqs.visible, k=4, method=args.method, strategy=strategy)
        t0 = time.perf_counter()
        jax.block_until_ready(run())  # compiles (for "loop": compiles once, then runs every trial)
        t1 = time.perf_counter()
        rec = jax.block_until_ready(run())
        t2 = time.perf_counter()
        per_trial[strategy] = (t2 - t1) / args.trials
        ok = int(jnp.sum(rec.status == nr.Status.success))
        print(f"{strategy:>5}: first call {t1 - t0:6.1f} s, then {per_trial[strategy]:.3f} s/trial ({ok} ok)")
    best = min(per_trial, key=per_trial.get)
    ratios = ", ".join(f"{s} {per_trial[s] / per_trial[best]:.2f}x" for s in per_trial)
    default = inspect.signature(nr.reconstruct_batch).parameters["strategy"].default
    print(f"fastest: {best} (time relative to it: {ratios}); library default: {default}")


if __name__ == "__main__":
    main()
