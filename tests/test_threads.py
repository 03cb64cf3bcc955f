"""LAPACK on one thread while the library's programs run on a CPU (jaxnrsfm.threads)."""

import jax
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from jaxnrsfm.threads import compute_single_threaded, single_threaded_lapack


def _threads() -> dict[str, int]:
    return {lib["filepath"]: lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"}


@pytest.mark.skipif(jax.default_backend() != "cpu", reason="the limit applies on a CPU backend only")
def test_one_thread_inside_and_the_caller_limit_after():
    # The test workers run on one core each, where OpenBLAS already has one thread: set two
    # first, so that both the limit and its undoing can fail.
    with threadpool_limits(2, user_api="blas"):
        before = _threads()
        # jaxlib's LAPACK kernels are SciPy's: its OpenBLAS is among the libraries limited.
        assert any("scipy" in path for path in before), before
        assert set(before.values()) == {2}
        with single_threaded_lapack():
            assert set(_threads().values()) == {1}
        assert _threads() == before
        # What the library's calls use: the function runs under the limit, and its result comes back.
        assert set(compute_single_threaded(_threads).values()) == {1}
        assert _threads() == before
