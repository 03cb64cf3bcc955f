"""The ``jaxnrsfm`` command."""

import json
import math
import time
import zipfile
from pathlib import Path
from typing import Annotated, NoReturn

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


_RECONSTRUCT_HELP = """Reconstruct a nonrigid object from its tracks and print a JSON summary on stdout.

INPUT is one of:

* .npz: array W (2m x n; rows 2i, 2i+1 = u, v of frame i; NaN = missing) and an optional boolean
  array visible (m x n).

* .mat (MATLAB v4-v7): the same 2m x n matrix in variable W, or the one --var names. Akhter et al.'s
  files hold W this way, with ground-truth shapes S (3m x n): then the summary reports e3D.

* .csv: the 2m x n matrix as a comma-separated table without a header, one matrix row per line (u of
  frame 0, v of frame 0, u of frame 1, ...); an empty cell or nan marks a missing coordinate.

The summary has the mean and RMS reprojection errors over the inliers, the number of observed entries
rejected as outliers, the status (name and message), the time of the reconstruction in seconds
(compilation included) and, with ground truth, e3D. Errors in the input print one line on stderr and
exit with status 1.
"""


class _InputError(ValueError):
    """Bad input found by the command itself; reported like the library's ValueErrors."""


@app.command(help=_RECONSTRUCT_HELP)
def reconstruct(
    tracks_file: Annotated[
        Path, typer.Argument(metavar="INPUT", help="Tracks: .npz, .mat or .csv.", show_default=False)
    ],
    k: Annotated[int, typer.Option("--k", help="Number of shape bases (1 = rigid).", show_default=False)],
    method: Annotated[
        str, typer.Option(help="direct, wang, huynh or ke_kanade (see jaxnrsfm.reconstruct).")
    ] = "direct",
    form: Annotated[
        str, typer.Option(help="augmented (rank 3k+1) or registered (rank 3k; direct only).")
    ] = "augmented",
    threshold: Annotated[
        float | None,
        typer.Option(help="Outlier threshold of the robust methods, in robust scales (default: chosen from the data)."),
    ] = None,
    out: Annotated[
        Path | None,
        typer.Option(help="Write W_hat, inliers, shapes, rotations, weights, bases, translations to this .npz."),
    ] = None,
    export: Annotated[
        Path | None,
        typer.Option(
            help="Write the 3-D shapes: FILE.ply or FILE.obj as one point cloud per frame (FILE_0000.ply, ...), "
            "FILE.wrl as one VRML97 file that plays the sequence.",
        ),
    ] = None,
    var: Annotated[str, typer.Option(help="The variable of a .mat INPUT that holds the tracks.")] = "W",
    frames: Annotated[
        str | None, typer.Option(help="Use only these frames: a Python slice START:STOP[:STEP], e.g. 0:100.")
    ] = None,
    fps: Annotated[float, typer.Option(help="Frame rate of the VRML animation.")] = 25.0,
    float32: Annotated[bool, typer.Option("--float32", help="Compute in float32 instead of float64.")] = False,
) -> None:
    _setup(float32)
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxnrsfm as nr

    from .export import export_format, export_shapes

    names = ("W_hat", "inliers", "shapes", "rotations", "weights", "bases", "translations")
    try:
        # Everything that can be checked is checked before the (slow) compilation.
        for path, option in ((out, "--out"), (export, "--export")):
            if path is not None and not path.parent.is_dir():
                raise _InputError(f"{option} {path}: the directory {path.parent} does not exist")
        if export is not None:
            export_format(export)
        if not fps > 0:
            raise _InputError(f"--fps must be positive; got {fps}")
        tracks = _read_tracks(tracks_file, var)
        W, visible, true_shapes = _select_frames(tracks, frames)
        W = W.astype(np.float32 if float32 else np.float64)  # an explicit float64 under float32 would warn
        t0 = time.perf_counter()
        rec = jax.block_until_ready(nr.reconstruct(W, visible, k=k, method=method, form=form, threshold=threshold))
        elapsed = time.perf_counter() - t0
        arrays = {name: np.asarray(getattr(rec, name)) for name in names}
        if out is not None:
            with open(out, "wb") as f:  # a file object: np.savez would append .npz to any other name
                np.savez(f, **arrays)
        exported = [] if export is None else export_shapes(export, arrays["shapes"], fps=fps, name=tracks.name)
    except (ValueError, OSError, KeyError) as err:
        _fail(err)

    Wj = jnp.asarray(W)
    summary = {
        "input": str(tracks_file),
        "frames": int(visible.shape[0]),
        "points": int(visible.shape[1]),
        "observed": int(visible.sum()),
        "k": k,
        "method": method,
        "form": form,
        "dtype": str(W.dtype),
        "mean_reprojection_error": _number(nr.mean_reprojection_error(Wj, rec.W_hat, rec.inliers)),
        "rms_reprojection_error": _number(nr.rms_error(Wj, rec.W_hat, rec.inliers)),
        "outliers": int(np.sum(visible & ~arrays["inliers"])),
        "status": _status_name(rec.status),
        "status_message": nr.Status[rec.status],
        "time_s": round(elapsed, 3),
        "e3d": None if true_shapes is None else _number(nr.e3d(rec.shapes, jnp.asarray(true_shapes, W.dtype))),
        "out": None if out is None else str(out),
        "export": None if not exported else str(exported[0]),
        "export_files": len(exported),
    }
    typer.echo(json.dumps(summary, indent=2))


def _fail(err: BaseException) -> NoReturn:
    # One line, no traceback: the messages of the library's errors name the problem already.
    message = " ".join(str(err).split()) or type(err).__name__
    if isinstance(err, KeyError):  # str(KeyError) is the bare quoted key
        message = f"missing {message}"
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(1)


def _read_tracks(path: Path, variable: str):
    from .datasets import load_tracks

    if not path.exists():
        raise _InputError(f"{path}: no such file")
    if not path.is_file():
        raise _InputError(f"{path}: not a file")
    if path.suffix.lower() == ".npz" and not zipfile.is_zipfile(path):
        # np.load would take a non-zip file for a pickle or a .npy and fail in other words.
        raise _InputError(f"{path}: not a .npz file (a zip archive of arrays, as numpy.savez writes)")
    try:
        return load_tracks(path, variable)
    except (zipfile.BadZipFile, EOFError) as err:
        raise _InputError(f"{path}: cannot be read ({err})") from None


def _select_frames(tracks, frames: str | None):
    """``W``, ``visible`` and the true shapes (or None) of the frames that ``frames`` selects."""
    import numpy as np

    m = tracks.visible.shape[0]
    index = np.arange(m)
    if frames is not None:
        parts = frames.split(":")
        try:
            if not 2 <= len(parts) <= 3:
                raise ValueError
            index = index[slice(*(int(p) if p.strip() else None for p in parts))]
        except ValueError:  # not integers, or a zero step
            raise _InputError(f"--frames {frames!r}: expected START:STOP or START:STOP:STEP, e.g. 0:100") from None
        if index.size == 0:
            raise _InputError(f"--frames {frames!r} selects no frame of the {m} in the input")
    rows = np.stack([2 * index, 2 * index + 1], axis=1).ravel()
    shapes = None if tracks.shapes is None else tracks.shapes[index]
    return tracks.W[rows], tracks.visible[index], shapes


def _number(x) -> float | None:
    # JSON has no NaN or infinity.
    x = float(x)
    return x if math.isfinite(x) else None


def _status_name(status) -> str:
    from .status import Status

    # equinox keeps an Enumeration's names only in this table; the message is public (Status[item]).
    return next(name for name, item in Status._name_to_item.items() if bool(status == item))
