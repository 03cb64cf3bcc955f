"""The cost of a backward pass relative to the forward pass, at the paper's size.

    python benchmarks/gradient_cost.py [--frames 100] [--repeats 3]

For each case, the jit-compiled forward pass (reconstruct + a scalar loss: e3D against
the truth plus the error of the fitted tracks) and the jit-compiled value-and-gradient
with respect to the tracks (and delta for Huber) are timed after compilation, in one
run on one machine; the ratio is printed. The goal is a ratio of at most 3.
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402

import jaxnrsfm as nr  # noqa: E402

K = 4


def best_time(fn, *args, repeats):
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return min(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    cases = [
        ("direct, complete", dict(noise=2.0), dict(method="direct")),
        ("direct, 20% missing", dict(noise=2.0, missing_ratio=0.2), dict(method="direct")),
        ("huber, 10% outliers", dict(noise=2.0, outlier_ratio=0.1), dict(method="huber")),
        ("wang, 10% outliers", dict(noise=2.0, outlier_ratio=0.1), dict(method="wang")),
    ]
    print(f"{args.frames} frames x 252 points, k={K}, float64, {jax.devices()[0].device_kind}")
    print(f"{'case':<22} {'forward [s]':>11} {'value+grad [s]':>15} {'ratio':>6}")
    for name, data, method in cases:
        seq = nr.deformable_cube(jax.random.key(0), n_frames=args.frames, **data)
        W = jnp.where(jnp.repeat(seq.visible, 2, axis=0), seq.W, 0.0)
        huber = method["method"] == "huber"

        def loss(W, delta, seq=seq, method=method, huber=huber):
            strategy = nr.Huber(delta=delta) if huber else method["method"]
            rec = nr.reconstruct(W, seq.visible, k=K, method=strategy)
            inl = seq.visible & ~seq.outliers
            return nr.e3d(rec.shapes, seq.shapes) + nr.rms_error(seq.W_clean, rec.W_hat, inl)

        argnums = (0, 1) if huber else 0
        forward = best_time(jax.jit(loss), W, 1.345, repeats=args.repeats)
        backward = best_time(jax.jit(jax.value_and_grad(loss, argnums=argnums)), W, 1.345, repeats=args.repeats)
        print(f"{name:<22} {forward:11.3f} {backward:15.3f} {backward / forward:6.2f}", flush=True)


if __name__ == "__main__":
    main()
