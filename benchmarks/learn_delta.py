"""Learn the Huber parameter delta by gradient descent through the whole pipeline.

    python benchmarks/learn_delta.py [--train 4] [--test 16] [--steps 10] [--frames 100]

The loss is the mean, over mapped synthetic trials (the deformable cube, sigma = 2,
20% outliers), of the RMS error of the Huber fit against the noise-free tracks on the
true inliers -- what a user of the method wants small, and what the classic
delta = 1.345 (95% Gaussian efficiency) does not aim at. delta is learned in log space
with Adam (optax); the gradient flows through the Huber solve by the implicit function
theorem (jaxnrsfm.implicit). The learned delta is then compared with the default on
fresh trials, never seen in training.
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import optax  # noqa: E402

import jaxnrsfm as nr  # noqa: E402

K = 4
DEFAULT = 1.345


def trials(seed, count, frames, noise, outliers):
    keys = jax.vmap(jax.random.fold_in, (None, 0))(jax.random.key(seed), jnp.arange(count))
    return jax.vmap(lambda key: nr.deformable_cube(key, noise=noise, outlier_ratio=outliers, n_frames=frames))(keys)


def error(delta, seq):
    rec = nr.reconstruct(seq.W, seq.visible, k=K, method=nr.Huber(delta=delta))
    return nr.rms_error(seq.W_clean, rec.W_hat, seq.visible & ~seq.outliers)


def mean_error(log_delta, seqs):
    # lax.map, not vmap: under vmap every trial's LM and CG iterations run in lockstep
    # until the slowest trial converges, several times slower at this size on a CPU.
    # The gradient is the same either way (tests/test_gradients.py checks vmap == loop).
    delta = jnp.exp(log_delta)
    return jnp.mean(jax.lax.map(lambda seq: error(delta, seq), seqs))


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--train", type=int, default=4)
    parser.add_argument("--test", type=int, default=16)
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--noise", type=float, default=2.0)
    parser.add_argument("--outliers", type=float, default=0.2)
    args = parser.parse_args()
    train = trials(0, args.train, args.frames, args.noise, args.outliers)
    test = trials(1, args.test, args.frames, args.noise, args.outliers)
    print(f"cube {args.frames} frames x 252 points, sigma={args.noise}, {args.outliers:.0%} outliers, k={K}")
    print(f"{args.train} training trials, {args.test} held-out trials (different seed)")

    value_and_grad = jax.jit(jax.value_and_grad(mean_error))
    optimizer = optax.adam(0.2)
    log_delta = jnp.log(jnp.asarray(DEFAULT))
    state = optimizer.init(log_delta)
    t0 = time.perf_counter()
    for step in range(args.steps):
        loss, grad = value_and_grad(log_delta, train)
        delta = float(jnp.exp(log_delta))
        print(f"step {step:2d}  delta {delta:.4f}  train error {float(loss):.5f}  d/dlog(delta) {float(grad):+.5f}")
        updates, state = optimizer.update(grad, state)
        log_delta = optax.apply_updates(log_delta, updates)
    print(f"training: {time.perf_counter() - t0:.1f} s (first step includes compilation)")

    evaluate = jax.jit(mean_error)
    learned = float(jnp.exp(log_delta))
    default_err = float(evaluate(jnp.log(DEFAULT), test))
    learned_err = float(evaluate(log_delta, test))
    print(f"held-out mean error: default delta {DEFAULT} -> {default_err:.5f}")
    print(f"                     learned delta {learned:.4f} -> {learned_err:.5f}")
    print(f"relative change: {learned_err / default_err - 1:+.2%}")


if __name__ == "__main__":
    main()
