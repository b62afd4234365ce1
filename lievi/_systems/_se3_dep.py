"""The DEP equation of a rigid body on SE(3) in closed form (paper (4.8); `lievi.DEP`).

For `RigidBodySE3` with kinetic tensor `M`, increment `ξ = (ω, v)` and `μ = (a, b) = Mξ/h`,
the left-invariant DEP equation `dφ⁻¹(ξ)ᵀ μ = m` has the block structure of `lievi.SE3`:
with `K = dφ⁻¹_SO(3)(ω)ᵀ` (the SO(3) equation's operator) and `L` its translation block,

    r_ω = K a + L b − Π,      r_v = K' b − P,

where, with `t = |ω|²`, `s = ω·v`,

- exp chart: `K y = K' y = y + ω×y/2 + c(t)(ω(ω·y) − t y)`, `c = (1 − (θ/2)cot(θ/2))/θ²`,
  and `L y = v×y/2 + 2c′(t)s(ω(ω·y) − t y) + c(ω(v·y) + v(ω·y) − 2s y)` (the transpose of
  `∂_v J⁻¹`, `lievi.SE3.dexpinv`'s lower-left block, expanded with `v×(ω×y) = ω(v·y) − y s`);
- Cayley chart: `K y = y + ω×y/2 + ω(ω·y)/4`, `K' y = y + ω×y/2`, `L y = v×K' y/2`
  (the transpose of `lievi.SE3.dcayinv`).

and its Jacobian is `dφ⁻¹(ξ)ᵀ M/h + E`, with `E` the derivative of `dφ⁻¹(ξ)ᵀ μ` at fixed `μ`
(written out in `_blocks`; needs `c′` and `c″`). `RigidBodySE3.kernel_step` runs the whole
DEP step from here: Newton with this Jacobian (`lievi/_systems/_se3_newton.py`: the same
formulas on small arrays, the 6×6 system by Gauss–Jordan elimination), then `F = φ(ξ)`,
`Ad_Fᵀ m` (DLP 3.3) and `g F` (2.9). It takes the same Newton iterates as the generic path
(`jax.jacfwd` of the residual built from `lievi.SE3.dexpinv`/`dcayinv`, `linalg.solve`),
at a fraction of the cost (`benchmarks/se3_step_cost.py`).

The forward step is written on `(3,)`–`(6, 6)` arrays whose elementwise expressions XLA
fuses into a few kernels: on CPU a scalar formulation (below, as in the SO(3) fast step
`lievi._batch._fast_so3`) runs each scalar it must materialise (`_barrier`) as a kernel of
its own, about a hundred an iteration, and for one body their launch cost, not the
arithmetic, set the time (measured: 7.1 µs a step against 3.9 µs on arrays, float64, exp
chart, `benchmarks/se3_step_cost.py`). The coefficients are power series in `u = θ²/4`, accurate to round-off up to
θ = π (the exp chart's domain), with no library trigonometry. Derivatives of the root come
from the implicit function theorem (`_at_root`), not from the Newton iterations, in the
scalar form: `residual` and the block solve `solve6` with 3×3 Cramer inverses. The tests
check `r`, `∂r/∂ξ` (both forms), the step and its gradients against the generic path.
"""

from __future__ import annotations

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._batch._fast_se3 import _dexpinv_coefficients as _dexpinv_coefficient
from .._batch._fast_se3 import _inverse3
from .._batch._fast_so3 import _C, _S, _dot
from .._results import RESULTS
from . import _se3_newton


# 3×3 matrices as nested tuples of scalars (structure of arrays).
def _hat(x):
    z = jnp.zeros_like(x[0])
    return ((z, -x[2], x[1]), (x[2], z, -x[0]), (-x[1], x[0], z))


def _outer(x, y):
    return tuple(tuple(x[i] * y[j] for j in range(3)) for i in range(3))


def _lin(*terms):
    """`Σ αₖ Xₖ` for pairs `(α, X)`; `X = None` stands for the identity."""
    out = [[0.0] * 3 for _ in range(3)]
    for alpha, X in terms:
        for i in range(3):
            for j in range(3):
                entry = (alpha if i == j else 0.0) if X is None else alpha * X[i][j]
                out[i][j] = out[i][j] + entry
    return tuple(tuple(row) for row in out)


