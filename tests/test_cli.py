import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
import scipy.io
import trimesh
from typer.testing import CliRunner

import jaxnrsfm as nr
from jaxnrsfm import cli, datasets
from jaxnrsfm.cli import CACHE_ENV, app


def test_demo_prints_table_and_writes_figure(tmp_path):
    # The paper's result on a 30-frame cube (the programs are compiled for that size).
    out = tmp_path / "frames.png"
    result = CliRunner().invoke(app, ["demo", "--out", str(out), "--frames", "30"])
    assert result.exit_code == 0, result.output
    for text in ("registered rank 12", "augmented rank 13", "10% outliers", "20% missing", "e3D", "ok", "floor"):
        assert text in result.output
    rows = {line.split("│")[1].strip(): line.split("│")[2:] for line in result.output.splitlines() if "│" in line}
    for label in cli.METHOD_LABELS.values():
        assert label in rows
    # The robust method within 10% of the oracle on the tracks, the direct fit far off.
    rms = {label: float(rows[label][0]) for label in ("direct", "wang (robust)", "oracle")}
    assert rms["wang (robust)"] < 1.1 * rms["oracle"] and rms["direct"] > 3 * rms["oracle"]
    assert out.stat().st_size > 10_000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# --- jaxnrsfm reconstruct -------------------------------------------------------------

OUTPUTS = ("W_hat", "inliers", "shapes", "rotations", "weights", "bases", "translations")


def _data_dir():
    try:
        return datasets.data_dir()
    except FileNotFoundError:
        return None


DATA = _data_dir()


def _run(*args):
    return CliRunner().invoke(app, ["reconstruct", *map(str, args)])


def test_second_call_loads_compiled_programs_from_the_cache(tmp_path):
    # Two separate processes, as two shell commands: the second finds the first one's
    # compiled pipeline in the persistent cache instead of compiling it.
    seq = nr.bregler_sequence(jax.random.key(0), k=2, n_frames=30, n_points=40, noise=0.5)
    np.savez(tmp_path / "tracks.npz", W=np.asarray(seq.W))
    command = [sys.executable, "-c", "from jaxnrsfm.cli import app; app()", "reconstruct", str(tmp_path / "tracks.npz")]
    command += ["--k", "2", "--method", "direct", "--shapes", "upgrade"]
    # Its own, empty cache: not the test session's shared one (conftest), which the command
    # would otherwise take as a cache its caller configured.
    env = {**os.environ, CACHE_ENV: str(tmp_path / "cache")}
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    first, second = (json.loads(subprocess.run(command, env=env, capture_output=True, check=True).stdout) for _ in "12")
    # (The first call can hit too: a small program it compiles twice under different jit wrappers.)
    assert second["compile_cache_hits"] > first["compile_cache_hits"]
    # Counted, not timed: the first call compiled the pipeline, the second compiled nothing.
    # (Its compile_s, 0.14-0.27 s against 0.65-1.05 s under the tests' XLA flags, is printed.)
    assert first["compiled_programs"] > 0
    assert second["compiled_programs"] == 0, (first, second)
    assert second["rms_reprojection_error"] == first["rms_reprojection_error"]


def _summary(result):
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout)


def _low_rank_tracks(m=12, n=20, noise=0.01, seed=0):
    # A rigid object (k=1) under random orthographic cameras, rank 4 with translations, plus noise.
    rng = np.random.default_rng(seed)
    S = rng.normal(size=(3, n))
    R = np.linalg.qr(rng.normal(size=(m, 3, 3)))[0][:, :2]
    W = np.einsum("iab,bn->ian", R, S) + rng.normal(size=(m, 2, 1))
    return W.reshape(2 * m, n) + noise * rng.normal(size=(2 * m, n))


