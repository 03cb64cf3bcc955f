"""Variable projection for low-rank factorization with missing data.

Minimise ``f(M) = sum_visible (W - M S)^2`` with the structure ``S`` eliminated in closed
form: given ``M``, each column ``s_j`` is the least-squares solution over the visible rows
of column ``j``, ``s_j = (M_j^T M_j)^-1 M_j^T w_j``. What is left is a function of ``M``
alone, minimised by Levenberg--Marquardt. This is the Wiberg algorithm (Wiberg 1976;
Okatani & Deguchi, IJCV 2007; Okatani, Yoshida & Deguchi's damped Wiberg, ICCV 2011) in
the unified form of Hong & Fitzgibbon, "Secrets of matrix factorization: approximations,
numerics, manifold optimization and random restarts" (ICCV 2015), whose ingredients are
kept here:

* **Variable projection** (Golub & Pereyra 1973): ``S`` never appears as an unknown, so
  the bilinear coupling that makes alternating least squares crawl is gone.
* **Gauss--Newton matrix.** With ``D_j`` the visible rows of column ``j``, ``G_j = M^T D_j
  M``, ``P_j = D_j M G_j^-1 M^T D_j`` and ``r_j = (D_j - P_j) w_j``, the Jacobian of the
  residual applied to a direction ``dM`` is (Ruhe & Wedin 1980)

      ``J dM = -(D_j - P_j) dM s_j  -  D_j M G_j^-1 dM^T r_j``.

  The two terms are orthogonal (``(D_j - P_j) D_j M = 0``), so the Gauss--Newton matrix is
  a sum of two Kronecker-structured parts, both assembled in closed form from per-column
  ``r x r`` and per-row-pair quantities (see :func:`_normal_equations`). Dropping the second
  term gives Kaufman's approximation (Wiberg's original algorithm, Hong & Fitzgibbon's
  "RW3"); keeping it is the full Gauss--Newton matrix ("RW2"), the default.
* **Gauge.** ``f(M) = f(M G)`` for every invertible ``r x r`` matrix ``G``: the
  Gauss--Newton matrix is singular along the ``r^2`` directions ``dM = M Gamma``. Hong &
  Fitzgibbon's *projection constraint* adds the projector onto those directions to the
  damped matrix (the gradient has no component along them, so the step is unchanged in
  exact arithmetic, but the solve is well conditioned), and the *retraction* replaces
  ``M + dM`` by the ``Q`` factor of its QR decomposition, which spans the same column
  space and so has the same cost: only the subspace ``span(M)`` matters (a point of the
  Grassmannian).
* **Damping.** Levenberg's ``lambda I``, multiplied by 10 after a rejected step and divided
  by 10 after an accepted one, as in Hong & Fitzgibbon's experiments.

The Oxford dinosaur (``shared/data/lrmf``) is the classic test: from random starts this
reaches the best known optimum (RMS 1.084673) almost every time, where alternating least
squares often stalls above it.
"""

from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int

from .tracks import row_mask


def _retract(M: Float[Array, "2m r"]) -> Float[Array, "2m r"]:
    # The cost depends on span(M) only: an orthonormal basis of it keeps every G_j and the
    # normal matrix on one scale and makes the gauge projector simply M M^T.
    return jnp.linalg.qr(M)[0]


def _project(
    W: Float[Array, "2m n"], mask: Float[Array, "2m n"], M: Float[Array, "2m r"]
) -> tuple[Float[Array, "r n"], Float[Array, "n r r"], Float[Array, "2m n"]]:
    """``S`` in closed form given ``M``, with each column's ``G_j^-1`` and the residual."""
    r = M.shape[1]
    eye = jnp.eye(r, dtype=M.dtype)
    G = jnp.einsum("ij,ia,ib->jab", mask, M, M)
    # A column seen in barely enough frames can have a nearly singular G_j for some M;
    # a ridge at round-off level keeps its s_j finite without changing any fit that
    # the data determines.
    ridge = 10 * jnp.finfo(M.dtype).eps * jnp.trace(G, axis1=1, axis2=2) / r + jnp.finfo(M.dtype).tiny
    Ginv = jnp.linalg.inv(G + ridge[:, None, None] * eye)
    S = jnp.einsum("jab,ij,ib->aj", Ginv, mask * W, M)
    R = mask * (W - M @ S)
    return S, Ginv, R