def _mm(X, Y):
    return tuple(
        tuple(sum(X[i][k] * Y[k][j] for k in range(3)) for j in range(3)) for i in range(3)
    )


def _mv(X, y):
    return tuple(sum(X[i][k] * y[k] for k in range(3)) for i in range(3))


def _blocks(chart, omega, v, a, b):
    """`(K, L, K′, E)`: the blocks of `dφ⁻¹(ξ)ᵀ = [[K, L], [0, K′]]` and the partial
    derivatives `E = ∂/∂ξ (dφ⁻¹(ξ)ᵀ μ)` at fixed `μ = (a, b)`, as 3×3 blocks
    `((E_ωω, E_ωv), (E_vω, 0))`."""
    W, V, Ba = _hat(omega), _hat(v), _hat(a)
    Bb = _hat(b)
    ow, vb = _outer(omega, omega), None
    if chart == "cayley":
        K = _lin((1.0, None), (0.5, W), (0.25, ow))
        Kp = _lin((1.0, None), (0.5, W))
        L = _lin((0.5, _mm(V, Kp)))
        Kb = _mv(Kp, b)
        oa = _dot(omega, a)
        E_ww = _lin((-0.5, Ba), (oa / 4, None), (0.25, _outer(omega, a)), (-0.25, _mm(V, Bb)))
        E_wv = _lin((-0.5, _hat(Kb)))
        E_vw = _lin((-0.5, Bb))
        return K, L, Kp, (E_ww, E_wv, E_vw)
    t, s = _dot(omega, omega), _dot(omega, v)
    c, c1, c2 = _barrier(_dexpinv_coefficient(t))
    W2 = _mm(W, W)
    K = _lin((1.0, None), (0.5, W), (c, W2))
    L = _lin((0.5, V), (2 * c1 * s, W2), (c, _mm(V, W)), (c, _mm(W, V)))

    def z(y):  # ω(ω·y) − t y
        oy = _dot(omega, y)
        return tuple(omega[i] * oy - t * y[i] for i in range(3))

    def D_K(y, By):  # ∂/∂ω [y + ω×y/2 + c z(y)]
        oy = _dot(omega, y)
        return _lin(
            (-0.5, By),
            (c * oy, None),
            (c, _outer(omega, y)),
            (-2 * c, _outer(y, omega)),
            (2 * c1, _outer(z(y), omega)),
        )

    ob, vb = _dot(omega, b), _dot(v, b)
    zb = z(b)
    w = tuple(omega[i] * vb + v[i] * ob - 2 * s * b[i] for i in range(3))
    # L b = v×b/2 + 2c′s z(b) + c w,  w = ω(v·b) + v(ω·b) − 2s b.
    dL_w = _lin(
        (4 * c2 * s, _outer(zb, omega)),
        (2 * c1, _outer(zb, v)),
        (2 * c1 * s * ob, None),
        (2 * c1 * s, _outer(omega, b)),
        (-4 * c1 * s, _outer(b, omega)),
        (2 * c1, _outer(w, omega)),
        (c * vb, None),
        (c, _outer(v, b)),
        (-2 * c, _outer(b, v)),
    )
    dL_v = _lin(
        (-0.5, Bb),
        (2 * c1, _outer(zb, omega)),
        (c, _outer(omega, b)),
        (c * ob, None),
        (-2 * c, _outer(b, omega)),
    )
    E_ww = _lin((1.0, D_K(a, Ba)), (1.0, dL_w))
    return K, L, K, (E_ww, dL_v, D_K(b, Bb))