@pytest.mark.skipif(
    DATA is None, reason="real data absent: set $JAXNRSFM_DATA or provide ../shared/data next to the repository"
)
def test_reconstruct_mat_csv_npz_agree(tmp_path):
    """The same Akhter tracks given as .mat, .csv and .npz give the same reconstruction,
    without --k: the library's default call, ``jaxnrsfm.reconstruct(W)``."""
    mat = DATA / "akhter" / "yoga.mat"
    W = scipy.io.loadmat(mat)["W"]
    csv = tmp_path / "yoga.csv"
    np.savetxt(csv, W, fmt="%.17g", delimiter=",")  # the layout load_csv reads: W itself, exact
    npz = tmp_path / "yoga.npz"
    np.savez(npz, W=W)
    common = ["--frames", "0:40"]
    runs = {}
    for path in (mat, csv, npz):
        out = tmp_path / f"{path.suffix[1:]}.npz"
        summary = _summary(_run(path, *common, "--out", out))
        with np.load(out) as f:
            assert sorted(f.files) == sorted(OUTPUTS)
            runs[path.suffix] = summary, {name: f[name] for name in OUTPUTS}
    (s_mat, r_mat), (s_csv, r_csv), (s_npz, r_npz) = runs[".mat"], runs[".csv"], runs[".npz"]
    assert s_npz["e3d"] is None
    assert r_mat["W_hat"].shape == (80, 41) and r_mat["shapes"].shape == (40, 3, 41)
    for other in (r_csv, r_npz):
        np.testing.assert_allclose(other["W_hat"], r_mat["W_hat"], rtol=0, atol=1e-12)
    assert s_mat["status"] == "success" and s_mat["status_message"] == "the reconstruction succeeded"
    assert s_mat["frames"] == 40 and s_mat["points"] == 41 and s_mat["outliers"] <= 0.02 * 40 * 41
    assert s_mat["mean_reprojection_error"] == pytest.approx(s_csv["mean_reprojection_error"], rel=1e-9)
    assert s_mat["mean_reprojection_error"] < 0.01 and s_mat["time_s"] > 0
    # The library's default call gives the same result, with the k it chooses.
    rec = nr.reconstruct(W[:80])
    assert s_mat["k"] == rec.weights.shape[1] == nr.choose_k(W[:80], robust=True)
    np.testing.assert_allclose(r_mat["shapes"], rec.shapes, rtol=1e-9, atol=1e-9)
    # Only the .mat file carries ground truth (S), scored in its frame (world, for yoga).
    assert 0 < s_mat["e3d"] < 0.2 and s_mat["e3d_frame"] == "world" and s_csv["e3d"] is None


def test_reconstruct_exports_and_counts_outliers(tmp_path):
    W = _low_rank_tracks()
    W[3, 5] += 5.0  # one gross outlier (500 noise sigmas): v of frame 1, point 5
    np.savez(tmp_path / "t.npz", W=W)
    args = ["--k", 1, "--method", "wang", "--export", tmp_path / "s.ply", "--out", tmp_path / "o"]
    summary = _summary(_run(tmp_path / "t.npz", *args))
    assert summary["outliers"] == 1 and summary["status"] == "success"
    assert summary["mean_reprojection_error"] < 0.05  # over the inliers: the noise level
    assert summary["export_files"] == 12 and summary["export"] == str(tmp_path / "s_0000.ply")
    assert sorted(p.name for p in tmp_path.glob("s_*.ply")) == [f"s_{i:04d}.ply" for i in range(12)]
    with np.load(tmp_path / "o") as f:  # written under the name given, no .npz appended
        assert np.argwhere(~f["inliers"]).tolist() == [[1, 5]]
    # --surface: the same shapes as triangle meshes, every frame with the same triangles
    summary = _summary(_run(tmp_path / "t.npz", *args[:4], "--export", tmp_path / "m.obj", "--surface"))
    meshes = [trimesh.load(tmp_path / f"m_{i:04d}.obj", process=False) for i in range(12)]
    assert summary["export_faces"] == len(meshes[0].faces) > 0
    assert all((mesh.faces == meshes[0].faces).all() and len(mesh.vertices) == W.shape[1] for mesh in meshes)


def test_reconstruct_float32(tmp_path, restore_x64):
    np.savez(tmp_path / "t.npz", W=_low_rank_tracks())
    summary = _summary(_run(tmp_path / "t.npz", "--k", 1, "--float32", "--out", tmp_path / "o.npz"))
    assert summary["dtype"] == "float32" and summary["status"] == "success"
    assert summary["mean_reprojection_error"] < 0.02  # the noise level, 0.01 per coordinate
    with np.load(tmp_path / "o.npz") as f:
        assert f["W_hat"].dtype == np.float32 and f["shapes"].dtype == np.float32


