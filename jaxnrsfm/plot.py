"""Figures. matplotlib is imported lazily, with the non-interactive Agg backend, so that
the library itself never needs a display."""

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .metrics import align_shapes


def plot_shapes(
    true_shapes,
    shapes,
    path: str | Path,
    *,
    frames: Sequence[int] = (0, 33, 66, 99),
    title: str = "",
    edges=None,
) -> Path:
    """Write a PNG of reconstructed shapes (aligned to the truth by the one orthogonal
    transform of e3D) over the true ones, one 3-D panel per frame; ``edges`` (E, 2)
    point-index pairs, such as a skeleton's bones, are drawn as segments. ``shapes`` is one
    ``(m, 3, n)`` array, or a mapping from labels to such arrays: one row of panels each
    (say, the direct fit above the robust one)."""
    plt = _pyplot()
    rows = shapes if isinstance(shapes, Mapping) else {"reconstruction": shapes}
    Y = np.asarray(true_shapes)
    Y = Y - Y.mean(axis=2, keepdims=True)
    frames = [f for f in frames if f < Y.shape[0]]
    fig = plt.figure(figsize=(4 * len(frames), 4.4 * len(rows)))
    for row, (label, rec) in enumerate(rows.items()):
        X = np.asarray(align_shapes(rec, true_shapes))
        for col, f in enumerate(frames):
            ax = fig.add_subplot(len(rows), len(frames), row * len(frames) + col + 1, projection="3d")
            ax.scatter(*Y[f], s=14, facecolors="none", edgecolors="tab:blue", label="truth")
            ax.scatter(*X[f], s=10, marker="x", color="tab:red", label=label)
            for a, b in [] if edges is None else np.asarray(edges):
                ax.plot(*Y[f][:, [a, b]], color="tab:blue", lw=1)
                ax.plot(*X[f][:, [a, b]], color="tab:red", lw=1)
            ax.set_title(f"{label}: frame {f}" if len(rows) > 1 else f"frame {f}")
            ax.set_box_aspect((1, 1, 1))
            lim = np.abs(Y[f]).max() * 1.1
            ax.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(-lim, lim))
            ax.tick_params(labelsize=6)
            if col == 0:
                ax.legend(loc="upper left", fontsize=8)
    return _save(fig, path, title)


def _save(fig, path: str | Path, title: str = "") -> Path:
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)
    return path


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_sweep(result: dict, path: str | Path) -> Path:
    """The paper's Fig. 5 from `jaxnrsfm.sweep.run_sweep`'s result: mean error on
    the inliers against the noise-free tracks vs the noise level, one panel per outlier
    ratio, one line per method, with the statistical floor of a rank-(3k+1) fit."""
    plt = _pyplot()
    cells = result["cells"]
    ratios = sorted({c["outliers"] for c in cells})
    methods = list(dict.fromkeys(c["method"] for c in cells))
    fig, axes = plt.subplots(1, len(ratios), figsize=(5.2 * len(ratios), 4.2), squeeze=False)
    for ax, ratio in zip(axes[0], ratios, strict=True):
        for method in methods:
            rows = sorted(
                (c["noise"], np.mean(c["error"])) for c in cells if c["outliers"] == ratio and c["method"] == method
            )
            ax.plot(*zip(*rows, strict=True), marker="o", label=method)
        noise = sorted(float(s) for s in result["floor"])
        ax.plot(noise, [result["floor"][str(s)] for s in noise], "k--", label="statistical floor")
        ax.set(xlabel="noise sigma [image units]", ylabel="mean inlier error vs truth", title=f"{ratio:.0%} outliers")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    trials = result["settings"]["trials"]
    return _save(fig, path, f"Deformable cube, {trials} trials per point (Fig. 5 protocol)")


def plot_residuals(noise, displacements, residuals, threshold: float, path: str | Path, title: str = "") -> Path:
    """The paper's Fig. 1: histograms of the injected noise and outlier displacement
    lengths, and of the reprojection residuals ``|e_ij|`` with the outlier threshold."""
    plt = _pyplot()
    fig, (a, b) = plt.subplots(1, 2, figsize=(11, 4))
    a.hist(np.asarray(noise).ravel(), bins=80, color="tab:blue", alpha=0.7, label="noise |n_ij|")
    a.hist(np.asarray(displacements).ravel(), bins=80, color="tab:red", alpha=0.7, label="outliers |o_ij|")
    a.set(xlabel="length [image units]", ylabel="entries", title="injected noise and outliers", yscale="log")
    a.legend()
    b.hist(np.asarray(residuals).ravel(), bins=120, color="tab:gray")
    b.axvline(threshold, color="k", ls="--", label=f"threshold {threshold:.2f}")
    b.set(xlabel="|e_ij| [image units]", ylabel="entries", title="reprojection residuals", yscale="log")
    b.legend()
    return _save(fig, path, title)