def residual(chart: str, x, m, A, with_jacobian: bool):
    """`r = dφ⁻¹(x)ᵀ A x − m` and, if asked, `∂r/∂x = dφ⁻¹(x)ᵀ A + E` (`_blocks`).

    All arguments structure of arrays: `x`, `m` 6-tuples, `A = M/h` a 6×6 nested tuple.
    Returns `(r, J)` as a 6-tuple and a 6×6 nested tuple (`J = None` without the Jacobian).
    """
    omega, v = x[:3], x[3:]
    mu = tuple(sum(A[i][j] * x[j] for j in range(6)) for i in range(6))
    a, b = mu[:3], mu[3:]
    K, L, Kp, E = _blocks(chart, omega, v, a, b)
    if with_jacobian:
        K, L, Kp, E = _barrier((K, L, Kp, E))
    Ka, Lb, Kpb = _mv(K, a), _mv(L, b), _mv(Kp, b)
    r = tuple(Ka[i] + Lb[i] - m[i] for i in range(3)) + tuple(Kpb[i] - m[3 + i] for i in range(3))
    if not with_jacobian:
        return r, None
    E_ww, E_wv, E_vw = E
    block = [
        [
            tuple(tuple(A[3 * I + i][3 * Jb + j] for j in range(3)) for i in range(3))
            for Jb in range(2)
        ]
        for I in range(2)
    ]
    (A11, A12), (A21, A22) = block
    J11 = _lin((1.0, _mm(K, A11)), (1.0, _mm(L, A21)), (1.0, E_ww))
    J12 = _lin((1.0, _mm(K, A12)), (1.0, _mm(L, A22)), (1.0, E_wv))
    J21 = _lin((1.0, _mm(Kp, A21)), (1.0, E_vw))
    J22 = _mm(Kp, A22)
    return r, tuple(J11[i] + J12[i] for i in range(3)) + tuple(J21[i] + J22[i] for i in range(3))


def _barrier(values):
    """The scalars of `values` (a pytree), computed once.

    XLA on CPU fuses a shared scalar subexpression into every consumer, so without this
    each of the six components of a Newton update recomputes the whole Jacobian (~6× the
    work; `lax.optimization_barrier` does not stop it). A reduction is not duplicated: the
    values pass through a sum with zeros, which leaves them unchanged.
    """
    leaves, tree = jax.tree.flatten(values)
    stacked = jnp.stack(jnp.broadcast_arrays(*leaves))
    stacked = jnp.sum(jnp.stack([stacked, jnp.zeros_like(stacked)]), axis=0)
    return jax.tree.unflatten(tree, [stacked[i] for i in range(len(leaves))])


def solve6(J, r):
    """`J⁻¹ r` for a 6×6 `J = [[P, Q], [R, S]]` by block elimination with 3×3 inverses
    (Cramer): `x₂ = (S − R P⁻¹ Q)⁻¹ (r₂ − R P⁻¹ r₁)`, `x₁ = P⁻¹ (r₁ − Q x₂)`. Needs `P`
    invertible: for the DEP equation `J` is `M/h` (positive definite) plus `O(|ξ|)`."""
    P = tuple(J[i][:3] for i in range(3))
    Q = tuple(J[i][3:] for i in range(3))
    R = tuple(J[3 + i][:3] for i in range(3))
    S = tuple(J[3 + i][3:] for i in range(3))
    Pinv = _barrier(_inverse3(P))
    # Separate barriers: under the implicit derivative `r` is a tangent and `J` is not,
    # and one stacked array mixing them would be linear in both.
    PinvQ, Pinv_r1 = _barrier(_mm(Pinv, Q)), _barrier(_mv(Pinv, r[:3]))
    schur = _lin((1.0, S), (-1.0, _mm(R, PinvQ)))
    R_Pinv_r1 = _mv(R, Pinv_r1)
    x2 = _barrier(_mv(_inverse3(schur), tuple(r[3 + i] - R_Pinv_r1[i] for i in range(3))))
    Qx2 = _mv(PinvQ, x2)
    return tuple(Pinv_r1[i] - Qx2[i] for i in range(3)) + x2


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _at_root(chart, x, m, A):
    """`x` (`(6,)`), a root of `r(·; m, A)`, with the derivative of the root as a function of
    `(m, A)` (`(6,)`, `(6, 6)`)."""
    return x


@_at_root.defjvp
def _at_root_jvp(chart, primals, tangents):
    # Implicit function theorem: J dx = −(∂r/∂m dm + ∂r/∂A dA), with the closed-form J,
    # in the scalar form (so that JAX transposes a few long elementwise loops).
    x, m, A = (_tuples(y) for y in primals)
    dm, dA = (_tuples(y) for y in tangents[1:])
    _, dr = jax.jvp(lambda mm, AA: residual(chart, x, mm, AA, False)[0], (m, A), (dm, dA))
    _, J = residual(chart, x, m, A, True)
    delta = solve6(J, dr)
    return primals[0], -jnp.stack(delta)


