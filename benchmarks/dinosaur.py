"""The paper's real-sequence test: the nonrigid dinosaur (231 frames, 49 points) with 8%
outliers from the library's injector; mean reprojection error on the inlying
observations, and outlier precision/recall, for every method.

    python benchmarks/dinosaur.py [--k K] [--trials 10] [--ratio 0.08] [--magnitude 20 100]

The paper reports 0.597 (robust), 0.926 (Huynh) and 0.733 (Ke & Kanade) on its own copy
of the tracks. The error of a trial is the mean of |e_ij| between the fit and the
original tracks over the entries that were not replaced by outliers. The paper does not
say how far its outliers were displaced; the baselines' errors depend on it steeply
(README: 5-25 px reproduces Huynh's figure, 10-50 px Ke & Kanade's).
"""

import argparse
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import jaxnrsfm as nr  # noqa: E402
from jaxnrsfm.datasets import load_nonrigid_dinosaur  # noqa: E402

OTHER_STATUSES = ("not_converged", "too_many_outliers", "nonfinite", "implausible")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--k", type=int, default=None, help="shape bases (default: jaxnrsfm.choose_k on the clean tracks)"
    )
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--ratio", type=float, default=0.08)
    parser.add_argument(
        "--magnitude",
        type=float,
        nargs=2,
        default=(20.0, 100.0),
        metavar=("MIN", "MAX"),
        help="outlier displacement range in pixels (the paper does not state its own)",
    )
    parser.add_argument("--methods", nargs="+", default=["direct", "huynh", "ke_kanade", "huber", "wang", "oracle"])
    args = parser.parse_args()
    tracks = load_nonrigid_dinosaur()
    W = jnp.asarray(tracks.W)
    visible = jnp.asarray(tracks.visible)
    keys = jax.vmap(jax.random.fold_in, (None, 0))(jax.random.key(0), jnp.arange(args.trials))
    Wo, outliers = jax.vmap(lambda key: nr.inject_outliers(key, W, visible, args.ratio, magnitude=args.magnitude))(keys)
    inl = visible & ~outliers
    if args.k is None:
        args.k = nr.choose_k(tracks.W, tracks.visible)
    direct = nr.reconstruct(W, visible, k=args.k, method="direct", shapes="upgrade")
    print(
        f"dinosaur {W.shape[0] // 2} frames x {W.shape[1]} points, k={args.k} (rank {3 * args.k + 1}), "
        f"{args.ratio:.0%} outliers of {args.magnitude[0]:g}-{args.magnitude[1]:g} px, {args.trials} trials; "
        "clean-track direct fit: mean error "
        f"{float(nr.mean_reprojection_error(W, direct.W_hat, visible)):.3f}"
    )
    # The status judges the Euclidean shapes too. The paper's own (shapes="upgrade") are
    # implausible on the dinosaur whatever the 2-D fit: with the oracle's fit they reproject
    # 375 px from it (a depth 2.4 times the in-plane extent, metric residual 0.12). This
    # 2-D comparison therefore runs the nuclear-norm shapes with the upgrade's rotations
    # (rotations="upgrade"), which leave W_hat as it is and are plausible where the fit is
    # sound (oracle: 0.5 px from the fit, depth 0.25 of the extent).
    print("ok: trials whose status is success; others: the other statuses, by name")
    print(
        f"{'method':>10} {'mean err':>9} {'(min..max)':>15} {'precision':>9} {'recall':>7} "
        f"{'ok':>4} {'s/trial':>8}  others"
    )
    for method in args.methods:
        t0 = time.perf_counter()
        # Reprojection errors: the rotation and shape steps do not change W_hat.
        strategy = nr.Oracle(outliers) if method == "oracle" else method
        rec = nr.reconstruct_batch(Wo, k=args.k, method=strategy, rotations="upgrade")
        rec = jax.block_until_ready(rec)
        elapsed = (time.perf_counter() - t0) / args.trials
        err = np.asarray(jax.vmap(nr.mean_reprojection_error, (None, 0, 0))(W, rec.W_hat, inl))
        found = visible & ~rec.inliers
        p, r = jax.vmap(nr.outlier_precision_recall, (0, 0, None))(found, outliers, visible)
        ok = int(jnp.sum(rec.status == nr.Status.success))
        counts = {name: int(jnp.sum(rec.status == getattr(nr.Status, name))) for name in OTHER_STATUSES}
        others = ", ".join(f"{name} {count}" for name, count in counts.items() if count) or "-"
        print(
            f"{method:>10} {err.mean():9.3f} {err.min():7.3f}..{err.max():6.3f} {float(jnp.mean(p)):9.3f} "
            f"{float(jnp.mean(r)):7.3f} {ok:4d} {elapsed:8.2f}  {others}",
            flush=True,
        )


if __name__ == "__main__":
    main()