def _bad_inputs(tmp: Path) -> dict:
    W = _low_rank_tracks(m=4, n=5)
    np.savez(tmp / "good.npz", W=W)
    np.savez(tmp / "odd.npz", W=W[:-1])
    np.savez(tmp / "vis.npz", W=W, visible=np.ones((3, 5), bool))
    np.savez(tmp / "noW.npz", tracks=W)
    (tmp / "garbage.npz").write_bytes(b"not a zip file")
    (tmp / "garbage.mat").write_bytes(b"not a MATLAB file")
    (tmp / "text.csv").write_text("1,2,3\n4,x,6\n")
    (tmp / "ragged.csv").write_text("1,2,3\n4,5\n")
    scipy.io.savemat(tmp / "noW.mat", {"X": W})
    scipy.io.savemat(tmp / "chars.mat", {"W": np.array(["ab", "cd"])})
    (tmp / "t.txt").write_text("1,2\n")
    good = tmp / "good.npz"
    return {
        "missing file": ([tmp / "nowhere.npz", "--k", 1], "no such file"),
        "unreadable npz": ([tmp / "garbage.npz", "--k", 1], "not a .npz file"),
        "unreadable mat": ([tmp / "garbage.mat", "--k", 1], "not a readable MATLAB"),
        "non-numeric csv": ([tmp / "text.csv", "--k", 1], "not a number"),
        "ragged csv": ([tmp / "ragged.csv", "--k", 1], "different numbers of columns"),
        "odd rows": ([tmp / "odd.npz", "--k", 1], "even number of rows"),
        "visible shape": ([tmp / "vis.npz", "--k", 1], "visible has shape"),
        "npz without W": ([tmp / "noW.npz", "--k", 1], "lacks the array 'W'"),
        "mat without W": ([tmp / "noW.mat", "--k", 1], "lacks the variable 'W'"),
        "missing --var": ([tmp / "noW.mat", "--k", 1, "--var", "Q"], "lacks the variable 'Q'"),
        "non-numeric mat": ([tmp / "chars.mat", "--k", 1], "not a real numeric matrix"),
        "unknown type": ([tmp / "t.txt", "--k", 1], "unknown track file type"),
        "k too large": ([good, "--k", 2], "larger than the data allows"),
        "k zero": ([good, "--k", 0], "positive integer"),
        "unknown method": ([good, "--k", 1, "--method", "magic"], "unknown method"),
        "unknown shapes": ([good, "--k", 1, "--shapes", "bmm"], "unknown shapes 'bmm'"),
        "option of another method": ([good, "--k", 1, "--delta", 2], "--delta does not apply to --method wang"),
        "option of another rotation": (
            [good, "--k", 1, "--shapes", "upgrade", "--rotation-rank", 3],
            "--rotation-rank does not apply to --rotations upgrade",
        ),
        "bad stage option": ([good, "--k", 1, "--passes", 0], "passes must be a positive integer"),
        "rotation rank too large": ([good, "--k", 1, "--rotation-rank", 9], "exceeds the centred tracks' rank"),
        "shapes without their rotations": (
            [good, "--k", 1, "--shapes", "upgrade", "--rotations", "high_rank"],
            "need its rotations",
        ),
        "oracle": ([good, "--k", 1, "--method", "oracle"], "needs the true outliers"),
        "bad frames": ([good, "--k", 1, "--frames", "a:b"], "--frames"),
        "no frames": ([good, "--k", 1, "--frames", "10:20"], "selects no frame"),
        "export format": ([good, "--k", 1, "--export", tmp / "s.stl"], "unknown export format"),
        "out directory": ([good, "--k", 1, "--out", tmp / "no" / "o.npz"], "does not exist"),
        "surface without export": ([good, "--k", 1, "--surface"], "give --export FILE"),
    }


