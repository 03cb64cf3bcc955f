"""Speed of the robust pipeline: 100 cube trials at the paper's size (100 frames x 252
points, k = 4, ``method="wang"``) run

(a) as the library runs them: ``jaxnrsfm.reconstruct_batch``, each of its strategies
    (``loop``, the default, ``map`` and ``vmap``, ``jaxnrsfm.batch.default_batch_size``
    trials at a time), and ``vmap`` over all trials at once;
(b) as a Python loop over the jit-compiled single-trial ``jaxnrsfm.reconstruct``, which
    compiles for a single call (``jaxnrsfm.pipeline.ONE_CALL_OPTIONS``: faster to compile,
    slower to run);
(c) by the NumPy/SciPy implementation of the same algorithm in ``numpy_wang.py``.

Compilation is timed apart (the first call minus a second one). Prints NumPy /
library, loop / library, vmap / loop (both strategies of (a), compiled alike), and the
library's time per trial in NumPy SVDs of the same tracking matrix; and checks that (a)
and (c) agree.

``--cores N`` runs the whole benchmark, the library and NumPy alike, on the first N cores
the process may use (default: all). On the 2-core machine this project is developed on, a
process on one core ran a trial 1.1-2x faster than on both (README, "Speed", run 10): OpenBLAS,
which runs XLA:CPU's LAPACK calls, split each over both cores. The library now runs them on
one thread (`jaxnrsfm.threads`), and both ways take about as long (run 11).

    python benchmarks/speed.py [--trials 100] [--numpy-trials 100] [--cores N]
"""

import argparse
import inspect
import os
import sys
import time


def parse():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=100)
    parser.add_argument("--numpy-trials", type=int, default=None, help="trials for (c); default: all")
    parser.add_argument("--noise", type=float, default=2.0)
    parser.add_argument("--outliers", type=float, default=0.1)
    parser.add_argument("--cores", type=int, default=None, help="run on this many cores; default: all")
    return parser.parse_args()


if __name__ == "__main__":
    ARGS = parse()
    if ARGS.cores is not None:
        # Before JAX and NumPy's BLAS start: they size their thread pools by the cores the
        # process may run on.
        os.sched_setaffinity(0, sorted(os.sched_getaffinity(0))[: ARGS.cores])

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxnrsfm as nr  # noqa: E402
from jaxnrsfm.sweep import trial_keys  # noqa: E402

sys.path.insert(0, os.path.dirname(__file__))
import numpy_wang  # noqa: E402

K = 4
"""The robust factorization and the metric upgrade: the 2-D pipeline whose inliers (c) reproduces."""


def timed(fn):
    t0 = time.perf_counter()
    out = jax.block_until_ready(fn())
    return out, time.perf_counter() - t0


def main(args) -> None:
    keys = trial_keys(0, args.trials)
    seqs = jax.vmap(lambda key: nr.deformable_cube(key, noise=args.noise, outlier_ratio=args.outliers))(keys)
    W, visible = np.asarray(seqs.W), np.asarray(seqs.visible)
    T = args.trials
    print(
        f"wang on the cube ({W.shape[1] // 2} frames x {W.shape[2]} points, k={K}), sigma={args.noise}, "
        f"{args.outliers:.0%} outliers, {T} trials; {len(jax.devices())} {jax.devices()[0].platform} device(s), "
        f"{len(os.sched_getaffinity(0))} core(s)"
    )

    def library(strategy, **options):
        options = dict(k=K, method="wang", shapes="upgrade", strategy=strategy, **options)
        return lambda: nr.reconstruct_batch(W, visible, **options)

    def loop():
        return [nr.reconstruct(W[t], visible[t], k=K, method="wang", shapes="upgrade") for t in range(T)]

    runs = {}
    cases = [(f"(a) {s}", library(s)) for s in nr.batch.STRATEGIES]
    cases += [("(a) vmap all", library("vmap", batch_size=T)), ("(b) loop", loop)]
    for label, fn in cases:
        _, first = timed(fn)
        out, steady = timed(fn)
        runs[label] = (out, steady)
        print(f"{label:12}: {steady:7.2f} s, {steady / T * 1e3:7.1f} ms/trial (compile {max(first - steady, 0):.1f} s)")

    nt = T if args.numpy_trials is None else min(args.numpy_trials, T)
    t0 = time.perf_counter()
    reference = [numpy_wang.reconstruct(W[t], visible[t], K) for t in range(nt)]
    numpy_time = (time.perf_counter() - t0) / nt * T
    print(f"(c) numpy   : {numpy_time:7.2f} s, {numpy_time / T * 1e3:7.1f} ms/trial ({nt} trials timed)")

    svd = []
    for t in range(min(T, 20)):
        t0 = time.perf_counter()
        np.linalg.svd(W[t], full_matrices=False)
        svd.append(time.perf_counter() - t0)
    svd_time = float(np.median(svd))

    default = f"(a) {inspect.signature(nr.reconstruct_batch).parameters['strategy'].default}"
    lib, lib_time = runs[default]
    W_clean, truth = np.asarray(seqs.W_clean), np.asarray(visible & ~seqs.outliers)
    agree = np.mean([np.array_equal(reference[t][1], np.asarray(lib.inliers[t])) for t in range(nt)])
    err = lambda fit, t: float(nr.rms_error(W_clean[t], fit, truth[t]))  # noqa: E731
    gap = max(abs(err(reference[t][0], t) - err(np.asarray(lib.W_hat[t]), t)) for t in range(nt))
    print(f"numpy vs library: same inliers in {agree:.0%} of trials; largest error difference {gap:.1e}")
    print(f"one numpy SVD of the {W.shape[1]}x{W.shape[2]} matrix: {svd_time * 1e3:.2f} ms")
    print(f"ratio numpy / library      : {numpy_time / lib_time:6.1f}x")
    print(f"ratio (b) loop / library   : {runs['(b) loop'][1] / lib_time:6.2f}x  ((b) compiled for one call)")
    loop = runs["(a) loop"][1]
    print(f"ratio vmap / loop, (a)     : {runs['(a) vmap'][1] / loop:6.2f}x  (goal <= 1.5)", end="")
    vmap_all = runs["(a) vmap all"][1] / loop
    print(f"  ({nr.batch.default_batch_size(T)} trials at a time; all {T}: {vmap_all:.2f}x)")
    print(f"per trial in numpy SVDs    : {lib_time / T / svd_time:6.1f}   (goal <= 20)")
    print(f"(library = reconstruct_batch's default strategy, {default[4:]})")


if __name__ == "__main__":
    main(ARGS)
