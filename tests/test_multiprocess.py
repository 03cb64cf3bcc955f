"""A sweep run as two processes on one machine gives one process's numbers: as two
``jax.distributed`` processes, and as `jaxnrsfm.processes`' independent ones.

The first is the README's several-hosts recipe with both "hosts" on 127.0.0.1: each process
owns one CPU device, runs the trials of its device, and gathers the other's.
"""

import json
import socket
import subprocess
import sys

import numpy as np
import pytest

from jaxnrsfm.processes import run_sweep_in_processes
from jaxnrsfm.sweep import SweepSettings, run_sweep

SCRIPT = """
import json, sys

import jax

jax.config.update("jax_enable_x64", True)
port, process, out = sys.argv[1], int(sys.argv[2]), sys.argv[3]
if process >= 0:
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=2, process_id=process)
from jaxnrsfm.sweep import SweepSettings, run_sweep

settings = SweepSettings(noise=(1.0,), outliers=(0.1,), trials=5, frames=12, methods=("direct",))
result = run_sweep(settings)
with open(out, "w") as f:
    json.dump(dict(devices=result["devices"], cells=result["cells"]), f)
"""


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _start(port: int, process: int, out) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", SCRIPT, str(port), str(process), str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def _finish(proc: subprocess.Popen) -> None:
    try:
        output, _ = proc.communicate(timeout=240)
    except subprocess.TimeoutExpired:
        proc.kill()
        output, _ = proc.communicate()
    assert proc.returncode == 0, output[-3000:]


def test_two_processes_match_one(tmp_path):
    port = _free_port()
    outs = [tmp_path / f"process{i}.json" for i in range(2)]
    single = tmp_path / "single.json"  # process -1: no distributed runtime, one device
    procs = [_start(port, i, out) for i, out in enumerate(outs)] + [_start(port, -1, single)]
    for proc in procs:
        _finish(proc)

    one = json.loads(single.read_text())
    assert len(one["devices"]) == 1
    for out in outs:
        two = json.loads(out.read_text())
        assert len(two["devices"]) == 2  # one device per process, both in the mesh
        for a, b in zip(one["cells"], two["cells"], strict=True):
            assert a["method"] == b["method"] and len(b["error"]) == 5
            np.testing.assert_allclose(b["error"], a["error"], rtol=1e-9)
            assert b["success"] == a["success"]


def test_processes_on_this_machine_match_one():
    # jaxnrsfm.processes: independent processes, each on a share of the trials (5 -> 2 + 3),
    # joined in trial order: one process's numbers, every cell in the same order.
    settings = SweepSettings(noise=(1.0,), outliers=(0.1, 0.2), trials=5, frames=12, methods=("direct",))
    one, split = run_sweep(settings), run_sweep_in_processes(settings, 2)
    assert split["devices"] == ["process 0: cpu:0", "process 1: cpu:0"]
    assert split["settings"] == one["settings"] and split["floor"] == one["floor"]
    for a, b in zip(one["cells"], split["cells"], strict=True):
        assert (b["outliers"], b["method"], b["success"]) == (a["outliers"], a["method"], a["success"])
        np.testing.assert_allclose(b["error"], a["error"], rtol=1e-9)
    with pytest.raises(ValueError, match="unknown method 'magic'"):  # before any process starts
        run_sweep_in_processes(SweepSettings(methods=("magic",)), 2)
    with pytest.raises(ValueError, match="processes must be >= 1"):
        run_sweep_in_processes(settings, 0)
