"""A sweep split across devices or processes gives the numbers of one process on one device:
over four CPU devices of one process; as two ``jax.distributed`` processes; and as
`jaxnrsfm.processes`' independent ones.

The second is the README's several-hosts recipe with both "hosts" on 127.0.0.1: each process
owns one CPU device, runs the trials of its device, and gathers the other's. Every case runs
the same small sweep (the cheapest method to compile: every process compiles the pipeline),
and is compared with one run of it in this process.
"""

import json
import os
import socket
import subprocess
import sys

import jax
import numpy as np
import pytest

from jaxnrsfm.processes import run_sweep_in_processes
from jaxnrsfm.sweep import SweepSettings, run_sweep

SETTINGS = dict(noise=(1.0,), outliers=(0.1, 0.2), trials=5, frames=12, methods=("direct",))
"""Five trials: over four devices, the trial axis is padded; over two processes, split 2 + 3."""

SCRIPT = f"""
import json, sys

import jax

jax.config.update("jax_enable_x64", True)
port, process, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
if process >= 0:
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{{port}}", num_processes=2, process_id=process)
from jaxnrsfm.sweep import SweepSettings, run_sweep

result = run_sweep(SweepSettings(**{SETTINGS!r}))
with open(out, "w") as f:
    json.dump(dict(devices=result["devices"], cells=result["cells"]), f)
"""
"""A sweep run in a new process (``process`` -1: no distributed runtime), written to ``out``."""


@pytest.fixture(scope="module")
def one():
    """The sweep in this process, on one device."""
    result = run_sweep(SweepSettings(**SETTINGS), devices=jax.devices()[:1])
    assert len(result["devices"]) == 1
    return result


def _assert_same_cells(cells, one, rtol=1e-9) -> None:
    assert len(cells) == len(one["cells"])
    for a, b in zip(one["cells"], cells, strict=True):
        assert (b["outliers"], b["method"], b["success"]) == (a["outliers"], a["method"], a["success"])
        assert len(b["error"]) == SETTINGS["trials"]
        np.testing.assert_allclose(b["error"], a["error"], rtol=rtol)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(port: int, process: int, out, env=None) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(port), str(process), str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env=env,
    )


def _finish(proc: subprocess.Popen) -> None:
    try:
        output, _ = proc.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        proc.kill()
        output, _ = proc.communicate()
    assert proc.returncode == 0, output[-3000:]


def test_four_cpu_devices_match_one(one, tmp_path):
    # The session's XLA flags (conftest: cheaper compilation) as well, as for the one device.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4".strip()
    out = tmp_path / "four.json"
    _finish(_start(0, -1, out, env=dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")))
    four = json.loads(out.read_text())
    assert len(four["devices"]) == 4
    _assert_same_cells(four["cells"], one, rtol=1e-12)


def test_two_processes_match_one(one, tmp_path):
    port = _free_port()
    outs = [tmp_path / f"process{i}.json" for i in range(2)]
    procs = [_start(port, i, out) for i, out in enumerate(outs)]
    for proc in procs:
        _finish(proc)
    for out in outs:
        two = json.loads(out.read_text())
        assert len(two["devices"]) == 2  # one device per process, both in the mesh
        _assert_same_cells(two["cells"], one)


def test_processes_on_this_machine_match_one(one):
    # jaxnrsfm.processes: independent processes, each on a share of the trials (5 -> 2 + 3),
    # joined in trial order: one process's numbers, every cell in the same order.
    settings = SweepSettings(**SETTINGS)
    split = run_sweep_in_processes(settings, 2)
    assert split["devices"] == ["process 0: cpu:0", "process 1: cpu:0"]
    assert split["settings"] == one["settings"] and split["floor"] == one["floor"]
    _assert_same_cells(split["cells"], one)
    with pytest.raises(ValueError, match="unknown method 'magic'"):  # before any process starts
        run_sweep_in_processes(SweepSettings(methods=("magic",)), 2)
    with pytest.raises(ValueError, match="processes must be >= 1"):
        run_sweep_in_processes(settings, 0)
