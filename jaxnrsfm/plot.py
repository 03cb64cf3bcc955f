"""Figures. matplotlib is imported lazily, with the non-interactive Agg backend, so that
the library itself never needs a display."""

from collections.abc import Sequence
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
) -> Path:
    """Write a PNG of reconstructed shapes (aligned to the truth by the one orthogonal
    transform of e3D) beside the true ones, one 3-D panel per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    Y = np.asarray(true_shapes)
    X = np.asarray(align_shapes(shapes, true_shapes))
    Y = Y - Y.mean(axis=2, keepdims=True)
    frames = [f for f in frames if f < Y.shape[0]]
    fig = plt.figure(figsize=(4 * len(frames), 4.4))
    for col, f in enumerate(frames):
        ax = fig.add_subplot(1, len(frames), col + 1, projection="3d")
        ax.scatter(*Y[f], s=14, facecolors="none", edgecolors="tab:blue", label="truth")
        ax.scatter(*X[f], s=10, marker="x", color="tab:red", label="reconstruction")
        ax.set_title(f"frame {f}")
        ax.set_box_aspect((1, 1, 1))
        lim = np.abs(Y[f]).max() * 1.1
        ax.set(xlim=(-lim, lim), ylim=(-lim, lim), zlim=(-lim, lim))
        ax.tick_params(labelsize=6)
    fig.axes[0].legend(loc="upper left", fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
