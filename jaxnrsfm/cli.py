"""The ``jaxnrsfm`` command."""

import functools
import json
import math
import os
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


CACHE_ENV = "JAXNRSFM_CACHE"
"""Environment variable naming the folder of the command's compilation cache ('' turns it off)."""


def _setup(float32: bool) -> None:
    import jax

    # The library never flips x64 on import; the command line chooses for the user.
    jax.config.update("jax_enable_x64", not float32)
    # A command is a fresh process whose jit caches start empty: JAX's persistent cache lets a
    # second call on the same shapes load the compiled programs instead of compiling them again
    # (on the cube's robust pipeline, ~17 s of XLA compilation). A cache the caller configured
    # (or a library user's own) is left alone. Every program is kept, not only those that took
    # JAX's default of a second to compile: a small sequence's whole pipeline can compile faster.
    folder = os.environ.get(CACHE_ENV, str(Path.home() / ".cache" / "jaxnrsfm"))
    if folder and jax.config.jax_compilation_cache_dir is None:
        jax.config.update("jax_compilation_cache_dir", folder)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    _listen_to_compilations()


_compiled = {"seconds": 0.0, "cache_hits": 0, "cache_writes": 0}


@functools.cache  # once a process: the listeners cannot be removed
def _listen_to_compilations() -> None:
    """Count the time XLA spends compiling (or loading from the cache), the cache's hits, and
    the programs compiled and written to it (JAX's ``cache_misses`` event, recorded as it writes)."""
    import jax

    def on_duration(event: str, seconds: float, **_) -> None:
        if event == "/jax/core/compile/backend_compile_duration":
            _compiled["seconds"] += seconds

    def on_event(event: str, **_) -> None:
        if event == "/jax/compilation_cache/cache_hits":
            _compiled["cache_hits"] += 1
        elif event == "/jax/compilation_cache/cache_misses":
            _compiled["cache_writes"] += 1

    jax.monitoring.register_event_duration_secs_listener(on_duration)
    jax.monitoring.register_event_listener(on_event)


