"""The SE(3) DEP step for one body (or a few) as whole-array operations (paper (4.8),
(3.3), (2.9)).

The same step as `_se3.dep_step` — the DEP equation `dφ⁻¹(ξ)ᵀ Mξ/h = m` (4.8) solved for
the increment `ξ = (ω, v)`, `F = φ(ξ)`, `m_{k+1} = Ad_Fᵀ m_k` (DLP (3.3)), `g_{k+1} = g_k F`
(2.9) — written on 6-vectors and 6×6 matrices instead of 36 scalars per body:

- the residual is the generic path's (`DEP.residual`: the chart's `dφ⁻¹` as `lievi.SE3`
  writes it), its Jacobian `jax.jacfwd`'s, each Newton step one `jnp.linalg.solve` of the
  6×6 system;
- one Newton loop (`lax.while_loop`) from the explicit-Euler guess `h M⁻¹m`, stopping on
  `newton_tolerance` (the test of every implicit step) or after `max_steps`, one
  evaluation of `(r, J)` and one LU factorisation a pass; its root is differentiated by
  the implicit function theorem (`_at_root`, as the other kernels' roots), not through
  the iterations;
- the branch rule of `DEP.on_branch` (`det ∂r/∂ξ` of the sign of `det(M/h) > 0`, and for
  the exp chart a rotation angle below π) and the codes of `_se3.dep_step`.

Why it exists: written out as scalars, the structure-of-arrays step (`_se3.py`: fixed
reduced Newton iterations, a chord step, a gathered tail) is what a large batch needs, but
its program is large — about ten thousand HLO instructions before optimisation — and an
eager one-body `simulate` spent most of its first call compiling it. This step is a
fraction of that, so `SE3NewtonKernel.one_body` hands it to one-body runs.
"""

from __future__ import annotations

import functools
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.ad_checkpoint import checkpoint_name

from .._newton import ROOT_NAME, newton_tolerance
from .._results import RESULTS
from ._flat_batch import bodies_batched
from ._se3_layout import SE3Kernel
from ._se3_residual import SINC3, dexpinv_coefficients
from ._soa import C_SERIES, S_SERIES, component_major, entries, horner, matrix


def _hat(y):
    """`ŷ`, `ŷ z = y × z`."""
    zero = jnp.zeros_like(y[0])
    return jnp.stack(
        [
            jnp.stack([zero, -y[2], y[1]]),
            jnp.stack([y[2], zero, -y[0]]),
            jnp.stack([-y[1], y[0], zero]),
        ]
    )


def _operator_and_e(chart, x, mu):
    """`(D, E)`: `D = dφ⁻¹(ξ)ᵀ = [[K, L], [0, K′]]` and `E = ∂(dφ⁻¹(ξ)ᵀμ)/∂ξ` at fixed
    `μ = (a, b)`, 6×6 each, built from 3-vector outer products (`_se3_residual`'s
    `operator` and `e_blocks`, there entry by entry; the derivation in its module doc).
    The residual is `Dμ − m` with `μ = Aξ`, its Jacobian `DA + E`."""
    w, v = x[:3], x[3:]
    a, b = mu[:3], mu[3:]
    # The five dot products in one matrix product (each alone was a kernel of its own).
    dots = jnp.stack([w, v]) @ jnp.stack([w, v, a, b]).T
    t, s, oa, ob, vb = dots[0, 0], dots[0, 1], dots[0, 2], dots[0, 3], dots[1, 3]
    # NumPy constants: `jnp.eye` inside a trace costs a compiled program of its own.
    eye, W, outer = np.eye(3, dtype=x.dtype), _hat(w), jnp.outer
    if chart == "cayley":
        Kp = eye + W / 2
        K = Kp + outer(w, w) / 4
        L = _hat(v) / 2 + (outer(w, v) - s * eye) / 4
        E_ww = (oa + vb) / 4 * eye + (outer(w, a) - outer(b, v)) / 4 - _hat(a) / 2
        E_wv, E_vw = -_hat(Kp @ b) / 2, -_hat(b) / 2
    else:
        c, c1, c2 = dexpinv_coefficients(t)
        k = 2 * c1 * s
        K = Kp = (1 - c * t) * eye + W / 2 + c * outer(w, w)
        L = _hat(v) / 2 - (k * t + 2 * c * s) * eye + k * outer(w, w)
        L = L + c * (outer(w, v) + outer(v, w))
        za, zb = w * oa - t * a, w * ob - t * b
        lw = w * vb + v * ob - 2 * s * b
        y = 2 * c1 * zb - 2 * c * b
        u = -2 * c * a + 2 * c1 * (za + lw) + 4 * s * (c2 * zb - c1 * b)
        E_ww = (c * (oa + vb) + k * ob) * eye + outer(w, c * a + k * b) + outer(v, c * b)
        E_ww = E_ww + outer(u, w) + outer(y, v) - _hat(a) / 2
        E_wv = E_vw = c * ob * eye + outer(w, c * b) + outer(y, w) - _hat(b) / 2
    zero = jnp.zeros_like(eye)
    D = jnp.block([[K, L], [zero, Kp]])
    E = jnp.block([[E_ww, E_wv], [E_vw, zero]])
    return D, E