def _tuples(y):
    """A `(6,)` or `(6, 6)` array as (nested) tuples of scalars."""
    if y.ndim == 1:
        return tuple(y[i] for i in range(y.shape[0]))
    return tuple(_tuples(row) for row in y)


_E44 = np.zeros((4, 4))
_E44[3, 3] = 1.0

# (θ − sin θ)/θ³ = Σ (−1)ᵏ tᵏ/(2k + 3)!, t = θ²: 13 terms reach round-off at θ = π.
_SINC3 = tuple((-1) ** k / math.factorial(2 * k + 3) for k in range(13))


def _horner(coefficients, u):
    value = jnp.zeros_like(u)
    for c in reversed(coefficients):
        value = value * u + c
    return value


def dep_step(chart: str, g, m, A, guess, tolerance, max_steps: int):
    """One DEP/DLP step of a left-invariant `RigidBodySE3` (no potential), structure of arrays.

    `g`: the `(4, 4)` pose; `m`: `(6,)`; `A = M/h`: `(6, 6)`; `guess`: the Newton start
    `(6,)` (`h·M⁻¹m`, as `DEP.solve_increment`). Solves the DEP equation, then
    `F = φ(ξ)`, `m_{k+1} = Ad_Fᵀ m` (DLP 3.3) and `g_{k+1} = g F` (2.9) with the rotation
    block re-orthonormalised as `lievi.SE3.compose` does.
    Returns `(g_next, m_next, result, iterations, residual)`; differentiable in `m`, `A`, `g`.
    """
    # Newton on arrays (`_se3_newton`: a few fused kernels an iteration); the derivative
    # at the root in scalar form (`_at_root`). The rest of the step on arrays too.
    stopped = jax.lax.stop_gradient((guess, m, A, tolerance))
    x, norm, iterations = _se3_newton.newton(chart, *stopped, max_steps)
    # A diverged solve continues from the finite guess (a masked failed step then
    # contributes 0, not NaN, to a gradient), as `newton_solve` does.
    finite = (norm == norm) & jnp.all(jnp.isfinite(x))
    x = jnp.where(finite, x, stopped[0])
    x = _at_root(chart, jax.lax.stop_gradient(x), m, A)

    omega, v = x[:3], x[3:]
    t, I3 = omega @ omega, _se3_newton._eye(x.dtype)
    W = _se3_newton._hat(omega)
    W2 = _se3_newton._outer(omega, omega) - t * I3  # ω̂²
    if chart == "exp":
        S, C = _horner(_S, t / 4), _horner(_C, t / 4)
        a, b = S * C, S * S / 2  # sin θ/θ, (1 − cos θ)/θ²
        RF = I3 + a * W + b * W2
        tF = (I3 + b * W + _horner(_SINC3, t) * W2) @ v
    else:
        alpha = 4 / (4 + t)
        RF = I3 + alpha * W + alpha / 2 * W2
        tF = (v + RF @ v) / 2  # (I + cay Ω)/2 v = (I − Ω/2)⁻¹ v
    # Ad_Fᵀ m = (RFᵀ(Π + P×tF), RFᵀP), P×tF = −t̂F P.
    m_next = _se3_newton._blocks(RF.T, -RF.T @ _se3_newton._hat(tF), jnp.zeros_like(RF), RF.T) @ m

    R, p = g[:3, :3], g[:3, 3]
    Rn = R @ RF
    Rn = Rn - Rn @ (Rn.T @ Rn - I3) / 2  # one Newton–Schulz step, as SE3.compose
    g_next = (
        jnp.pad(Rn, ((0, 1), (0, 1)))
        + jnp.pad((R @ tF + p)[:, None], ((0, 1), (3, 0)))
        + jnp.asarray(_E44, Rn.dtype)
    )

    converged = norm <= tolerance
    result = jnp.where(converged, RESULTS.successful, RESULTS.newton_not_converged)
    if chart == "exp":
        # Beyond the injectivity radius of exp (rotation angle π) the root is on another branch.
        result = jnp.where(t >= math.pi**2, RESULTS.step_too_large, result)
    ok = jnp.isfinite(norm) & jnp.all(jnp.isfinite(m_next))
    result = jnp.where(ok, result, RESULTS.nonfinite)
    return g_next, m_next, result.astype(jnp.int32), iterations, norm