@app.command(epilog="Example: jaxnrsfm demo --noise 3 --outliers 0.2 --out cube.png")
def demo(
    out: Annotated[Path, typer.Option(help="Where to write the figure (PNG).")] = Path("demo_frames.png"),
    seed: Annotated[int, typer.Option(help="PRNG seed of the synthetic cube.")] = 0,
    noise: Annotated[float, typer.Option(help="Gaussian noise sigma, image units.")] = 2.0,
    outliers: Annotated[float, typer.Option(help="Fraction of entries made outliers.")] = 0.10,
    missing: Annotated[float, typer.Option(help="Fraction of entries hidden in the missing-data case.")] = 0.20,
    frames: Annotated[int, typer.Option(min=12, help="Frames of the cube (the paper's: 100).")] = 100,
    float32: Annotated[bool, typer.Option("--float32", help="Compute in float32 instead of float64.")] = False,
) -> None:
    """The paper's result on its deformable cube: the robust method beside the direct fit, the
    baselines and the oracle, with outliers; then the registered rank-3k and the augmented
    rank-(3k+1) factorizations with outliers, missing entries and complete tracks."""
    _setup(float32)
    import jax

    import jaxnrsfm as nr

    from .plot import plot_shapes

    k, rank = 4, 13
    points = 252
    floor = float(nr.statistical_floor(noise, frames, points, rank))

    def run(seq, **kwargs):
        t0 = time.perf_counter()
        rec = jax.block_until_ready(nr.reconstruct(seq.W, seq.visible, k=k, shapes="upgrade", **kwargs))
        return rec, time.perf_counter() - t0

    def errors(seq, rec):
        # Against the noise-free tracks, over every entry that is not an outlier (missing ones too).
        rms = nr.rms_error(seq.W_clean, rec.W_hat, ~seq.outliers)
        return f"{float(rms):.3f}", f"{float(nr.e3d(rec.shapes, seq.shapes)):.4f}"

    # 1. The paper's comparison (its Fig. 5 protocol, one trial): every outlier strategy on the
    #    augmented rank-(3k+1) factorization, then the metric upgrade.
    seq = nr.deformable_cube(jax.random.key(seed), n_frames=frames, noise=noise, outlier_ratio=outliers)
    table = Table(
        title=f"Deformable cube with {outliers:.0%} outliers, {frames} frames x {points} points, "
        f"sigma={noise:g}, k={k} (augmented rank {rank}), seed {seed}"
    )
    for col in ("method", "RMS vs truth", "/ floor", "e3D", "precision", "recall", "status", "time [s]"):
        # Numbers and method names whole on a narrow terminal; headers and statuses may wrap.
        table.add_column(col, justify="left" if col in ("method", "status") else "right", no_wrap=col != "status")
    shown = {}
    for method, label in METHOD_LABELS.items():
        rec, elapsed = run(seq, method=nr.Oracle(seq.outliers) if method == "oracle" else method)
        precision, recall = nr.outlier_precision_recall(seq.visible & ~rec.inliers, seq.outliers, seq.visible)
        rms, e3d = errors(seq, rec)
        table.add_row(
            label,
            rms,
            f"{float(rms) / floor:.2f}",
            e3d,
            f"{float(precision):.3f}",
            f"{float(recall):.3f}",
            _status(rec.status),
            f"{elapsed:.2f}",
        )
        if method in ("direct", "wang"):
            shown[f"{label}, e3D {e3d}"] = rec.shapes
    console.print(table)
    console.print(
        "RMS vs truth: per-coordinate RMS of W_hat against the noise-free tracks over every entry that is "
        f"not an outlier. Statistical floor (a rank-{rank} least-squares fit of the same tracks without "
        f"outliers): {floor:.3f}. e3D: 3-D error against the true shapes (Akhter et al.). Precision and "
        "recall of the entries each method reports as outliers (the direct fit reports none). Methods: "
        "direct = least squares, huynh = Huynh et al., ke_kanade = Ke & Kanade's L1, huber = the Huber loss, "
        "wang = the paper's robust algorithm, oracle = least squares told the true outliers."
    )

    # 2. Registered against augmented, with the direct fit.
    cases = {
        f"{outliers:.0%} outliers": dict(noise=noise, outlier_ratio=outliers),
        f"{missing:.0%} missing": dict(noise=noise, missing_ratio=missing),
        "complete": dict(noise=noise),
    }
    table = Table(title=f"Registered rank-3k against augmented rank-(3k+1), direct fit, sigma={noise:g}, k={k}")
    for col in ("data", "factorization", "RMS vs truth", "e3D", "status", "time [s]"):
        table.add_column(col, justify="left" if col in ("data", "factorization", "status") else "right")
    for name, kw in cases.items():
        case = nr.deformable_cube(jax.random.key(seed), n_frames=frames, **kw)
        for form, r in (("registered", 3 * k), ("augmented", 3 * k + 1)):
            rec, elapsed = run(case, method="direct", form=form)
            table.add_row(name, f"{form} rank {r}", *errors(case, rec), _status(rec.status), f"{elapsed:.2f}")
        table.add_section()
    console.print(table)
    path = plot_shapes(
        seq.shapes,
        shown,
        out,
        frames=[round(f * (frames - 1)) for f in (0, 1 / 3, 2 / 3, 1)],
        title=f"The cube with {outliers:.0%} outliers: the direct fit (top) and the robust method (bottom) vs truth",
    )
    console.print(f"figure: {path}")


METHOD_LABELS = {
    "direct": "direct",
    "huynh": "huynh",
    "ke_kanade": "ke_kanade",
    "huber": "huber",
    "wang": "wang (robust)",
    "oracle": "oracle",
}
"""The demo's rows: ``reconstruct``'s methods under their ``method=`` names (least squares;
Huynh et al.'s and Ke & Kanade's baselines; the Huber loss; the paper's robust algorithm;
least squares told the true outliers)."""


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