@pytest.mark.parametrize(
    "case",
    [
        "missing file",
        "unreadable npz",
        "unreadable mat",
        "non-numeric csv",
        "ragged csv",
        "odd rows",
        "visible shape",
        "npz without W",
        "mat without W",
        "missing --var",
        "non-numeric mat",
        "unknown type",
        "k too large",
        "k zero",
        "unknown method",
        "unknown shapes",
        "option of another method",
        "option of another rotation",
        "bad stage option",
        "rotation rank too large",
        "shapes without their rotations",
        "oracle",
        "bad frames",
        "no frames",
        "export format",
        "out directory",
        "surface without export",
    ],
)
def test_reconstruct_bad_input_is_one_line(tmp_path, case):
    """Bad input: one line on stderr, exit status 1, no traceback, nothing on stdout."""
    args, fragment = _bad_inputs(tmp_path)[case]
    result = _run(*args)
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output and result.stdout == ""
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and fragment in lines[0], result.output


def test_sweep_writes_json_and_figures(tmp_path):
    # One sweep for every check (each method compiles once): from sigma = 0, as many papers'
    # sweeps start, into a folder it creates. 40 frames: at 20 the cube's passes settle on a
    # wrong consensus at sigma = 0 (README, "Known limitations").
    out = tmp_path / "new" / "dir"
    args = ["sweep", "--trials", "2", "--frames", "40", "--outliers", "0.1", "--out", str(out)]
    for sigma in ("0", "1", "3"):
        args += ["--noise", sigma]
    for method in ("direct", "wang", "oracle"):
        args += ["--method", method]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    sweep = json.loads((out / "sweep.json").read_text())
    assert len(sweep["cells"]) == 9 and all(len(c["error"]) == 2 for c in sweep["cells"])
    cells = {(c["method"], c["noise"]): c for c in sweep["cells"]}
    errors = {key: np.mean(c["error"]) for key, c in cells.items()}
    # The oracle sits near the statistical floor; ignoring the outliers costs far more.
    for sigma in (1, 3):
        assert errors["oracle", sigma] < 1.5 * sweep["floor"][str(float(sigma))] < errors["direct", sigma]
    # Noise-free, the robust method finds every outlier and is exact (to the sqrt(eps)
    # weight its fit keeps on the rejected entries), as the oracle is.
    assert max(cells["oracle", 0.0]["error"]) < 1e-9
    assert max(cells["wang", 0.0]["error"]) < 1e-6
    assert min(cells["wang", 0.0]["precision"]) == min(cells["wang", 0.0]["recall"]) == 1.0
    assert errors["wang", 1.0] < 1.05 * errors["oracle", 1.0]
    assert (out / "fig5.png").stat().st_size > 0 and (out / "fig1.png").stat().st_size > 0


def test_sweep_rejects_bad_options(tmp_path):
    result = CliRunner().invoke(app, ["sweep", "--method", "magic", "--out", str(tmp_path)])
    assert result.exit_code == 1 and "unknown method 'magic'" in result.output and "Traceback" not in result.output
    result = CliRunner().invoke(app, ["sweep", "--processes", "0", "--out", str(tmp_path)])
    assert result.exit_code == 1 and "--processes must be >= 1" in result.output and "Traceback" not in result.output


@pytest.mark.parametrize("command", ["demo", "reconstruct", "sweep"])
def test_help_shows_an_example(command):
    result = CliRunner().invoke(app, [command, "--help"], terminal_width=200)
    assert result.exit_code == 0 and f"jaxnrsfm {command}" in result.output and "Example" in result.output


def test_every_stage_option_has_a_flag():
    """CLI parity: every field of every built-in stage has a flag of `jaxnrsfm reconstruct`
    (but the oracle's outliers, which a tracks file does not have), and --help shows it."""
    import dataclasses

    from jaxnrsfm.stages import ROTATIONS, SHAPES, STRATEGIES, MaskedALS

    tables = {"method": STRATEGIES, "rotations": ROTATIONS, "shapes": SHAPES, "solver": {"masked_als": MaskedALS}}
    help_text = CliRunner().invoke(app, ["reconstruct", "--help"], terminal_width=200).output
    for stage, table in tables.items():
        for name, cls in table.items():
            fields = {f.name for f in dataclasses.fields(cls)} - ({"outliers"} if name == "oracle" else set())
            assert fields <= set(cli.STAGE_FLAGS[stage]), (name, fields - set(cli.STAGE_FLAGS[stage]))
            if stage != "solver" and name != "oracle":
                assert name in help_text, name
    for flags in cli.STAGE_FLAGS.values():
        for flag in flags.values():
            assert flag in help_text, flag