def _residual(chart, x, m, A):
    """The DEP residual `dφ⁻¹(ξ)ᵀ Aξ − m` (4.8), `A = M/h`: the generic path's
    (`DEP.residual`) to round-off."""
    mu = A @ x
    return _operator_and_e(chart, x, mu)[0] @ mu - m


def _residual_and_jacobian(chart, x, m, A):
    """`(r, ∂r/∂ξ)` in closed form, `∂r/∂ξ = dφ⁻¹(ξ)ᵀA + E` (`_operator_and_e`): about a
    quarter of the compile time of `jax.jacfwd` of `_residual`."""
    mu = A @ x
    D, E = _operator_and_e(chart, x, mu)
    return D @ mu - m, D @ A + E


def _newton(chart, m, A, guess, tolerance, max_steps: int):
    """Newton from `guess` on the 6×6 system: `(ξ, iterations, ‖r‖_∞, sign of det J)`,
    `J = ∂r/∂ξ` at `ξ`.

    Each pass takes the step found in the previous one (none in the first, which
    evaluates the guess), then evaluates `r` and `J` (`jax.jacfwd`) at the new iterate and
    factors `J` once (LU): the norm for the test, the next step and the sign of `det J`
    for the branch rule (from the factors' diagonal and pivots: `det J` itself, a product
    of six factors of the size of `M/h`, can leave float32's range). One evaluation of
    `(r, J)` in the program: evaluated before the loop as well, it was a second copy of
    the largest piece of the step."""

    def cond(carry):
        _, _, _, norm, iterations, started = carry
        going = (norm > tolerance) & jnp.isfinite(norm) & (iterations < max_steps)
        return ~started | going

    def body(carry):
        x, delta, _, _, iterations, started = carry
        x = jnp.where(started, x - delta, x)
        iterations = iterations + started.astype(jnp.int32)
        r, J = _residual_and_jacobian(chart, x, m, A)
        # LU with partial pivoting of `[J | r]`: `P[J | r] = L[U | c]` with `c = L⁻¹Pr`, so
        # `J⁻¹r = U⁻¹c`, one triangular solve and no permutation to apply (a loop in
        # XLA's program: `lu_solve` compiled into twice the kernels).
        lu, pivots, _ = jax.lax.linalg.lu(jnp.concatenate([J, r[:, None]], axis=1))
        U = lu[:, :6]
        delta = jax.lax.linalg.triangular_solve(U, lu[:, 6:], left_side=True, lower=False)[:, 0]
        swaps = jnp.sum(pivots != jnp.arange(6, dtype=pivots.dtype))
        sign = jnp.prod(jnp.sign(U.reshape(-1)[::7])) * (1 - 2 * (swaps % 2))
        return x, delta, sign, jnp.max(jnp.abs(r)), iterations, jnp.asarray(True)

    zero = jnp.zeros((), guess.dtype)
    carry = (guess, jnp.zeros_like(guess), zero, zero, jnp.asarray(0, jnp.int32), False)
    x, _, sign, norm, iterations, _ = jax.lax.while_loop(cond, body, carry)
    return x, iterations, norm, sign


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def _at_root(chart, x, m, A):
    """`x`, a root of the DEP residual for `(m, A)`, with the derivative of the root as a
    function of `(m, A)` (as `_implicit._at_root`): the implicit function theorem,
    `dξ = −J⁻¹(∂r/∂m dm + ∂r/∂A dA)`, `J` in closed form (`_residual_and_jacobian`).
    A `custom_jvp`, traced only when differentiated (`jax.lax.custom_root` linearises the
    residual whenever it is traced: it was a third of the step's tracing time)."""
    return x