The defaults are jaxnrsfm.reconstruct's: k chosen from the tracks, the paper's robust method, rotations
from a high-rank factorization and the nuclear-norm shapes.

The summary has the k used, the mean and RMS reprojection errors over the inliers, the number of
observed entries rejected as outliers, the status (name and message), the time of the reconstruction
in seconds (compilation included), the part of it XLA spent compiling or loading compiled programs
from the cache ($JAXNRSFM_CACHE, default ~/.cache/jaxnrsfm; '' turns it off) and, with ground truth,
e3D (in the ground truth's frame: the camera frame for a static camera, as Akhter's dance). Errors
in the input print one line on stderr and exit with status 1.

Example: jaxnrsfm reconstruct ../shared/data/akhter/drink.mat --out drink.npz --export drink.wrl
"""


class _InputError(ValueError):
    """Bad input found by the command itself; reported like the library's ValueErrors."""


# The help's panels: one per stage.
_OUT, _ROT, _SHAPE, _SOLVER = "Outlier strategy", "Rotation recovery", "Shape step", "Missing-data solver"


@app.command(
    help=_RECONSTRUCT_HELP,
    epilog="Examples: jaxnrsfm reconstruct ../shared/data/akhter/drink.mat --out drink.npz --export drink.wrl  |  "
    "jaxnrsfm reconstruct tracks.csv --k 3 --method huber --delta 2 --shapes upgrade",
)
def reconstruct(
    tracks_file: Annotated[
        Path, typer.Argument(metavar="INPUT", help="Tracks: .npz, .mat or .csv.", show_default=False)
    ],
    k: Annotated[
        int | None,
        typer.Option(
            "--k", help="Number of shape bases (1 = rigid); default: chosen from the tracks.", show_default=False
        ),
    ] = None,
    method: Annotated[
        str, typer.Option(help="Outlier strategy: wang, direct, huynh, ke_kanade, huber or l1.", rich_help_panel=_OUT)
    ] = "wang",
    threshold: Annotated[
        float | None,
        typer.Option(
            help="wang, ke_kanade, huber, l1: outlier threshold in robust scales [the residual model's boundary].",
            show_default=False,
            rich_help_panel=_OUT,
        ),
    ] = None,
    passes: Annotated[
        int | None, typer.Option(help="wang: minimum rejection passes [3].", show_default=False, rich_help_panel=_OUT)
    ] = None,
    unweighted: Annotated[
        bool, typer.Option("--unweighted", help="wang: skip step 5's weighted fit.", rich_help_panel=_OUT)
    ] = False,
    iterations: Annotated[
        int | None, typer.Option(help="huynh: correction iterations [10].", show_default=False, rich_help_panel=_OUT)
    ] = None,
    delta: Annotated[
        float | None,
        typer.Option(help="huber: the loss's kink in robust scales [1.345].", show_default=False, rich_help_panel=_OUT),
    ] = None,
    rotations: Annotated[
        str | None,
        typer.Option(
            help="Rotation recovery: high_rank, upgrade or trace_norm [the shape step's: high_rank for nuclear, "
            "upgrade for upgrade].",
            show_default=False,
            rich_help_panel=_ROT,
        ),
    ] = None,
    rotation_rank: Annotated[
        int | None,
        typer.Option(
            help="high_rank: rank of the factorization [every direction of the tracks above the noise].",
            show_default=False,
            rich_help_panel=_ROT,
        ),
    ] = None,
    starts: Annotated[
        int | None, typer.Option(help="high_rank: random starts [16].", show_default=False, rich_help_panel=_ROT)
    ] = None,
    refills: Annotated[
        int | None,
        typer.Option(help="high_rank: refills of unobserved entries [2].", show_default=False, rich_help_panel=_ROT),
    ] = None,
    held_out: Annotated[
        float | None,
        typer.Option(
            help="high_rank: fraction of entries the solve sees only through the refills [0].",
            show_default=False,
            rich_help_panel=_ROT,
        ),
    ] = None,
    trace_norm_weight: Annotated[
        float | None,
        typer.Option(help="trace_norm: weight of the trace norm [0.1].", show_default=False, rich_help_panel=_ROT),
    ] = None,
    camera: Annotated[
        str | None,
        typer.Option(
            help="high_rank: the camera's motion, constant_velocity (where the rotations follow one) or free "
            "[constant_velocity].",
            show_default=False,
            rich_help_panel=_ROT,
        ),
    ] = None,
    shapes: Annotated[
        str,
        typer.Option(
            help="Shape step: nuclear (Dai et al.'s nuclear-norm shapes) or upgrade (the paper's H^-1 S).",
            rich_help_panel=_SHAPE,
        ),
    ] = "nuclear",
    shape_steps: Annotated[
        int | None,
        typer.Option(
            help="nuclear: ADMM iterations (also of high_rank's refills) [500].",
            show_default=False,
            rich_help_panel=_SHAPE,
        ),
    ] = None,
    shape_rho: Annotated[
        float | None, typer.Option(help="nuclear: ADMM penalty [1.0].", show_default=False, rich_help_panel=_SHAPE)
    ] = None,
    raw_tracks: Annotated[
        bool,
        typer.Option(
            "--raw-tracks",
            help="nuclear: reproject onto the inliers themselves, not their part above the noise.",
            rich_help_panel=_SHAPE,
        ),
    ] = False,
    max_steps: Annotated[
        int, typer.Option(help="Missing-data solver: most ALS sweeps.", rich_help_panel=_SOLVER)
    ] = 500,
    rtol: Annotated[float, typer.Option(help="Missing-data solver: ALS tolerance.", rich_help_panel=_SOLVER)] = 1e-10,
    varpro: Annotated[
        str,
        typer.Option(
            help="Missing-data solver: finish least-squares fits by VarPro: never, stalled or always.",
            rich_help_panel=_SOLVER,
        ),
    ] = "never",
    form: Annotated[
        str, typer.Option(help="augmented (rank 3k+1) or registered (rank 3k; direct only).")
    ] = "augmented",
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
    surface: Annotated[
        bool,
        typer.Option(
            "--surface",
            help="With --export: triangulated surfaces (Delaunay of the first frame's points in its image plane, "
            "the same triangles in every frame) instead of point clouds.",
        ),
    ] = False,
    var: Annotated[str, typer.Option(help="The variable of a .mat INPUT that holds the tracks.")] = "W",
    frames: Annotated[
        str | None, typer.Option(help="Use only these frames: a Python slice START:STOP[:STEP], e.g. 0:100.")
    ] = None,
    fps: Annotated[float, typer.Option(help="Frame rate of the VRML animation.")] = 25.0,
    float32: Annotated[bool, typer.Option("--float32", help="Compute in float32 instead of float64.")] = False,
) -> None:
    _setup(float32)
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import numpy as np

    import jaxnrsfm as nr

    from .export import export_format, export_shapes, triangulate

    names = ("W_hat", "inliers", "shapes", "rotations", "weights", "bases", "translations")
    try:
        # Everything that can be checked is checked before the (slow) compilation.
        for path, option in ((out, "--out"), (export, "--export")):
            if path is not None and not path.parent.is_dir():
                raise _InputError(f"{option} {path}: the directory {path.parent} does not exist")
        if export is not None:
            export_format(export)
        elif surface:
            raise _InputError("--surface shapes the --export files; give --export FILE")
        if not fps > 0:
            raise _InputError(f"--fps must be positive; got {fps}")
        given = {
            "--threshold": threshold,
            "--passes": passes,
            "--unweighted": False if unweighted else None,
            "--iterations": iterations,
            "--delta": delta,
            "--rotation-rank": rotation_rank,
            "--starts": starts,
            "--refills": refills,
            "--held-out": held_out,
            "--trace-norm-weight": trace_norm_weight,
            "--camera": camera,
            "--shape-steps": shape_steps,
            "--shape-rho": shape_rho,
            "--raw-tracks": False if raw_tracks else None,
            "--max-steps": max_steps,
            "--rtol": rtol,
            "--varpro": varpro,
        }
        stages = _stages(method, rotations, shapes, given)
        tracks = _read_tracks(tracks_file, var)
        W, visible, true_shapes = _select_frames(tracks, frames)
        frame = tracks.frame
        W = W.astype(np.float32 if float32 else np.float64)  # an explicit float64 under float32 would warn
        t0, before = time.perf_counter(), dict(_compiled)
        rec = jax.block_until_ready(nr.reconstruct(W, visible, k=k, form=form, **stages))
        elapsed = time.perf_counter() - t0
        compile_s, cache_hits, compiled = (
            _compiled[key] - before[key] for key in ("seconds", "cache_hits", "cache_writes")
        )
        arrays = {name: np.asarray(getattr(rec, name)) for name in names}
        if out is not None:
            with open(out, "wb") as f:  # a file object: np.savez would append .npz to any other name
                np.savez(f, **arrays)
        faces = triangulate(arrays["shapes"]) if surface else None
        exported = (
            [] if export is None else export_shapes(export, arrays["shapes"], faces=faces, fps=fps, name=tracks.name)
        )
    except (ValueError, OSError, KeyError) as err:
        _fail(err)

    Wj = jnp.asarray(W)
    summary = {
        "input": str(tracks_file),
        "frames": int(visible.shape[0]),
        "points": int(visible.shape[1]),
        "observed": int(visible.sum()),
        "k": int(rec.weights.shape[1]),
        "method": method,
        "form": form,
        "stages": {name: eqx.tree_pformat(stage, width=10_000) for name, stage in stages.items()},
        "dtype": str(W.dtype),
        "mean_reprojection_error": _number(nr.mean_reprojection_error(Wj, rec.W_hat, rec.inliers)),
        "rms_reprojection_error": _number(nr.rms_error(Wj, rec.W_hat, rec.inliers)),
        "outliers": int(np.sum(visible & ~arrays["inliers"])),
        "status": _status_name(rec.status),
        "status_message": nr.Status[rec.status],
        "time_s": round(elapsed, 3),
        "compile_s": round(compile_s, 3),
        "compile_cache_hits": cache_hits,
        "compiled_programs": compiled,
        "e3d": None
        if true_shapes is None
        else _number(nr.e3d(rec.shapes_in(frame), jnp.asarray(true_shapes, W.dtype))),
        "e3d_frame": None if true_shapes is None else frame,
        "out": None if out is None else str(out),
        "export": None if not exported else str(exported[0]),
        "export_files": len(exported),
        "export_faces": None if faces is None else len(faces),
    }
    typer.echo(json.dumps(summary, indent=2))


