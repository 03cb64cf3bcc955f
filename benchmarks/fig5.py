"""The paper's Fig. 5 protocol: the deformable cube, sigma = 1..5, 5% and 20% outliers,
many independent trials per setting; the mean inlier reprojection error against the
noise-free truth for every method, beside the statistical floor.

    python benchmarks/fig5.py [--trials 100] [--noise 1 2 3 4 5] [--outliers 0.05 0.2]

The error of a trial is the per-coordinate RMS of W_hat against the noise-free tracks
over the true inliers (the paper measures on "the original inlying data without
outliers"). Every method is the single-sequence pipeline mapped over trials.
"""

import argparse
import time
from functools import partial

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import jaxnrsfm as nr  # noqa: E402

K = 4


def run(method, seqs):
    def one(seq):
        outliers = seq.outliers if method == "oracle" else None
        rec = nr.reconstruct(seq.W, seq.visible, k=K, method=method, outliers=outliers)
        inl = seq.visible & ~seq.outliers
        detected = seq.visible & ~rec.inliers
        precision, recall = nr.outlier_precision_recall(detected, seq.outliers, seq.visible)
        ok = rec.status == nr.Status.success
        return nr.rms_error(seq.W_clean, rec.W_hat, inl), precision, recall, ok

    return jax.jit(lambda s: jax.lax.map(one, s))(seqs)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--noise", type=float, nargs="+", default=[1, 2, 3, 4, 5])
    parser.add_argument("--outliers", type=float, nargs="+", default=[0.05, 0.2])
    parser.add_argument("--methods", nargs="+", default=["direct", "huynh", "ke_kanade", "wang", "oracle"])
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    print(f"deformable cube, 100 frames x 252 points, k={K}, {args.trials} trials per setting")
    print("mean over trials of the RMS error on true inliers against the noise-free tracks [image units]")
    header = f"{'outliers':>8} {'sigma':>5} {'floor':>6} " + " ".join(f"{m:>10}" for m in args.methods)
    print(header + "   wang/oracle  wang P/R (min over trials)   time/trial per method [s]")
    for ratio in args.outliers:
        for sigma in args.noise:
            # Trial i's key does not depend on the number of trials: runs of different
            # sizes share their first trials.
            keys = jax.vmap(jax.random.fold_in, (None, 0))(jax.random.key(args.seed), jnp.arange(args.trials))
            seqs = jax.vmap(partial(nr.deformable_cube, noise=sigma, outlier_ratio=ratio))(keys)
            means, times, pr = [], [], ""
            for method in args.methods:
                t0 = time.perf_counter()
                err, precision, recall, ok = jax.block_until_ready(run(method, seqs))
                times.append((time.perf_counter() - t0) / args.trials)
                means.append(float(jnp.mean(err)))
                if method == "wang":
                    lo = f"{float(jnp.min(precision)):.3f}/{float(jnp.min(recall)):.3f}"
                    pr = f"{float(jnp.mean(precision)):.3f}/{float(jnp.mean(recall)):.3f} ({lo})"
                if not bool(jnp.all(ok)):
                    pr += f" [{method}: {int(jnp.sum(~ok))} trials not ok]"
            floor = float(nr.statistical_floor(sigma, 100, 252, 3 * K + 1))
            cells = " ".join(f"{m:10.3f}" for m in means)
            rel = ""
            if "wang" in args.methods and "oracle" in args.methods:
                rel = f"{means[args.methods.index('wang')] / means[args.methods.index('oracle')]:.4f}"
            times_s = " ".join(f"{t:.3f}" for t in times)
            print(f"{ratio:8.0%} {sigma:5.1f} {floor:6.3f} {cells}   {rel:>11}  {pr}   {times_s}", flush=True)


if __name__ == "__main__":
    main()
