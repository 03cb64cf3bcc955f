"""Every Python example in the README runs as written: the blocks are executed in order in
one namespace, as a reader pastes them. The several-hosts launcher is skipped (it needs a
coordinator and other processes; tests/test_multiprocess.py runs the same sweep as two
processes)."""

import re
from pathlib import Path

import pytest

from jaxnrsfm import datasets

README = Path(__file__).resolve().parents[1] / "README.md"
LAUNCHER = "jax.distributed.initialize("


def _python_blocks() -> list[str]:
    return re.findall(r"^```python\n(.*?)^```", README.read_text(), flags=re.S | re.M)


def _has_data() -> bool:
    try:
        datasets.data_dir()
    except FileNotFoundError:
        return False
    return True


def test_readme_has_the_examples():
    blocks = _python_blocks()
    assert len(blocks) >= 4 and sum(LAUNCHER in block for block in blocks) == 1


@pytest.mark.skipif(
    not _has_data(), reason="real data absent: set $JAXNRSFM_DATA or provide ../shared/data next to the repository"
)
def test_readme_examples_run(capsys):
    namespace: dict = {}
    for block in _python_blocks():
        if LAUNCHER in block:
            continue
        exec(compile(block, str(README), "exec"), namespace)
    printed = capsys.readouterr().out
    # What the examples print: the figures they promise, finite.
    for label in ("yoga, 150 frames: e3D", "cube: RMS", "trials succeeded:", "a rigid object with a rigid prior"):
        assert label in printed, printed
    assert "nan" not in printed.lower(), printed
    grads = namespace["grads"]
    assert grads.shape == (2,) and bool((abs(grads) > 0).all())
    nr = namespace["nr"]
    # the last reconstruction: the rigid prior on a rigid object (noise 0.5 in ~10-unit tracks)
    assert float(nr.e3d(namespace["rec"].shapes, namespace["rigid"].shapes)) < 0.05