STAGE_FLAGS = {
    "method": {
        "threshold": "--threshold",
        "passes": "--passes",
        "weighted": "--unweighted",
        "iterations": "--iterations",
        "delta": "--delta",
    },
    "rotations": {
        "rank": "--rotation-rank",
        "starts": "--starts",
        "refills": "--refills",
        "held_out": "--held-out",
        "weight": "--trace-norm-weight",
        "camera": "--camera",
        # The high-rank rotations' refills solve the shape step's ADMM: --shape-steps sets both.
        "steps": "--shape-steps",
    },
    "shapes": {"steps": "--shape-steps", "rho": "--shape-rho", "denoise": "--raw-tracks"},
    "solver": {"max_steps": "--max-steps", "rtol": "--rtol", "varpro": "--varpro"},
}
"""The command-line flag of every option (field) of every built-in stage, by stage."""


def _build(cls: type, stage: str, given: dict, named: str, shared: frozenset = frozenset()):
    """``cls`` with the fields whose flags (``STAGE_FLAGS[stage]``) were given (``given``: flag
    -> value, ``None`` = not given). A flag given for a field ``cls`` lacks is an error
    (``named`` says which stage the user chose), except a ``shared`` one, which serves another
    stage too."""
    import dataclasses

    fields = {f.name for f in dataclasses.fields(cls)}
    chosen = {field: flag for field, flag in STAGE_FLAGS[stage].items() if given[flag] is not None}
    if wrong := [flag for field, flag in chosen.items() if field not in fields and flag not in shared]:
        raise _InputError(f"{wrong[0]} does not apply to {named}")
    return cls(**{field: given[flag] for field, flag in chosen.items() if field in fields})


