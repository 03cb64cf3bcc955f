"""The ``jaxnrsfm`` command."""

import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

app = typer.Typer(
    help="Robust structure and motion factorization of nonrigid objects.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)
console = Console()


@app.callback()
def _main() -> None:
    """Robust structure and motion factorization of nonrigid objects."""


def _setup(float32: bool) -> None:
    import jax

    # The library never flips x64 on import; the command line chooses for the user.
    jax.config.update("jax_enable_x64", not float32)


@app.command()
def demo(
    out: Annotated[Path, typer.Option(help="Where to write the figure (PNG).")] = Path("demo_frames.png"),
    seed: Annotated[int, typer.Option(help="PRNG seed of the synthetic cube.")] = 0,
    noise: Annotated[float, typer.Option(help="Gaussian noise sigma, image units.")] = 2.0,
    outliers: Annotated[float, typer.Option(help="Fraction of entries made outliers.")] = 0.10,
    missing: Annotated[float, typer.Option(help="Fraction of entries hidden in the missing-data case.")] = 0.20,
    float32: Annotated[bool, typer.Option("--float32", help="Compute in float32 instead of float64.")] = False,
) -> None:
    """Reconstruct the paper's deformable cube by the registered rank-3k and the augmented
    rank-(3k+1) factorizations and compare both with the ground truth."""
    _setup(float32)
    import jax

    import jaxnrsfm as nr

    from .plot import plot_shapes

    k = 4
    cases = {
        f"{outliers:.0%} outliers": dict(noise=noise, outlier_ratio=outliers),
        f"{missing:.0%} missing": dict(noise=noise, missing_ratio=missing),
        "complete": dict(noise=noise),
    }
    table = Table(title=f"Deformable cube, 100 frames x 252 points, sigma={noise:g}, k={k}, seed {seed}")
    for col in ("data", "factorization", "RMS vs truth", "e3D", "status", "time [s]"):
        table.add_column(col, justify="left" if col in ("data", "factorization", "status") else "right")
    figure_input = None
    for name, kw in cases.items():
        seq = nr.deformable_cube(jax.random.key(seed), **kw)
        truth_mask = ~seq.outliers  # every entry whose true position is known and clean
        for form, rank in (("registered", 3 * k), ("augmented", 3 * k + 1)):
            t0 = time.perf_counter()
            rec = jax.block_until_ready(nr.reconstruct(seq.W, seq.visible, k=k, form=form))
            elapsed = time.perf_counter() - t0
            table.add_row(
                name,
                f"{form} rank {rank}",
                f"{float(nr.rms_error(seq.W_clean, rec.W_hat, truth_mask)):.3f}",
                f"{float(nr.e3d(rec.shapes, seq.shapes)):.4f}",
                _status(rec.status),
                f"{elapsed:.2f}",
            )
            if figure_input is None and form == "augmented":
                figure_input = (seq.shapes, rec.shapes, name)
        table.add_section()
    console.print(table)
    floors = ", ".join(f"{float(nr.statistical_floor(noise, 100, 252, r)):.3f} (rank {r})" for r in (3 * k, 3 * k + 1))
    console.print(
        "RMS vs truth: per-coordinate RMS of W_hat against the noise-free tracks over every entry that is "
        f"not an outlier, missing ones included. Statistical floor on complete data: {floors}. "
        "e3D: 3-D error against the true shapes (Akhter et al.)."
    )
    true_shapes, shapes, name = figure_input
    path = plot_shapes(true_shapes, shapes, out, title=f"Augmented rank-(3k+1) reconstruction ({name}) vs truth")
    console.print(f"figure: {path}")


def _status(status) -> str:
    from .status import Status

    return "ok" if bool(status == Status.success) else Status[status]
