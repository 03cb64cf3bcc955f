"""e3D on the Akhter motion-capture sequences beside the published PTA and BMM numbers.

For every sequence: k from the tracks alone (:func:`jaxnrsfm.choose_k`), then the same
methods with the same settings:

* ``upgrade``: ``reconstruct(W, k=k)`` (metric upgrade only, the default pipeline);
* ``refine/GN``: ``refine=True`` (nuclear-norm shapes given the upgrade's rotations);
* ``refine/TN``: ``refine=True, trace_norm=0.1`` (nuclear-norm shapes given Dai et al.'s
  trace-norm rotations);
* ``refine/HR``: ``refine=True, rotation_rank=n - 2`` (nuclear-norm shapes given the
  rotations from a rank-``n - 2`` factorization of the ``n`` points' tracks,
  :func:`jaxnrsfm.refine.high_rank_rotations`);
* ``wang/GN``: ``method="wang", refine=True`` (the robust pipeline: the paper's outlier
  rejection, then as refine/GN);
* ``wang/HR``: the robust pipeline with ``rotation_rank=n - 2``.

Then the variants of ``DEGRADED`` again, on the complete tracks with 30% of the entries
hidden at random (:func:`jaxnrsfm.drop_entries`) and, the robust ones, on the tracks with
10% outliers from :func:`jaxnrsfm.inject_outliers` (displacements of 2.5--12.5% of the
tracks' extent, the paper's 20--100 pixels on an 800-pixel image), each against its own
clean-data e3D.

Writes a figure of reconstructed (red) vs true (blue) skeletons for a few frames of every
sequence. Run: ``python benchmarks/real_sequences.py [--out real_sequences.png]``.
Needs ``shared/data`` (see ``jaxnrsfm.datasets.data_dir``).
"""

import argparse
import time

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxnrsfm as nr  # noqa: E402
from jaxnrsfm import datasets  # noqa: E402

PTA = {"drink": 0.0250, "pickup": 0.2369, "yoga": 0.1625, "stretch": 0.1088, "dance": 0.2956}
BMM = {"drink": 0.027, "pickup": 0.173, "yoga": 0.115, "stretch": 0.103, "dance": 0.186}
VARIANTS = {
    "upgrade": {},
    "refine/GN": {"refine": True},
    "refine/TN": {"refine": True, "trace_norm": 0.1},
    "refine/HR": {"refine": True, "rotation_rank": "n - 2"},
    "wang/GN": {"method": "wang", "refine": True},
    "wang/HR": {"method": "wang", "refine": True, "rotation_rank": "n - 2"},
}
DEGRADED = ("refine/HR", "wang/GN", "wang/HR")
"""The variants run again on degraded tracks (outliers only for the robust ones)."""
FIGURE_VARIANT = "refine/HR"


def _settings(label: str, n_points: int) -> dict:
    kwargs = VARIANTS[label]
    if kwargs.get("rotation_rank") == "n - 2":
        kwargs = {**kwargs, "rotation_rank": n_points - 2}
    return kwargs


def run(name: str) -> dict:
    seq = datasets.load_akhter(name)
    k = nr.choose_k(seq.W, seq.visible)
    out = {"k": k, "seq": seq}
    for label in VARIANTS:
        t = time.perf_counter()
        rec = nr.reconstruct(seq.W, seq.visible, k=k, **_settings(label, seq.W.shape[1]))
        e = float(nr.e3d(rec.shapes, seq.shapes))
        out[label] = (e, time.perf_counter() - t, rec)
    return out


def degraded(seq, k: int, label: str) -> tuple[float | None, float | None, float]:
    """A variant's e3D with 10% outliers (robust variants only, else None) and with 30%
    missing entries, and the outlier recall."""
    W = jnp.asarray(seq.W)
    settings = _settings(label, W.shape[1])
    outl = recall = None
    if settings.get("method") == "wang":
        extent = float(W.max() - W.min())
        magnitude = (0.025 * extent, 0.125 * extent)
        W_out, outliers = nr.inject_outliers(jax.random.key(1), W, ratio=0.1, magnitude=magnitude)
        rec = nr.reconstruct(W_out, k=k, **settings)
        recall = float(np.mean(~np.asarray(rec.inliers)[np.asarray(outliers)]))
        outl = float(nr.e3d(rec.shapes, seq.shapes))
    visible = nr.drop_entries(jax.random.key(2), jnp.ones(seq.shapes[:, 0].shape, bool), 0.3)
    missing = nr.reconstruct(W, visible, k=k, **settings)
    return outl, float(nr.e3d(missing.shapes, seq.shapes)), recall


def figure(results: dict, path: str, frames_per_sequence: int = 3) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    fig = plt.figure(figsize=(3.2 * frames_per_sequence, 3.2 * len(names)))
    for row, name in enumerate(names):
        seq, rec = results[name]["seq"], results[name][FIGURE_VARIANT][2]
        Y = seq.shapes - seq.shapes.mean(axis=2, keepdims=True)
        X = np.asarray(nr.align_shapes(rec.shapes, seq.shapes))
        scale = np.mean(np.std(seq.shapes, axis=2))
        m = Y.shape[0]
        for col, f in enumerate(np.linspace(0, m - 1, frames_per_sequence + 2)[1:-1].astype(int)):
            ax = fig.add_subplot(len(names), frames_per_sequence, row * frames_per_sequence + col + 1, projection="3d")
            for P, color in ((Y[f], "tab:blue"), (X[f], "tab:red")):
                if seq.edges is not None:
                    for a, b in seq.edges:
                        ax.plot(*P[:, [a, b]], color=color, lw=1.2)
                ax.scatter(*P, s=4, color=color)
            err = np.mean(np.linalg.norm(X[f] - Y[f], axis=0)) / scale
            ax.set_title(f"{name} frame {f}  e3D_f={err:.3f}", fontsize=8)
            lim = np.abs(Y[f]).max() * 1.1
            ax.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(-lim, lim))
            ax.set_box_aspect((1, 1, 1))
            ax.tick_params(labelsize=5)
    fig.suptitle(f"truth (blue) vs {FIGURE_VARIANT} (red), one orthogonal alignment per sequence", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="real_sequences.png", help="figure path")
    parser.add_argument("--sequences", default=",".join(datasets.AKHTER_SEQUENCES))
    args = parser.parse_args()
    results = {}
    head = f"{'sequence':8} {'k':>2} " + " ".join(f"{v:>10}" for v in VARIANTS) + f" {'PTA':>7} {'BMM':>6}  seconds"
    print(head)
    for name in args.sequences.split(","):
        r = results[name] = run(name)
        cells = " ".join(f"{r[v][0]:10.4f}" for v in VARIANTS)
        times = "/".join(f"{r[v][1]:.1f}" for v in VARIANTS)
        print(f"{name:8} {r['k']:2d} {cells} {PTA[name]:7.4f} {BMM[name]:6.3f}  {times}", flush=True)
    for label in DEGRADED:
        print(f"\n{label} with degraded tracks (change against its clean e3D)")
        print(f"{'sequence':8} {'clean':>7} {'10% outliers':>18} {'recall':>6} {'30% missing':>18}")
        for name, r in results.items():
            clean = r[label][0]
            outl, miss, recall = degraded(r["seq"], r["k"], label)
            robust = f"{outl:8.4f} ({outl / clean - 1:+6.1%}) {recall:6.3f}" if outl is not None else " " * 25
            print(f"{name:8} {clean:7.4f} {robust} {miss:8.4f} ({miss / clean - 1:+6.1%})", flush=True)
    figure(results, args.out)
    print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
