import gc
import os
from pathlib import Path

import jax
import pytest

from jaxnrsfm.cli import CACHE_ENV

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
