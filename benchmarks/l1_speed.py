"""Time one batch of L1 regressions: the per-column S-step of Ke & Kanade on the paper's cube.

The deformable cube of section 5.1 has 100 frames and 252 points; at k = 4 the augmented
factorization has rank 13, so one S half-sweep is 252 L1 regressions of size 200 x 13.
Compile time is reported separately from the run time (best of a few repeats), and
SciPy's HiGHS on a handful of the same problems is timed as a reference.

    python benchmarks/l1_speed.py [--float32] [--problems 252] [--rows 200] [--rank 13]
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np


def problems(rng, batch, rows, rank, outliers=0.1, missing=0.1):
    A = rng.normal(size=(rows, rank)) * 100
    X = rng.normal(size=(rank, batch))
    B = A @ X + rng.normal(size=(rows, batch))
    gross = rng.random((rows, batch)) < outliers
    B[gross] += rng.uniform(-400, 400, size=gross.sum())
    mask = rng.random((rows, batch)) > missing
    return A, B, mask


def highs(A, b, mask):
    from scipy.optimize import linprog

    A, b = A[mask], b[mask]
    n, r = A.shape
    c = np.r_[np.zeros(r), np.ones(2 * n)]
    A_eq = np.hstack([A, np.eye(n), -np.eye(n)])
    bounds = [(None, None)] * r + [(0, None)] * (2 * n)
    return linprog(c, A_eq=A_eq, b_eq=b, bounds=bounds, method="highs").fun


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--float32", action="store_true")
    parser.add_argument("--problems", type=int, default=252)
    parser.add_argument("--rows", type=int, default=200)
    parser.add_argument("--rank", type=int, default=13)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--reference", type=int, default=10, help="problems to time with scipy (0: none)")
    args = parser.parse_args()
    if not args.float32:
        jax.config.update("jax_enable_x64", True)
    from jaxnrsfm.l1 import l1_regression

    dtype = jnp.float32 if args.float32 else jnp.float64
    A, B, mask = problems(np.random.default_rng(0), args.problems, args.rows, args.rank)
    Aj, Bj, Mj = jnp.asarray(A, dtype), jnp.asarray(B, dtype), jnp.asarray(mask)
    solve = jax.jit(jax.vmap(l1_regression, in_axes=(None, 1, 1), out_axes=1))

    t0 = time.perf_counter()
    compiled = solve.lower(Aj, Bj, Mj).compile()
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        X = jax.block_until_ready(compiled(Aj, Bj, Mj))
        times.append(time.perf_counter() - t0)
    X = np.asarray(X, float)
    cost = np.sum(mask * np.abs(A @ X - B), axis=0)
    print(
        f"{args.problems} L1 regressions of {args.rows} x {args.rank}, {jnp.dtype(dtype).name}, vmap, "
        f"{jax.devices()[0].platform}"
    )
    print(f"  compile: {compile_s:.2f} s")
    print(
        f"  run:     {min(times) * 1e3:.1f} ms best, {np.median(times) * 1e3:.1f} ms median of {args.repeats}"
        f"  ({min(times) / args.problems * 1e6:.0f} us per problem)"
    )
    if args.reference:
        k = min(args.reference, args.problems)
        t0 = time.perf_counter()
        ref = np.array([highs(A, B[:, j], mask[:, j]) for j in range(k)])
        scipy_s = (time.perf_counter() - t0) / k
        rel = np.max((cost[:k] - ref) / ref)
        print(
            f"  scipy linprog(highs): {scipy_s * 1e3:.1f} ms per problem "
            f"(~{scipy_s * args.problems:.2f} s per batch); max relative excess cost over HiGHS on "
            f"{k} problems: {rel:.1e}"
        )


if __name__ == "__main__":
    main()