def _stages(method: str, rotations: str | None, shapes: str, given: dict) -> dict:
    """The stage instances that the command-line options name, before anything is compiled."""
    from .stages import ROTATIONS, SHAPES, STRATEGIES, MaskedALS

    if method == "oracle":
        raise _InputError("--method oracle needs the true outliers, which a tracks file does not have")
    for option, name, table in (
        ("method", method, STRATEGIES),
        ("shapes", shapes, SHAPES),
        ("rotations", rotations, ROTATIONS),
    ):
        if name is not None and name not in table:
            raise _InputError(f"unknown {option} {name!r}; choose one of {', '.join(table)}")
    shape_step = _build(SHAPES[shapes], "shapes", given, f"--shapes {shapes}")
    if rotations is None:
        default = type(shape_step.default_rotations())
        rotations = next(name for name, cls in ROTATIONS.items() if cls is default)
    shared = frozenset(STAGE_FLAGS["rotations"].values()) & frozenset(STAGE_FLAGS["shapes"].values())
    return dict(
        method=_build(STRATEGIES[method], "method", given, f"--method {method}"),
        rotations=_build(ROTATIONS[rotations], "rotations", given, f"--rotations {rotations}", shared),
        shapes=shape_step,
        solver=_build(MaskedALS, "solver", given, "the solver"),
    )


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


