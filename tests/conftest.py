import gc
import os
import shutil
import tempfile
from pathlib import Path


def _pin_worker() -> None:
    """Give each pytest-xdist worker its own share of the CPU cores.

    XLA's CPU runtime sizes its thread pools by the cores a process may run on; two workers
    (and the notebook kernels and command-line processes they start) each spreading over
    every core contend. Measured on a 2-core CPU: the whole drink sequence's default
    reconstruction took 89 s alone, 76 s on one core, and 765 s beside the other worker.
    Subprocesses inherit the affinity.
    """
    worker, count = os.environ.get("PYTEST_XDIST_WORKER"), os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if worker is None or count is None or not hasattr(os, "sched_setaffinity"):
        return
    cores = sorted(os.sched_getaffinity(0))
    share = len(cores) // int(count)
    if share:
        index = int(worker.removeprefix("gw"))
        os.sched_setaffinity(0, cores[index * share : (index + 1) * share])


# Before jax starts its backend (and sizes its thread pools).
_pin_worker()

CACHE_FOLDER = "JAXNRSFM_TEST_COMPILATION_CACHE"
"""Environment variable holding the test session's compilation cache folder, made by the
process that starts the session (the pytest-xdist controller, or pytest alone)."""


def _share_compiled_programs() -> None:
    """One persistent compilation cache for the whole test session, empty at its start.

    Many tests compile the same programs (the robust pipeline at the same shapes and
    options), in other modules (whose compiled programs are dropped when the module is
    done, see below), in the other xdist worker, or in the notebook kernels and command-line
    processes the tests start: each compiles once a session, and the others load it. The
    folder is made fresh by the session's first process, inherited by the workers and the
    subprocesses it starts, and removed at the session's end (:func:`pytest_unconfigure`),
    so no test ever sees a program compiled by an earlier session.
    """
    if CACHE_FOLDER not in os.environ:
        os.environ[CACHE_FOLDER] = tempfile.mkdtemp(prefix="jaxnrsfm-tests-")
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.environ[CACHE_FOLDER]
    # Every program, not only those that took JAX's default of a second to compile: under the
    # flags below most of the suite's programs compile faster than that.
    os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "0"


_share_compiled_programs()
# A program with a host callback is never written to the persistent cache (JAX bakes the
# callback's address into it), and equinox's runtime checks (`eqx.error_if`, in lineax's and
# optimistix's backward solves) are host callbacks: every differentiated pipeline was
# compiled again in each test that used it. Their "nan" mode makes the same check poison
# the result instead of raising, with no callback (the gradient tests assert finite values;
# the library's users keep equinox's default, raising). tests/test_gradients.py in one
# process: 250 s -> 235 s (a case whose derivatives another case compiled: 24 -> 11 s).
os.environ["EQX_ON_ERROR"] = "nan"
# The tests compile far more than they run: XLA's lowest backend optimisation level cut the
# compilation of the robust pipeline by ~40% (cube, 30 frames: 18.5 s -> 11.3 s) and made
# its run ~40% slower (0.48 s -> 0.67 s). The computation is the same; results agree to round-off.
# XLA:CPU's older (non-MLIR) fusion emitters compile the default pipeline (cube, 30 frames,
# k = 2) in 3.5-5.0 s instead of 6.4-9.0 s, its run 3-10% slower, the same e3D to the digit.
# Each worker has one core (above), where splitting a program's code generation into parallel
# parts only adds work: with one part the default pipeline (cube, 30 frames, k = 3) compiled in
# 6.6-7.3 s instead of 7.2-8.6 s, and tests/test_gradients.py (one process) took 226 s, not 237 s.
os.environ["XLA_FLAGS"] = " ".join(
    [
        os.environ.get("XLA_FLAGS", ""),
        "--xla_backend_optimization_level=0",
        "--xla_cpu_use_fusion_emitters=false",
        "--xla_cpu_parallel_codegen_split_count=1",
    ]
).strip()

import jax  # noqa: E402
import pytest  # noqa: E402

from jaxnrsfm.cli import CACHE_ENV  # noqa: E402

# Numerical tests run in float64; the library itself never flips this flag.
jax.config.update("jax_enable_x64", True)

# The real data sit in ../shared/data beside the repository. Name it explicitly: with a
# non-editable install (as in CI) the package cannot find it from its own location, and
# the notebooks execute in a temporary directory.
_SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
if _SHARED.is_dir():
    os.environ.setdefault("JAXNRSFM_DATA", str(_SHARED))
# The command line's persistent compilation cache stays off in the tests that call it in this
# process (it would then cache every later test's programs in the home folder); the test of the
# cache names its own folder.
os.environ[CACHE_ENV] = ""


@pytest.fixture
def key():
    return jax.random.key(0)


@pytest.fixture
def restore_x64():
    """For a test that switches x64 (or runs a command that does): float64 again after it,
    the choice made above."""
    yield
    jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_programs():
    """Drop every compiled program when a test module is done.

    XLA:CPU maps each kernel of a compiled program into the process (three memory mappings a
    kernel, about 1800 for one robust reconstruction of the cube), and jit caches keep them all
    alive. A whole suite in one process passed Linux's default limit of 65530 mappings, and XLA
    aborted inside a compilation ("Fatal Python error: Aborted" in backend_compile).
    """
    yield
    jax.clear_caches()
    gc.collect()


HEAVIEST_FIRST = (
    "test_robust.py",
    "test_gradients.py",
    "test_notebooks.py",
    "test_cli.py",
    "test_readme.py",
    "test_pipeline.py",
    "test_multiprocess.py",
    "test_real.py",
    "test_varpro.py",
    "test_stages.py",
    "test_batch.py",
)
"""The modules that take longest, longest first (their tests' durations summed, two workers on
a 2-core CPU: about 140, 74, 62, 53, 31, 30, 29, 24, 17, 16 and 16 s); the others, 5 s or
less each, follow in their own order."""


def pytest_collection_modifyitems(items):
    # pytest-xdist hands whole modules to the workers (`--dist loadfile`, pyproject.toml), in
    # this order, each worker taking the next when it is nearly done: the longest first, so
    # that the last ones handed out are short and neither worker waits long for the other
    # at the end. Whole modules: a module's tests share its compiled programs and module
    # fixtures, which a module split over both workers compiled and computed twice.
    rank = {name: i for i, name in enumerate(HEAVIEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


def pytest_unconfigure(config):
    # The session's starting process (not an xdist worker) made the cache folder: remove it.
    if not hasattr(config, "workerinput"):
        shutil.rmtree(os.environ[CACHE_FOLDER], ignore_errors=True)