@_at_root.defjvp
def _at_root_jvp(chart, primals, tangents):
    # Linear in the tangents with coefficients from the primal point, so JAX transposes
    # it for reverse mode (`jnp.linalg.solve` is transposable).
    x, m, A = primals
    _, dm, dA = tangents
    _, dr = jax.jvp(lambda mm, AA: _residual(chart, x, mm, AA), (m, A), (dm, dA))
    _, J = _residual_and_jacobian(chart, x, m, A)
    return x, -jnp.linalg.solve(J, dr)


def dense_solve(chart, max_steps: int, m, A, Ainv, tolerance):
    """The DEP equation of one body solved from the explicit-Euler guess `h M⁻¹ m`
    (`DEP.solve_increment`'s), not differentiated: `(ξ, iterations, ‖r‖_∞,
    off_branch)`. A diverged solve hands back the finite guess: the implicit derivative is
    then evaluated at a finite point, so a failed step whose output is masked contributes
    0, not NaN, to a gradient."""
    guess = Ainv @ m
    root, iterations, norm, sign = _newton(chart, m, A, guess, tolerance, max_steps)
    root = jnp.where(jnp.all(jnp.isfinite(root)) & jnp.isfinite(norm), root, guess)
    # `DEP.on_branch`'s rule: `det J` of the sign of `det A > 0` (either sign of `h`, six
    # dimensions), and for the exp chart a rotation angle below π.
    off = ~(sign > 0) | chart.beyond_branch(jnp.sum(root[:3] ** 2), math.pi)
    return root, iterations, norm, off


def _increment(chart, m, A, Ainv, tolerance, solve):
    """The DEP equation of one body solved by `solve` (`dense_solve`'s signature):
    `(ξ, iterations, ‖r‖_∞, converged, off_branch)`, `ξ` differentiable in `m` and
    `A = M/h` by the implicit function theorem (`_at_root`), not through the loop."""
    root, iterations, norm, off = solve(*jax.lax.stop_gradient((m, A, Ainv, tolerance)))
    # Tagged before `_at_root`, whose derivative rule reads it: the backward pass of a
    # `jax.checkpoint`-ed step finds the root stored (`_implicit.differentiable_root`).
    root = checkpoint_name(root, ROOT_NAME)
    return _at_root(chart, root, m, A), iterations, norm, norm <= tolerance, off