@app.command(epilog="Example: jaxnrsfm sweep --noise 0 --noise 2 --outliers 0.1 --trials 20 --out results/sweep")
def sweep(
    noise: Annotated[list[float] | None, typer.Option(help="Noise level sigma; repeat for several [1..5].")] = None,
    outliers: Annotated[list[float] | None, typer.Option(help="Outlier ratio; repeat for several [0.05, 0.2].")] = None,
    missing: Annotated[float, typer.Option(help="Fraction of entries hidden in every trial.")] = 0.0,
    trials: Annotated[int, typer.Option(help="Independent trials per setting.")] = 100,
    methods: Annotated[
        list[str] | None, typer.Option("--method", help="Method; repeat for several [the paper's five].")
    ] = None,
    k: Annotated[int, typer.Option(help="Shape bases of the model.")] = 4,
    frames: Annotated[int, typer.Option(help="Frames per sequence.")] = 100,
    seed: Annotated[int, typer.Option(help="PRNG seed; trial t uses fold_in(key(seed), t).")] = 0,
    out: Annotated[Path, typer.Option(help="Folder for sweep.json and the figures (created if absent).")] = Path("."),
    float32: Annotated[bool, typer.Option("--float32", help="Compute in float32 instead of float64.")] = False,
    processes: Annotated[
        int, typer.Option(help="Processes on this machine sharing the trials, each on its own cores (a CPU).")
    ] = 1,
) -> None:
    """The paper's Fig. 5 protocol on the deformable cube (by default: sigma 1..5, 5% and
    20% outliers, 100 trials, five methods). Writes sweep.json (every trial's error,
    detection and status, the settings and timings), fig5.png and fig1.png. Trials are
    split across all JAX devices, or with --processes N across N processes, each on its
    share of the cores (faster on a CPU where running the trials takes longer than
    compiling them)."""
    from .sweep import PAPER_METHODS, SweepSettings

    defaults = SweepSettings()
    noise = list(noise or defaults.noise)
    outliers = list(outliers or defaults.outliers)
    methods = list(methods or PAPER_METHODS)
    _setup(float32)
    try:
        _check_sweep(noise, outliers, missing, trials, methods, k, frames, out, processes)
    except ValueError as err:
        _fail(err)
    import jax
    from rich.progress import Progress

    from . import robust
    from .metrics import entry_errors
    from .pipeline import reconstruct as reconstruct_tracks
    from .plot import plot_residuals, plot_sweep
    from .processes import run_sweep_in_processes
    from .sweep import run_sweep
    from .synthetic import deformable_cube

    settings = SweepSettings(tuple(noise), tuple(outliers), missing, trials, frames, tuple(methods), k, seed)
    cells = len(noise) * len(outliers) * len(methods)
    if processes > 1:
        with Console(stderr=True).status(f"sweep in {processes} processes ({cells} cells)"):
            try:
                result = run_sweep_in_processes(settings, processes)
            except RuntimeError as err:
                typer.echo(f"error: {err}", err=True)
                raise typer.Exit(1) from err
    else:
        with Progress(console=Console(stderr=True)) as bar:
            task = bar.add_task(f"sweep on {len(jax.devices())} device(s)", total=cells)
            result = run_sweep(settings, progress=lambda line: bar.update(task, advance=1, description=line))
    (out / "sweep.json").write_text(json.dumps(result, indent=1))
    plot_sweep(result, out / "fig5.png")
    # Fig. 1: one trial at the middle noise level and the largest outlier ratio.
    sigma, ratio = sorted(noise)[len(noise) // 2], max(outliers)
    seq = deformable_cube(jax.random.key(seed), n_frames=frames, noise=sigma, outlier_ratio=ratio)
    W0 = jax.numpy.where(jax.numpy.isnan(seq.W), 0.0, seq.W)
    rec = reconstruct_tracks(W0, seq.visible, k=k, method="wang", shapes="upgrade")
    _, model = robust.classify(W0, rec.W_hat, seq.visible)
    lengths = entry_errors(W0, seq.W_clean)
    plot_residuals(
        lengths[seq.visible & ~seq.outliers],
        lengths[seq.outliers],
        entry_errors(W0, rec.W_hat)[seq.visible],
        float(model.threshold),
        out / "fig1.png",
        title=f"one trial, sigma={sigma:g}, {ratio:.0%} outliers, method wang",
    )
    table = Table(title=f"mean inlier error vs truth, {trials} trials per cell")
    table.add_column("outliers")
    table.add_column("sigma")
    table.add_column("floor")
    for method in methods:
        table.add_column(method, justify="right")
    for r in outliers:
        for s in noise:
            row = [c for c in result["cells"] if c["outliers"] == r and c["noise"] == s]
            errors = {c["method"]: sum(c["error"]) / len(c["error"]) for c in row}
            table.add_row(
                f"{r:.0%}", f"{s:g}", f"{result['floor'][str(s)]:.3f}", *(f"{errors[m]:.3f}" for m in methods)
            )
    console.print(table)
    console.print(f"wrote {out / 'sweep.json'}, {out / 'fig5.png'}, {out / 'fig1.png'}")


def _check_sweep(noise, outliers, missing, trials, methods, k, frames, out, processes) -> None:
    from .sweep import check_methods

    if processes < 1:
        raise ValueError(f"--processes must be >= 1; got {processes}")
    check_methods(methods)
    if trials < 1 or k < 1 or frames < 2 or not noise or not outliers:
        raise ValueError("trials, k must be >= 1, frames >= 2, and at least one noise level and outlier ratio given")
    if any(s < 0 for s in noise) or any(not 0 <= r < 1 for r in outliers) or not 0 <= missing < 1:
        raise ValueError("noise levels must be >= 0, outlier and missing ratios in [0, 1)")
    if 3 * k + 1 > min(2 * frames, 252):
        raise ValueError(f"k={k} needs rank {3 * k + 1}, more than the {frames}-frame cube allows")
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder")
    out.mkdir(parents=True, exist_ok=True)  # after every other check: a bad call leaves nothing
