import os
from pathlib import Path

import jax
import pytest

# Numerical tests run in float64; the library itself never flips this flag.
jax.config.update("jax_enable_x64", True)

# The real data sit in ../shared/data beside the repository. Name it explicitly: with a
# non-editable install (as in CI) the package cannot find it from its own location, and
# the notebooks execute in a temporary directory.
_SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
if _SHARED.is_dir():
    os.environ.setdefault("JAXNRSFM_DATA", str(_SHARED))


@pytest.fixture
def key():
    return jax.random.key(0)
