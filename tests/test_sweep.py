"""A sweep split across several devices gives the numbers of one device."""

import json
import os
import subprocess
import sys

import jax
import numpy as np

from jaxnrsfm.sweep import SweepSettings, run_sweep

# Small, and the cheapest method to compile: every device compiles the pipeline. Six
# trials over four devices also exercises the padding of the trial axis.
SETTINGS = dict(noise=(2.0,), outliers=(0.1,), trials=6, frames=12, methods=("direct",))

FOUR_DEVICES = f"""
import json, jax
jax.config.update("jax_enable_x64", True)
from jaxnrsfm.sweep import SweepSettings, run_sweep
print(json.dumps(run_sweep(SweepSettings(**{SETTINGS!r}))))
"""


def test_four_cpu_devices_match_one():
    # The session's XLA flags (conftest: cheaper compilation) as well, as for the one device below.
    flags = f"{os.environ.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count=4".strip()
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, "-c", FOUR_DEVICES], env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, done.stderr[-3000:]
    four = json.loads(done.stdout.strip().splitlines()[-1])
    one = run_sweep(SweepSettings(**SETTINGS), devices=jax.devices()[:1])
    assert len(four["devices"]) == 4 and len(one["devices"]) == 1
    (a,), (b,) = four["cells"], one["cells"]
    assert len(a["error"]) == SETTINGS["trials"]
    np.testing.assert_allclose(a["error"], b["error"], rtol=1e-12)
    assert a["success"] == b["success"]
