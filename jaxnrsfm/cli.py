"""The ``jaxnrsfm`` command."""

import time
from pathlib import Path

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
    out: Path = typer.Option(Path("demo_frames.png"), help="Where to write the figure (PNG)."),
    seed: int = typer.Option(0, help="PRNG seed of the synthetic cube."),
    noise: float = typer.Option(2.0, help="Gaussian noise sigma, image units."),
    outliers: float = typer.Option(0.10, help="Fraction of entries made outliers."),
    missing: float = typer.Option(0.20, help="Fraction of entries hidden in the missing-data case."),
    float32: bool = typer.Option(False, "--float32", help="Compute in float32 instead of float64."),
) -> None:
    """Reconstruct the paper's deformable cube by the registered rank-3k and the augmented
    rank-(3k+1) factorizations and compare both with the ground truth."""
    _setup(float32)
    import jax

    import jaxnrsfm as nr

    from .plot import plot_shapes

    k = 4
    cases = {
        f"sigma={noise:g}, {outliers:.0%} outliers": dict(noise=noise, outlier_ratio=outliers),
        f"sigma={noise:g}, {missing:.0%} missing": dict(noise=noise, missing_ratio=missing),
        f"sigma={noise:g}, no outliers": dict(noise=noise),
    }
    table = Table(title=f"Deformable cube, 100 frames x 252 points, k={k}, seed {seed}")
    for col in ("data", "factorization", "RMS vs truth", "floor", "e3D", "status", "time [s]"):
        table.add_column(col, justify="left" if col in ("data", "factorization", "status") else "right")
    figure_input = None
    for name, kw in cases.items():
        seq = nr.deformable_cube(jax.random.key(seed), **kw)
        truth_mask = ~seq.outliers  # every entry whose true position is known and clean
        for form, rank in (("registered", 3 * k), ("augmented", 3 * k + 1)):
            t0 = time.perf_counter()
            rec = jax.block_until_ready(nr.reconstruct(seq.W, seq.visible, k=k, form=form))
            elapsed = time.perf_counter() - t0
            m, n = seq.visible.shape
            table.add_row(
                name,
                f"{form} rank {rank}",
                f"{float(nr.rms_error(seq.W_clean, rec.W_hat, truth_mask)):.3f}",
                f"{float(nr.statistical_floor(noise, m, n, rank)):.3f}",
                f"{float(nr.e3d(rec.shapes, seq.shapes)):.4f}",
                _status(rec.status),
                f"{elapsed:.2f}",
            )
            if figure_input is None and form == "augmented":
                figure_input = (seq.shapes, rec.shapes, name)
        table.add_section()
    console.print(table)
    console.print(
        "RMS vs truth: per-coordinate RMS of W_hat against the noise-free tracks over every "
        "entry that is not an outlier (missing ones included); floor: sigma*sqrt(r(2m+n-r)/(2mn))."
    )
    true_shapes, shapes, name = figure_input
    path = plot_shapes(
        true_shapes, shapes, out, title=f"Augmented rank-(3k+1) reconstruction ({name}) vs truth"
    )
    console.print(f"figure: {path}")


def _status(status) -> str:
    from .status import Status

    return "success" if bool(status == Status.success) else Status[status]