def _increment_map(chart, x):
    """`F = φ(ξ)` as `(R_F, t_F)`, by the power series of `_se3.increment` (no library
    trigonometry): `R_F = 1 + α ω̂ + β(ωωᵀ − t)`, with exp `α = sin θ/θ`,
    `β = (1 − cos θ)/θ²`, `t_F = v + β ω×v + γ(ω(ω·v) − t v)`, `γ = (θ − sin θ)/θ³`;
    Cayley `α = 4/(4 + t)`, `β = α/2`, `t_F = (v + R_F v)/2` (`lievi.SE3.exp`, `cay`)."""
    w, v = x[:3], x[3:]
    t, wv = w @ jnp.stack([w, v]).T
    if chart == "exp":
        S, C = horner(S_SERIES, t / 4), horner(C_SERIES, t / 4)
        alpha, beta = S * C, S * S / 2
        gamma = horner(SINC3, t)
    else:
        alpha = 4 / (4 + t)
        beta = alpha / 2
    eye = np.eye(3, dtype=x.dtype)
    RF = (1 - beta * t) * eye + alpha * _hat(w) + beta * jnp.outer(w, w)
    if chart == "exp":
        tF = v + beta * jnp.cross(w, v) + gamma * (w * wv - t * v)
    else:
        tF = (v + RF @ v) / 2
    return RF, tF


def dense_step(chart, g, m, A, Ainv, tolerance, solve):
    """One DEP + DLP + reconstruction step of one body: `g` the top rows `[R | p]` of the
    pose `(3, 4)`, `m` `(6,)`, `A = M/h`, `Ainv = h M⁻¹` `(6, 6)`. Returns `(g_next,
    m_next, result, iterations, residual)`; differentiable in `g`, `m`, `A`."""
    x, iterations, norm, converged, off_branch = _increment(chart, m, A, Ainv, tolerance, solve)
    RF, tF = _increment_map(chart, x)
    # g F (2.9): `R R_F` re-orthonormalised by one Newton–Schulz step, `R ← R − R(RᵀR − 1)/2`
    # (as `lievi.SE3.compose`), and `p + R t_F`.
    R, p = g[:, :3], g[:, 3]
    Rn = R @ RF
    Rn = Rn - Rn @ (Rn.T @ Rn - np.eye(3, dtype=Rn.dtype)) / 2
    g_next = jnp.concatenate([Rn, (p + R @ tF)[:, None]], axis=1)
    # Ad_Fᵀ m = (R_Fᵀ(Π + P × t_F), R_Fᵀ P) (3.3).
    Pi, P = m[:3], m[3:]
    m_next = (jnp.stack([Pi + jnp.cross(P, tF), P], axis=1).T @ RF).reshape(6)
    result = jnp.where(converged, RESULTS.successful, RESULTS.newton_not_converged)
    result = jnp.where(off_branch, RESULTS.step_too_large, result)
    ok = jnp.isfinite(norm) & jnp.all(jnp.isfinite(m_next))
    result = jnp.where(ok, result, RESULTS.nonfinite)
    return g_next, m_next, result.astype(jnp.int32), iterations, norm


