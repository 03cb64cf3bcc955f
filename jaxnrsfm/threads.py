"""LAPACK on one thread while the library's compiled programs run on a CPU.

XLA:CPU runs a program's SVDs, eigendecompositions, Cholesky and QR factorizations through
SciPy's LAPACK (jaxlib takes its kernels from ``scipy.linalg.cython_lapack``), i.e.
OpenBLAS, which by default splits each call over every core. The pipeline's matrices are
small (the paper's cube: 200 x 252) and it makes hundreds of such calls a trial, each
waking threads that then contend with XLA's own. Measured on a 2-core CPU, 20 paper-size
cube trials of ``wang`` through `jaxnrsfm.reconstruct_batch`, the code before and after
alternating (five pairs of runs, best of three repetitions each): 276-430 ms a trial
before, 202-280 ms after, 13-36% less in every pair; the same results to round-off (the
trials' summed e3D equal to 11 digits). A process on both cores now runs a trial about as
fast as one pinned to a single core, which before was 1.1-2x faster. NumPy's own calls in
`jaxnrsfm.choose_k`'s robust PCA (300 SVDs of the tracks) run under the limit too: on an
idle machine it changes nothing (drink 1.3-1.7 s either way), beside another process on the
other core it is what keeps them fast (drink 3.5 -> 1.4 s, dance 5.9-11.9 -> 1.5 s). Only
the threads change: the limit is set for the call and restored after it, and applies to every BLAS
library of the process (NumPy's too) meanwhile.
"""

import contextlib
import functools
from collections.abc import Callable, Iterator
from typing import TypeVar

import jax
import scipy.linalg.cython_lapack  # noqa: F401 -- loads the OpenBLAS that jaxlib's LAPACK kernels call
from threadpoolctl import ThreadpoolController

T = TypeVar("T")


@functools.cache
def _controller() -> ThreadpoolController:
    # The thread pools of the BLAS libraries loaded at the first call (SciPy's above).
    return ThreadpoolController()


@contextlib.contextmanager
def single_threaded_lapack(host: bool = False) -> Iterator[None]:
    """Within the block, BLAS and LAPACK run on one thread: on a CPU backend, or for
    NumPy's own calls on the host (``host``) on any. JAX dispatches asynchronously: block
    on the results inside it."""
    if not host and jax.default_backend() != "cpu":
        yield
        return
    with _controller().limit(limits=1, user_api="blas"):
        yield


def compute_single_threaded(fn: Callable[..., T], *args, **kwargs) -> T:
    """``fn(*args, **kwargs)`` computed to the end (blocked on) within
    `single_threaded_lapack`: how the library runs its compiled programs on concrete arrays."""
    with single_threaded_lapack():
        return jax.block_until_ready(fn(*args, **kwargs))
