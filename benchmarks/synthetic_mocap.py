"""The default call on synthetic motion-capture-like sequences: data its rules were not
chosen on.

`jaxnrsfm.articulated_sequence`: a 17-joint figure with 41 markers whose spectra resemble
Akhter's sequences, under an orbiting camera (its tilt wobbling by 5 degrees, so not quite
the constant-velocity camera of `jaxnrsfm.camera`) or a panning one (which that prior must
not take). For each key and camera, printed: e3D of the nuclear-norm shapes given the TRUE
rotations (what the rotations could reach), of the default call, of ``camera="free"``
(no camera prior), of ``HighRankRotations(held_out=0.1)`` (a tenth of the entries seen by
the rotation solve only through its refills from the shapes), the median angle between the
free rotations and their fitted constant-velocity camera (the prior is taken at most
`jaxnrsfm.camera.MAX_TURN`), and the
default's e3D change with 10% outliers (recall beside it) and with 30% missing entries, as
in ``benchmarks/real_sequences.py``.

Run: ``python benchmarks/synthetic_mocap.py [--keys 6]``.
"""

import argparse

import jax
import jax.numpy as jnp

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import jaxnrsfm as nr  # noqa: E402
from jaxnrsfm import camera, refine  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keys", type=int, default=6, help="sequences per camera")
    args = parser.parse_args()
    free = nr.HighRankRotations(camera="free")
    held_out = nr.HighRankRotations(held_out=0.1)
    print(
        f"{'camera':6} {'key':>3} {'k':>2} {'true R':>7} {'default':>7} {'free':>7} {'held':>7} {'turn':>5}"
        "  outliers (recall)  missing"
    )
    for kind in ("orbit", "pan"):
        gains = []
        for key in range(args.keys):
            seq = nr.articulated_sequence(jax.random.key(key), camera=kind)
            W, truth = seq.W, seq.shapes
            frames = nr.to_frames(W)
            frames = frames - frames.mean(axis=2, keepdims=True)
            oracle = float(nr.e3d(refine.nuclear_shapes(frames, seq.rotations), truth))
            rec = nr.reconstruct(W)
            e_default = float(nr.e3d(rec.shapes, truth))
            rec_free = nr.reconstruct(W, rotations=free)
            e_free = float(nr.e3d(rec_free.shapes, truth))
            e_held = float(nr.e3d(nr.reconstruct(W, rotations=held_out).shapes, truth))
            turn = float(jnp.median(camera.turning(rec_free.rotations, camera.constant_velocity(rec_free.rotations))))
            extent = float(W.max() - W.min())
            W_out, outliers = nr.inject_outliers(
                jax.random.key(100 + key), W, ratio=0.1, magnitude=(0.025 * extent, 0.125 * extent)
            )
            dirty = nr.reconstruct(W_out)
            recall = float(np.mean(~np.asarray(dirty.inliers)[np.asarray(outliers)]))
            visible = nr.drop_entries(jax.random.key(200 + key), jnp.ones(rec.inliers.shape, bool), 0.3)
            missing = nr.reconstruct(W, visible)
            change_out = float(nr.e3d(dirty.shapes, truth)) / e_default - 1
            change_missing = float(nr.e3d(missing.shapes, truth)) / e_default - 1
            gains.append(e_default / e_free)
            print(
                f"{kind:6} {key:3d} {rec.weights.shape[1]:2d} {oracle:7.4f} {e_default:7.4f} {e_free:7.4f}"
                f" {e_held:7.4f} {turn:5.1f}  {change_out:+8.1%} ({recall:.3f})  {change_missing:+7.1%}",
                flush=True,
            )
        print(f"{kind}: default / free e3D, geometric mean {np.exp(np.mean(np.log(gains))):.3f}\n", flush=True)


if __name__ == "__main__":
    main()
