import jax
import pytest

# Numerical tests run in float64; the library itself never flips this flag.
jax.config.update("jax_enable_x64", True)


@pytest.fixture
def key():
    return jax.random.key(0)
