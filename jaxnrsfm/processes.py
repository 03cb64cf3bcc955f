"""A sweep split over processes on this machine, each on its own cores.

On a CPU one running program keeps about one core busy, and the ways of using more from
one process failed: two CPU devices ran no faster than one, and trials from two Python
threads hung XLA:CPU (README, "Known limitations"). Separate processes share nothing: each
runs `jaxnrsfm.sweep.run_sweep` on a contiguous share of the trials, pinned to its share of
the cores (XLA and BLAS size their thread pools by them), and the shares are joined in
trial order. Trial ``t``'s data depend only on the seed and ``t``, so the numbers are those
of one process. Each process compiles its programs, one core each, or loads them from
JAX's persistent compilation cache when the caller set one (the processes are given its
folder); so the split pays where running the trials takes longer than compiling them
(README, "Several devices and hosts").
"""

import dataclasses
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

from .sweep import SweepSettings, check_methods, run_sweep

_CHILD = "import sys; from jaxnrsfm.processes import _child; _child(sys.argv[1], sys.argv[2])"


def run_sweep_in_processes(settings: SweepSettings, processes: int) -> dict:
    """`jaxnrsfm.sweep.run_sweep` of ``settings`` (default solver) as ``processes``
    processes on this machine (at most one per trial), each pinned to its share of the
    cores this process may use; the same JSON-ready dict, with every process's devices and
    each cell's wall time the slowest process's. A process that fails raises
    ``RuntimeError`` with the end of its output."""
    if processes < 1:
        raise ValueError(f"processes must be >= 1; got {processes}")
    check_methods(settings.methods)  # here, not in every process after its start
    processes = min(processes, settings.trials)
    starts = [i * settings.trials // processes for i in range(processes + 1)]
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    config = dict(
        x64=jax.config.jax_enable_x64,
        cache=jax.config.jax_compilation_cache_dir,
        min_compile_seconds=jax.config.jax_persistent_cache_min_compile_time_secs,
    )
    with tempfile.TemporaryDirectory() as folder:
        jobs = []
        for i in range(processes):
            share = dataclasses.replace(settings, trials=starts[i + 1] - starts[i])
            spec = Path(folder) / f"{i}.json"
            own = cores[i * len(cores) // processes : (i + 1) * len(cores) // processes]
            spec.write_text(json.dumps(dict(config, settings=dataclasses.asdict(share), first=starts[i], cores=own)))
            log = open(Path(folder) / f"{i}.log", "w")  # noqa: SIM115 -- closed when the process ends
            command = [sys.executable, "-c", _CHILD, str(spec), str(Path(folder) / f"{i}.out.json")]
            jobs.append((subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT), log))
        try:
            # Whichever ends first is seen first: a process that fails at its start stops the
            # others then, not after they have run their shares.
            running = set(range(processes))
            while running:
                time.sleep(0.1)
                for i in sorted(running):
                    code = jobs[i][0].poll()
                    if code is None:
                        continue
                    running.discard(i)
                    if code:
                        output = (Path(folder) / f"{i}.log").read_text()[-3000:]
                        raise RuntimeError(f"sweep process {i} of {processes} failed (exit status {code}):\n{output}")
        finally:
            # One place for every way out (done, a failed process, an interrupt): no process
            # outlives the call (killing one that has ended does nothing), no log stays open.
            for job, log in jobs:
                job.kill()
                job.wait()
                log.close()
        parts = [json.loads((Path(folder) / f"{i}.out.json").read_text()) for i in range(processes)]
    return _join(parts, settings)


def _join(parts: list[dict], settings: SweepSettings) -> dict:
    # The processes ran the same cells in the same order, each on its share of the trials.
    cells = []
    for shares in zip(*(part["cells"] for part in parts), strict=True):
        cell = dict(shares[0], seconds=max(share["seconds"] for share in shares))
        for field in ("error", "precision", "recall", "success"):
            cell[field] = [value for share in shares for value in share[field]]
        cells.append(cell)
    devices = [f"process {i}: {device}" for i, part in enumerate(parts) for device in part["devices"]]
    return dict(parts[0], settings=dataclasses.asdict(settings), devices=devices, cells=cells)


def _child(spec_path: str, out_path: str) -> None:
    # One process's share: its cores (before JAX starts its backend, which sizes its thread
    # pools by them), the caller's float width and compilation cache, then run_sweep.
    spec = json.loads(Path(spec_path).read_text())
    if spec["cores"]:
        os.sched_setaffinity(0, spec["cores"])
    jax.config.update("jax_enable_x64", spec["x64"])
    if spec["cache"] is not None:
        jax.config.update("jax_compilation_cache_dir", spec["cache"])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", spec["min_compile_seconds"])
    settings = spec["settings"]
    settings = SweepSettings(**{k: tuple(v) if isinstance(v, list) else v for k, v in settings.items()})
    result = run_sweep(settings, first_trial=spec["first"])
    Path(out_path).write_text(json.dumps(result))