def _normal_equations(
    M: Float[Array, "2m r"],
    S: Float[Array, "r n"],
    Ginv: Float[Array, "n r r"],
    R: Float[Array, "2m n"],
    mask: Float[Array, "2m n"],
    full: bool,
) -> tuple[Float[Array, "2mr 2mr"], Float[Array, " 2mr"]]:
    """Gauss--Newton matrix ``J^T J`` and gradient ``J^T r`` of ``f / 2`` over ``vec(M)``
    (row-major: index ``(i, a)`` is ``M[i, a]``), assembled without forming ``J``.

    ``sum_j (s_j s_j^T) (x) (D_j - P_j)`` is the first term's part: a block diagonal (the
    alternating-least-squares normal matrix of ``M``) minus the projections. The second
    term contributes ``sum_j (r_j r_j^T) (x) G_j^-1``. Each is one contraction over the
    ``n`` columns of ``(2m)^2 x r^2`` outer products, ``O(n m^2 r^2)`` work and
    ``(2m r)^2`` memory, where the dense Jacobian would be ``2mn x 2mr``.
    """
    two_m, r = M.shape
    SS = jnp.einsum("aj,bj->jab", S, S)
    MG = jnp.einsum("ic,jcd->jid", M, Ginv)
    Q = jnp.einsum("jid,kd->jik", MG, M) * mask.T[:, :, None] * mask.T[:, None, :]
    H = -jnp.einsum("jik,jab->iakb", Q, SS)
    blocks = jnp.einsum("ij,jab->iab", mask, SS)
    H = H + jnp.einsum("ik,iab->iakb", jnp.eye(two_m, dtype=M.dtype), blocks)
    if full:
        H = H + jnp.einsum("ij,kj,jab->iakb", R, R, Ginv)
    g = -(R @ S.T)
    return H.reshape(two_m * r, two_m * r), g.reshape(-1)


class _State(eqx.Module):
    M: Float[Array, "2m r"]
    S: Float[Array, "r n"]
    cost: Float[Array, ""]
    H: Float[Array, "2mr 2mr"]
    g: Float[Array, " 2mr"]
    damping: Float[Array, ""]
    step: Int[Array, ""]
    done: Bool[Array, ""]
    converged: Bool[Array, ""]