class SE3DenseKernel(SE3Kernel):
    """`DEP`'s step (either chart) for `RigidBodySE3` without a potential, as whole-array
    operations (`dense_step`): the step `SE3NewtonKernel.one_body` runs for one body.

    Its state is `SE3Kernel`'s components (the 12 entries of `[R | p]`, the 6 of `m`), each
    kept as one array, `(12, B)` and `(6, B)` (`carried`, `carried_momentum`), which the
    step reshapes to a pose and a momentum per body: as 18 arrays `(B,)`, the step's
    results were split into 18 arrays and joined again at the next step, each split and
    join a compiled kernel of its own (the eager block's program had 101 of them, and 4×
    the SO(3) step's compile time). Its constants are `M` and `M⁻¹` as `(…, 6, 6)` arrays.
    """

    chart: str = eqx.field(static=True)
    rtol: float | None = eqx.field(static=True)
    atol: float | None = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    # The batch kernel (`_se3.SE3NewtonKernel`): under `jax.vmap` (e.g. of `simulate`) its
    # solve runs the bodies (`solve_bodies`), as `simulate_batch` would.
    batch: Any = None

    def carried(self, g0):
        # (B, 4, 4) → the 12 entries of `[R | p]`, row-major, `(12, B)`.
        return jnp.moveaxis(g0[:, :3].reshape(g0.shape[0], 12), 0, -1)

    def carried_momentum(self, m0):
        return jnp.moveaxis(m0, 0, -1)

    def constants(self, tensor):
        # M⁻¹ (the Newton guess and the step bound) is not differentiated. By Cholesky
        # (`M` is positive definite, `RigidBodySE3.parameter_conditions`): no pivots, whose
        # permutation `jnp.linalg.inv` applies in a loop of its own.
        factor = jax.scipy.linalg.cho_factor(jax.lax.stop_gradient(tensor))
        # A batch of systems (`(B, 6, 6)`, e.g. `Tuning(fast=False)`'s bodies) solves each.
        eye = jnp.broadcast_to(np.eye(6, dtype=factor[0].dtype), jnp.shape(tensor))
        return tensor, jax.scipy.linalg.cho_solve(factor, eye)

    def turn_rates(self, constants, h):
        # |h| times the rotation rows of M⁻¹, `(3, 6, …)` as `turn_squared` reads them.
        Minv = constants[1][..., :3, :]
        return component_major(jnp.abs(jnp.asarray(h))[..., None, None] * Minv)

    def prepare(self, constants, h):
        M, Minv = constants
        h = jnp.asarray(h)[..., None, None]
        return M / h, h * Minv

    def step(self, params, g, m, alive):
        # `g` `(12, …)`, `m` `(6, …)` (`carried`, `carried_momentum`) → `(…, 3, 4)`, `(…, 6)`.
        A, Ainv = params
        shape = jnp.shape(m)[1:]
        m = jnp.moveaxis(m, 0, -1)
        g = jnp.moveaxis(g, 0, -1).reshape(shape + (3, 4))
        # A failed body (`alive` false) takes no Newton iteration: its tolerance is ∞.
        tolerance = newton_tolerance(jnp.max(jnp.abs(m), -1), m.dtype, self.rtol, self.atol)
        tolerance = jnp.where(alive, tolerance, jnp.inf)

        def one(g, m, A, Ainv, tolerance):
            return dense_step(self.chart, g, m, A, Ainv, tolerance, self._solve)

        args = (g, m, A, Ainv, tolerance)
        cores = ((3, 4), (6,), (6, 6), (6, 6), ())
        batch = jnp.broadcast_shapes(
            *(jnp.shape(y)[: jnp.ndim(y) - len(c)] for y, c in zip(args, cores))
        )
        if math.prod(batch) == 1:
            # One body: called as is, not under `jax.vmap`, whose batched loop predicate
            # and batched LU made the program compile 10–20 % longer.
            outputs = one(*(jnp.reshape(y, c) for y, c in zip(args, cores)))
            outputs = jax.tree.map(lambda y: jnp.reshape(y, batch + jnp.shape(y)), outputs)
        else:
            signature = "(3,4),(6),(6,6),(6,6),()->(3,4),(6),(),(),()"
            outputs = jnp.vectorize(one, signature=signature)(*args)
        g_next, m_next, *info = outputs
        g_next = jnp.moveaxis(g_next.reshape(batch + (12,)), -1, 0)
        return (g_next, jnp.moveaxis(m_next, -1, 0), *info)

    def _solve(self, m, A, Ainv, tolerance):
        """`dense_solve` for one body; under `jax.vmap` the batch kernel's solve on the
        vmapped bodies (`bodies_batched`): batched, the whole-array Newton loop ran at a
        fifth of the body-steps/s of the structure-of-arrays one (`jax.vmap(simulate)`,
        64 bodies)."""
        args = (tuple(m[i] for i in range(6)), entries(A), entries(Ainv), tolerance)
        return bodies_batched(self._solve_bodies)(*args)

    def _solve_bodies(self, m, A, Ainv, tolerance):
        if self.batch is None or all(jnp.ndim(x) == 0 for x in jax.tree.leaves((m, A, tolerance))):
            return dense_solve(
                self.chart, self.max_steps, jnp.stack(m), matrix(A), matrix(Ainv), tolerance
            )
        return self.batch.solve_bodies(m, A, Ainv, tolerance)