@eqx.filter_jit
def varpro(
    W: Float[Array, "2m n"],
    visible: Bool[Array, "m n"],
    M0: Float[Array, "2m r"],
    *,
    max_steps: int = 300,
    rtol: float | None = None,
    damping: float = 1e-4,
    jacobian: Literal["full", "approximate"] = "full",
) -> tuple[Float[Array, "2m r"], Float[Array, "r n"], Int[Array, ""], Bool[Array, ""]]:
    """Minimise ``sum_visible (W - M S)^2`` by variable projection with
    Levenberg--Marquardt damping (damped Wiberg; Hong & Fitzgibbon, ICCV 2015).

    Pure and jit-compiled; vmap over starts or over problems of one shape. Under
    ``jax.vmap`` the loop runs in lockstep until the slowest member stops, so
    ``jax.lax.map`` can be faster for many starts of one small problem.

    **Arguments:**

    - `W`: tracks ``(2m, n)``, zero at missing entries (see
      :func:`jaxnrsfm.tracks.prepare_tracks`); the dtype of the computation.
    - `visible`: ``(m, n)`` mask; entry ``(i, j)`` covers rows ``2i, 2i+1`` of column ``j``.
      Every column needs at least ``r`` visible rows and every row at least ``r``
      visible columns, or its factor is not determined.
    - `M0`: the start ``(2m, r)``: random (``jax.random.normal``) or an SVD factor; only its
      column space matters.
    - `max_steps`: Levenberg--Marquardt iterations, rejected ones included.
    - `rtol`: stop when an accepted step lowers the cost by less than ``rtol`` of itself.
      Default ``1e-10``, or ``1e3`` machine epsilons if that is larger (float32).
    - `damping`: initial Levenberg damping, relative to the mean diagonal of ``J^T J``.
    - `jacobian`: ``"full"`` Gauss--Newton matrix (Ruhe & Wedin's algorithm II) or
      ``"approximate"`` (Kaufman's, as in the original Wiberg algorithm).

    **Returns:** ``(M, S, steps, converged)``: ``M`` with orthonormal columns, ``S`` the
    least-squares structure for it, the iterations taken, and whether a stopping test
    (relative decrease below ``rtol``, cost negligible against the data, or no descent
    step left at working precision) was met before ``max_steps``.
    """
    if jacobian not in ("full", "approximate"):
        raise ValueError(f"jacobian must be 'full' or 'approximate'; got {jacobian!r}")
    dtype = W.dtype
    eps = jnp.finfo(dtype).eps
    rtol = max(1e-10, 1e3 * float(eps)) if rtol is None else rtol
    full = jacobian == "full"
    mask = row_mask(visible).astype(dtype)
    two_m, r = M0.shape
    floor = eps**2 * jnp.sum(mask * W**2)
    identity = jnp.eye(two_m * r, dtype=dtype)
    # Beyond this relative damping a step is a gradient step too short to change the cost
    # at working precision: the iterate is stationary.
    max_damping = 1 / eps

    def evaluate(M):
        S, Ginv, R = _project(W, mask, M)
        return S, Ginv, R, jnp.sum(R**2)

    def body(state: _State) -> _State:
        # Hand-rolled rather than optx.least_squares: the retraction (QR of M after every
        # step) and the projection constraint are outside optimistix's LM, and its linear
        # solvers see J only through JVPs (a dense QR of the 2mn x 2mr Jacobian, or CG
        # whose iteration count vmap runs in lockstep), where here J^T J is assembled
        # exactly and cheaply from the block structure and solved by one Cholesky.
        scale = jnp.trace(state.H) / (two_m * r)
        gauge = jnp.einsum("ik,ab->iakb", state.M @ state.M.T, jnp.eye(r, dtype=dtype)).reshape(identity.shape)
        A = state.H + scale * (state.damping * identity + gauge)
        operator = lx.MatrixLinearOperator(A, lx.positive_semidefinite_tag)
        delta = lx.linear_solve(operator, -state.g, lx.Cholesky(), throw=False).value
        M = _retract(state.M + delta.reshape(two_m, r))
        S, Ginv, R, cost = evaluate(M)
        accept = jnp.isfinite(cost) & (cost < state.cost)
        H, g = jax.lax.cond(
            accept,
            lambda: _normal_equations(M, S, Ginv, R, mask, full),
            lambda: (state.H, state.g),
        )
        small = accept & ((state.cost - cost <= rtol * cost) | (cost <= floor))
        damping = jnp.where(accept, jnp.maximum(state.damping / 10, eps), state.damping * 10)
        stuck = damping > max_damping
        return _State(
            M=jnp.where(accept, M, state.M),
            S=jnp.where(accept, S, state.S),
            cost=jnp.where(accept, cost, state.cost),
            H=H,
            g=g,
            damping=damping,
            step=state.step + 1,
            done=small | stuck,
            converged=small | stuck,
        )

    M = _retract(M0.astype(dtype))
    S, Ginv, R, cost = evaluate(M)
    H, g = _normal_equations(M, S, Ginv, R, mask, full)
    init = _State(
        M=M,
        S=S,
        cost=cost,
        H=H,
        g=g,
        damping=jnp.asarray(damping, dtype),
        step=jnp.array(0),
        done=cost <= floor,
        converged=cost <= floor,
    )
    final = jax.lax.while_loop(lambda s: ~s.done & (s.step < max_steps), body, init)
    return final.M, final.S, final.step, final.converged
