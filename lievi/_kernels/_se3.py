"""A fast batched DEP step for the free rigid body on SE(3) (paper (4.8), (3.3), (2.9)).

The SE(3) counterpart of `_kernels/_so3.py`, for `RigidBodySE3` with any symmetric positive
definite 6×6 kinetic tensor `M` (Kirchhoff's body in a fluid, or `diag(J, m1)` in vacuum)
and no potential, written for throughput over many bodies:

- **structure of arrays**: the pose's top 3×4 block `[R | p]` is 12 arrays, the momentum
  `m = (Π, P)` 6, each of shape `(B,)` with the batch minor, so that XLA emits long
  elementwise loops that it vectorises; the tensor's 36 entries are arrays `(B,)` when
  each body has its own, scalars when the batch shares one;
- **Newton in the rotation part**: the DEP equation `dφ⁻¹(ξ)ᵀ Mξ/h = m` (4.8) splits as
  `r_ω = K a + L b − Π`, `r_v = K′b − P` with `(a, b) = Mξ/h` (derivation below), and `r_v`
  is linear in `b`: for a given `ω`, `b = K′(ω)⁻¹P` in closed form and
  `v = A₂₂⁻¹(b − A₂₁ω)` (`A = M/h`). Newton runs on `ρ(ω) = r_ω(ω, v(ω))` with its 3×3
  Jacobian — the Schur complement of the 6×6 one (`reduced_residual`), solved by
  Cramer's rule — instead of on the 6×6 system: a 3×3 solve and fewer operations per
  iteration, and the root is the same (the generic path's, from the same explicit-Euler
  guess `h M⁻¹m`). The convergence check is on the full six-component residual, so a
  body reported converged satisfies the same test as on the generic path;
- **a Newton policy for batches**: a fixed number of iterations, the first a chord step
  (`_chord_step`: the Jacobian at `ω = 0` for the body's momentum in place of the
  Jacobian at the iterate: about half a Newton step's cost, and it saves one), one
  residual check, and a
  `while_loop` only for the bodies still above tolerance, up to `max_steps`, run on those
  bodies gathered into a small batch, in rounds when they are many (`compacted_tail`); a body that
  does not converge gets `RESULTS.newton_not_converged`;
- **implicit differentiation**: the converged root `ξ` passes through
  `_implicit.differentiable_root`, whose derivative is the implicit function theorem's `dξ = −J⁻¹(∂r/∂m dm + ∂r/∂A dA)` with the
  closed-form 6×6 Jacobian (`residual`) and a block solve with 3×3 Cramer inverses; the
  Newton iterations are not differentiated.

The derivation of the residual and its Jacobian is in `_se3_residual.py`; the reduced
residual (`v` eliminated) is `_se3_reduced.py`.

One body takes the same step written on whole arrays (`_se3_dense.py`, this kernel's
`one_body`): its program is a fraction of this one's, which a batch of thousands needs.

Then `F = φ(ξ)`, `m_{k+1} = Ad_Fᵀ m_k` (DLP (3.3)) and `g_{k+1} = g_k F` (2.9), the
rotation block re-orthonormalised by one Newton–Schulz step as `lievi.SE3.compose` does.
The tests compare the iterates and the gradients (with respect to `M`, `m_0`, `g_0`, `h`)
with the generic path, and the Jacobians with `jax.jacfwd`.

Values stored once (`materialise`) were chosen by counting the operations in the
compiled step and timing it (`benchmarks/se3_step_cost.py`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._groups._se3 import SE3
from .._newton import newton_tolerance
from .._results import RESULTS
from ._base import compacted_tail, materialise
from ._flat_batch import bodies_batched
from ._implicit import differentiable_root
from ._se3_dense import SE3DenseKernel
from ._se3_layout import SE3Kernel
from ._se3_reduced import reduced_residual, velocity_part
from ._se3_residual import (
    SINC3,
    SE3Equation,
    add_hat,
    mv,
    ones,
    residual,
)
from ._soa import (
    C_SERIES,
    S_SERIES,
    component_major,
    cramer_inverse,
    cross,
    det3,
    dot,
    entries,
    flat,
    horner,
    matrix,
    max_abs,
    nested,
    solve3,
)


def _chord_jacobian(chart, m, C):
    """`∂ρ/∂ω` at `ω = 0` for the body's momentum `m = (Π, P)`: the chord step's matrix.

    At `ω = 0` (`K = K′ = 1`, `L = v̂/2`, `q = P`, `Q = P̂/2`; `reduced_residual`), with
    `a₀ = ZP`, `v₀ = A₂₂⁻¹P`, `V₀ = A₂₂⁻¹P̂/2 − T`:

        Cayley: J₀ = S + ZP̂/2 − â₀/2 − P̂V₀/2,
        exp:    J₀ = (Cayley's) + (v₀Pᵀ + Pv₀ᵀ)/12 − (v₀·P)/6,

    the exp chart's extra terms from `E_ωω = c(v·b) + c vbᵀ − 2c bvᵀ − â/2` and `LQ =
    v̂P̂/4` at `c(0) = 1/12`. The terms in `P` are what the Schur complement `S` alone
    lacks: for a body whose translation per step is a sizable part of its radius of
    gyration they are several per cent of `J₀` (8 % for the lighter body of the binary
    asteroid of `benchmarks/compile_time.py`), and the chord step with `S` left the two
    Newton steps after it above the tolerance at about one step in eight with Cayley's
    chart (`tests/test_se3_batch.py`)."""
    S, Z, A22inv, T = C
    P = m[3:]
    a0, v0 = mv(Z, P), mv(A22inv, P)
    # Row i of `X P̂` is `X[i] × P` (`yᵀP̂ = (y × P)ᵀ`).
    ZP = tuple(cross(Z[i], P) for i in range(3))
    V0 = tuple(tuple(e / 2 - T[i][j] for j, e in enumerate(cross(A22inv[i], P))) for i in range(3))
    # Column j of `P̂V₀` is `P × V₀[:, j]`.
    PV = [cross(P, tuple(V0[k][j] for k in range(3))) for j in range(3)]
    J = tuple(tuple(S[i][j] + ZP[i][j] / 2 - PV[j][i] / 2 for j in range(3)) for i in range(3))
    J = add_hat(J, a0, -0.5)
    if chart == "exp":
        vP = dot(v0, P) / 6
        J = tuple(
            tuple(
                J[i][j] + (v0[i] * P[j] + P[i] * v0[j]) / 12 - (vP if i == j else 0)
                for j in range(3)
            )
            for i in range(3)
        )
    return J


def _chord_step(chart, w, m, C):
    """A simplified Newton step: `ω − J₀⁻¹ρ(ω)`, with `J₀ = ∂ρ/∂ω` at `ω = 0` for this
    body's momentum (`_chord_jacobian`: the Schur complement `A₁₁ − A₁₂A₂₂⁻¹A₂₁` and the
    terms of the translational momentum) in place of the Jacobian at `ω`. From the
    explicit-Euler guess (`O(h²)` off the root) it gains an order of `h` for the cost of a
    residual, about half a Newton step's: two Newton steps then reach the tolerance where
    three were needed (`DEFAULT_FIXED_ITERATIONS`)."""
    rho, _, _ = reduced_residual(chart, w, m, C, False)
    delta = solve3(_chord_jacobian(chart, m, C), rho)
    return tuple(w[i] - delta[i] for i in range(3))


def _newton_steps(chart, w, m, C, count: int):
    """`count` Newton steps from `w`, and `det(∂ρ/∂ω)` at the last iterate (the branch
    rule's, `_off_branch`): `count + 1` evaluations of `(ρ, J)`, the last for the rule.

    Written out, not a `fori_loop`: looped, the evaluation was compiled once and the SE(3)
    step compiled 1–3 s sooner, but it ran 10–20 % slower (batch and one body, exp chart
    and its composition; XLA fuses across the written-out iterations)."""
    for k in range(count + 1):
        rho, J, _ = reduced_residual(chart, w, m, C, True)
        if k < count:
            delta = solve3(J, rho, divide_each=True)
            w = tuple(w[i] - delta[i] for i in range(3))
    return w, det3(J)


def _full_residual(chart, w, m, A, C):
    """`(ξ, ‖r(ξ)‖_∞)` with `ξ = (ω, v(ω))` (`velocity_part`): the six-component check."""
    _, v = velocity_part(chart, w, m, C)
    x = tuple(w) + tuple(v)
    return x, max_abs(residual(chart, x, m, A, False)[0])


def _off_branch(chart, w, det, C):
    """`DEP.on_branch`'s rule, negated: `det J` not of the sign of `det A > 0` (the root was
    reached across a fold of the branch continued from `h → 0`), or the chart's own rule
    (exp: a rotation angle of π or more).

    `det J = det(∂r_v/∂v) det(∂ρ/∂ω)` (the Schur complement, `reduced_residual`), and
    `∂r_v/∂v = K′(ω)A₂₂` has the determinant sign of `h³` (`A₂₂ = M₂₂/h` with `M₂₂`
    positive definite, and `det K′ > 0` on the chart's branch), while `det A > 0` for
    either sign of `h` (6 dimensions): so the rule is `sign(h)·det(∂ρ/∂ω) > 0`, with
    `sign(h)` that of the Schur complement's `S₁₁` (`S = (M/M₂₂)/h`, `M/M₂₂` positive
    definite). Negative steps occur inside compositions (`lievi.Composition`).
    `det`: `det(∂ρ/∂ω)` at `ω = w` (`_newton_steps`).
    """
    S = C[0]
    return ~(det * S[0][0] > 0) | chart.beyond_branch(dot(w, w), math.pi)


def _stacked_residual(chart, x, m, A):
    """The DEP residual `dφ⁻¹(ξ)ᵀ Aξ − m` of one body (4.8), `x`, `m` of shape `(6,)` and
    `A = M/h` `(6, 6)`, with the chart's `dφ⁻¹` as `lievi.SE3` writes it: the generic
    path's residual (`DEP.residual`), as whole-array operations."""
    return chart.dinverse(SE3, x).T @ (A @ x) - m


def _residual_and_jacobian(chart, x, m, A):
    """`(r, ∂r/∂ξ)` for stacked bodies, `x`, `m` `(…, 6)` and `A` `(…, 6, 6)` (one
    shared by the batch, or one per body): `jax.jacfwd` of `_stacked_residual`, as the
    generic path differentiates it."""

    def one(x, m, A):
        residual = functools.partial(_stacked_residual, chart, m=m, A=A)
        return residual(x), jax.jacfwd(residual)(x)

    return jnp.vectorize(one, signature="(n),(n),(n,n)->(n),(n,n)")(x, m, A)


def _newton_tail(chart, max_steps, state, args):
    """The generic path's Newton, for the bodies of `state = (ξ, ‖r‖_∞, iterations,
    off_branch)` not yet on a root of the branch: each restarts from the explicit-Euler
    guess and takes up to `max_steps` Newton steps on the full 6×6 system, its residual
    and Jacobian those of the generic path (`_residual_and_jacobian`);
    `args = (m, A, guess, tolerance, alive)`.

    Why not more reduced steps: eliminating `v` makes `ρ(ω)` far more nonlinear than the
    six-component residual when the translation per step is large (`v(ω)` carries
    `K′(ω)⁻¹P`), and it rounds to about the tensor's condition number times the
    tolerance when `M` is ill-conditioned; there the reduced iteration diverges, stalls
    or lands on a root across a fold, where Newton on the full system converges in a few
    steps. Restarting from the guess with the generic path's iteration and budget, a body
    converges here whenever it converges there, to the same root.

    Why whole-array operations (`(…, 6)` and `(…, 6, 6)` arrays, a batched LU) and not
    the closed forms of the fixed iterations: the tail runs for a few bodies in ten
    thousand, so its speed hardly counts, while its code is compiled into every run;
    written entry by entry it was about 40 % of the SE(3) step's compile time.
    """
    m, A, guess, tolerance, alive = args
    x, norm, fixed, off_branch = state
    restart = alive & (~(norm <= tolerance) | off_branch)
    x = jnp.stack([jnp.where(restart, x0, y) for x0, y in zip(guess, x)], -1)
    m, A = jnp.stack(m, -1), matrix(A)

    def active(started, norm, iterations):
        going = (norm > tolerance) & jnp.isfinite(norm) & (iterations < max_steps)
        return restart & (~started | going)

    def cond(carry):
        *_, started, norm, iterations = carry
        return jnp.any(active(started, norm, iterations))

    def body(carry):
        # Each pass takes the step found in the previous one (none in the first, which
        # evaluates the guess), then evaluates `r` and `J` at the new iterate: the norm
        # for the test, the next step, and the sign of `det J` for the branch rule (from
        # `slogdet`: `det J` itself is a product of six factors of the size of `M/h`,
        # which can leave float32's range). One evaluation of `(r, J)` a pass.
        x, delta, sign, started, norm, iterations = carry
        on = active(started, norm, iterations)
        stepping = on & started
        x = jnp.where(stepping[..., None], x - delta, x)
        r, J = _residual_and_jacobian(chart, x, m, A)
        delta = jnp.linalg.solve(J, r[..., None])[..., 0]
        norm = jnp.where(on, jnp.max(jnp.abs(r), -1), norm)
        sign = jnp.where(on, jnp.linalg.slogdet(J)[0], sign)
        iterations = iterations + stepping.astype(jnp.int32)
        return x, delta, sign, jnp.asarray(True), norm, iterations

    zero = jnp.zeros_like(norm)
    carry = (x, jnp.zeros_like(x), zero, jnp.asarray(False), norm, jnp.zeros_like(fixed))
    x, _, sign, _, norm, iterations = jax.lax.while_loop(cond, body, carry)
    # `DEP.on_branch`'s rule on the 6×6 Jacobian, the generic path's: `det J > 0`, of
    # the sign of `det A > 0`.
    off = ~(sign > 0) | chart.beyond_branch(jnp.sum(x[..., :3] ** 2, -1), math.pi)
    off_branch = jnp.where(restart, off, off_branch)
    return tuple(x[..., i] for i in range(6)), norm, fixed + iterations, off_branch


def solve_increment(chart, m, A, C, guess, tolerance, fixed: int, max_steps: int, alive=True):
    """Newton for the DEP equation on a batch, on `ω` with `v` eliminated
    (`reduced_residual`): `fixed` iterations from the rotation part of `guess`, one check
    of the full residual `r(ω, v(ω))` and of the branch rule (`_off_branch`), then (only
    if some body needs it) the generic path's Newton from the guess for the bodies above
    `tolerance` or off the branch (`_newton_tail`). Returns `(ξ, iterations, residual
    ∞-norm, converged, off_branch)` per body. The first of the fixed iterations is a
    chord step (`_chord_step`). Not differentiable (see `_implicit.differentiable_root`)."""
    fixed = min(fixed, max_steps)
    w = guess[:3]
    if fixed > 0:
        w = _chord_step(chart, w, m, C)
    w, det = _newton_steps(chart, w, m, C, max(fixed - 1, 0))
    x, norm = _full_residual(chart, w, m, A, C)
    off_branch = _off_branch(chart, w, det, C)
    iterations = jnp.full(norm.shape, fixed, jnp.int32)
    if max_steps > fixed:
        x, norm, iterations, off_branch = compacted_tail(
            alive & (~(norm <= tolerance) | off_branch),
            functools.partial(_newton_tail, chart, max_steps),
            (x, norm, iterations, off_branch),
            (m, A, guess, tolerance, alive),
        )
    return x, iterations, norm, norm <= tolerance, off_branch


def increment(chart, w, v, one):
    """The increment `F = φ(ξ)` of `ξ = (ω, v)` in the chart (`lievi.SE3.exp` or `cay`) as
    `(R_F, t_F)`, 3×3 nested and 3 arrays, each entry stored once (`materialise`: read by
    every entry of `m_{k+1}` and `g_{k+1}`)."""
    t = dot(w, w)
    if chart == "exp":
        S, C = horner(S_SERIES, t / 4), horner(C_SERIES, t / 4)
        alpha, beta = S * C, S * S / 2  # sin θ/θ, (1 − cos θ)/θ²
        gamma = horner(SINC3, t)  # (θ − sin θ)/θ³
        wv, wwv = cross(w, v), dot(w, v)
        # tF = (1 + β ω̂ + γ ω̂²) v, ω̂² v = ω(ω·v) − t v.
        tF = tuple(v[i] + beta * wv[i] + gamma * (w[i] * wwv - t * v[i]) for i in range(3))
    else:
        alpha = 4 / (4 + t)
        beta = alpha / 2
    # RF = 1 + α ω̂ + β (ωωᵀ − t).
    W = ((0, -w[2], w[1]), (w[2], 0, -w[0]), (-w[1], w[0], 0))
    RF = tuple(
        tuple(
            alpha * W[i][j] + beta * w[i] * w[j] + ((1 - beta * t) if i == j else 0)
            for j in range(3)
        )
        for i in range(3)
    )
    if chart == "cayley":
        RFv = mv(RF, v)
        tF = tuple((v[i] + RFv[i]) / 2 for i in range(3))  # (1 − ω̂/2)⁻¹ v
    return nested(materialise(flat(RF), one)), materialise(tF, one)


def compose_increment(g, RF, tF, one):
    """`g F` (2.9) on the 12 entries of `[R | p]`: `R R_F`, re-orthonormalised by one
    Newton–Schulz step `R ← R − R(RᵀR − 1)/2` (as `lievi.SE3.compose`), and `p + R t_F`."""
    R = tuple(tuple(g[4 * i + j] for j in range(3)) for i in range(3))
    p = tuple(g[4 * i + 3] for i in range(3))
    Rn = tuple(tuple(sum(R[i][k] * RF[k][j] for k in range(3)) for j in range(3)) for i in range(3))
    Rn = nested(materialise(flat(Rn), one))
    G = tuple(
        tuple(sum(Rn[k][i] * Rn[k][j] for k in range(3)) - (1 if i == j else 0) for j in range(3))
        for i in range(3)
    )
    Rn = tuple(
        tuple(Rn[i][j] - sum(Rn[i][k] * G[k][j] for k in range(3)) / 2 for j in range(3))
        for i in range(3)
    )
    Rt = mv(R, tF)
    return tuple(e for i in range(3) for e in (Rn[i][0], Rn[i][1], Rn[i][2], Rt[i] + p[i]))


def dep_step(chart, g, m, A, Ainv, C, tolerance, fixed: int, max_steps: int, alive=True):
    """One DEP + DLP + reconstruction step on structure-of-arrays state.

    `g`: 12 arrays, the rows of `[R | p]`; `m`: 6; `A = M/h`, `Ainv = h M⁻¹`: 6×6 nested
    tuples of arrays or scalars. Returns `(g_next, m_next, result, iterations, residual)`;
    reverse-mode differentiable in `g`, `m`, `A`.
    """
    stopped = jax.lax.stop_gradient((m, A, Ainv, C, tolerance))
    sm, sA, sAinv, sC, stol = stopped
    # The explicit-Euler guess `h M⁻¹ m` (`DEP.solve_increment`'s).
    guess = tuple(sum(sAinv[i][j] * sm[j] for j in range(6)) for i in range(6))

    def solve(m, A, C, guess, tolerance, alive):
        return solve_increment(chart, m, A, C, guess, tolerance, fixed, max_steps, alive)

    x, iterations, norm, converged, off_branch = bodies_batched(solve)(
        sm, sA, sC, guess, stol, jnp.asarray(alive)
    )
    x = differentiable_root(SE3Equation(chart), x, guess, m, A)
    one = ones(m[0])
    # Stored once each (`materialise`): read by every entry of `F`, `m_{k+1}`, `g_{k+1}`.
    x = materialise(x, one)

    w, v = x[:3], x[3:]
    RF, tF = increment(chart, w, v, one)
    # Ad_Fᵀ m = (RFᵀ(Π + P × tF), RFᵀ P).
    Pi, P = m[:3], m[3:]
    Pt = cross(P, tF)
    y = tuple(Pi[i] + Pt[i] for i in range(3))
    m_next = tuple(sum(RF[k][i] * y[k] for k in range(3)) for i in range(3)) + tuple(
        sum(RF[k][i] * P[k] for k in range(3)) for i in range(3)
    )
    g_next = compose_increment(g, RF, tF, one)

    result = jnp.where(converged, RESULTS.successful, RESULTS.newton_not_converged)
    result = jnp.where(off_branch, RESULTS.step_too_large, result)
    ok = jnp.isfinite(norm)
    for y in m_next:
        ok = ok & jnp.isfinite(y)
    result = jnp.where(ok, result, RESULTS.nonfinite)
    return g_next, m_next, result.astype(jnp.int32), iterations, norm


# Iterations every body takes before the one convergence check (see
# `_so3.DEPEquation.fixed_iterations`): a chord step and two Newton steps. From the
# explicit-Euler guess they reach 64 ulps for every one of 2·10⁴ random free bodies
# (|ω| ≤ 0.3, speeds up to 3) over 5 steps of 0.05, 0.1 and 0.2, with either chart
# (`tests/test_se3_batch.py` runs 2000 of them at 0.2); with the momentum-free chord matrix, 19 of them (Cayley) and 2 (exp) needed the
# gathered tail at 0.1 and 1738 and 162 at 0.2. Measured with
# `benchmarks/se3_step_cost.py --one-thread` (with that matrix): 11–16 % less time a step
# than three Newton steps from the guess.
DEFAULT_FIXED_ITERATIONS = {"exp": 3, "cayley": 3}


class SE3NewtonKernel(SE3Kernel):
    """`DEP`'s step (either chart) for `RigidBodySE3` without a potential (`dep_step`).

    Its constants are the kinetic tensor's 36 entries (row-major); its state the 12
    entries of `[R | p]` and the 6 of `m = (Π, P)`.
    """

    chart: str = eqx.field(static=True)
    rtol: float | None = eqx.field(static=True)
    atol: float | None = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    fixed_iterations: int | None = eqx.field(default=None, static=True)

    def constants(self, tensor):
        # The 36 entries of M, and those of M⁻¹ (not differentiated: the Newton guess and
        # the step bound), one 6×6 inverse per body, once per run. A tensor shared by the
        # batch stays one set of scalars: broadcast inside the step's loops, 108 per-run
        # constants would otherwise be arrays `(B,)` read from memory at every step.
        inverse = jnp.linalg.inv(jax.lax.stop_gradient(tensor))
        return entries(tensor), entries(inverse)

    def prepare(self, constants, h):
        # Computed on `(…, 6, 6)` arrays, each product one operation on the whole matrix:
        # written entry by entry (as the step is), the few hundred scalar operations were
        # over a hundred kernels in XLA's program, each compiled on its own.
        M, Minv = (matrix(X) for X in constants)
        h = jnp.asarray(h)[..., None, None]
        A = M / h
        # What the reduced Newton iteration reads (`reduced_residual`, `_chord_jacobian`):
        # the Schur complement S = A₁₁ − A₁₂A₂₂⁻¹A₂₁, Z = A₁₂A₂₂⁻¹, A₂₂⁻¹ (Cramer),
        # T = A₂₂⁻¹A₂₁.
        # Not differentiated (Newton only; the root's derivative is `_implicit.differentiable_root`'s).
        blocks = jax.lax.stop_gradient(A)
        A11, A12 = blocks[..., :3, :3], blocks[..., :3, 3:]
        A21, A22 = blocks[..., 3:, :3], blocks[..., 3:, 3:]
        A22inv = cramer_inverse(A22)
        Z, T = A12 @ A22inv, A22inv @ A21
        S = A11 - Z @ A21
        C = tuple(component_major(X) for X in (S, Z, A22inv, T))
        return component_major(A), component_major(h * Minv), C

    def step(self, params, g, m, alive):
        # Nested tuples of `(B,)` arrays or scalars, as the step's code reads them (the
        # entries are slices, which fuse into the code that reads them).
        A, Ainv, C = jax.tree.map(lambda X: entries(X, component_major=True), params)
        fixed = self._fixed()
        tolerance = newton_tolerance(max_abs(m), m[0].dtype, self.rtol, self.atol)
        return dep_step(self.chart, g, m, A, Ainv, C, tolerance, fixed, self.max_steps, alive)

    def with_fixed_iterations(self, fixed_iterations: int):
        return dataclasses.replace(self, fixed_iterations=fixed_iterations)

    def one_body(self):
        # One body: the same step on whole arrays (`_se3_dense.py`), a program a fraction
        # of this one's size, so a one-body run's first call is mostly not compiling.
        return SE3DenseKernel(self.chart, self.rtol, self.atol, self.max_steps, self)

    def solve_bodies(self, m, A, Ainv, tolerance):
        """`_se3_dense.dense_solve`'s results for bodies given as structure of arrays (`m`:
        6 arrays `(B,)`, `A = M/h`, `Ainv = h M⁻¹`: 6×6 nested, arrays `(B,)` or scalars):
        this kernel's Newton (`solve_increment`) from the explicit-Euler guess, for the
        one-body step batched by `jax.vmap`. Not differentiated."""
        shape = jnp.broadcast_shapes(*(jnp.shape(x) for x in jax.tree.leaves((m, A, tolerance))))
        blocks = matrix(jax.tree.map(lambda x: jnp.broadcast_to(x, shape), A))
        A11, A12, A21, A22 = (
            blocks[..., :3, :3],
            blocks[..., :3, 3:],
            blocks[..., 3:, :3],
            blocks[..., 3:, 3:],
        )
        A22inv = cramer_inverse(A22)
        Z, T = A12 @ A22inv, A22inv @ A21
        C = tuple(entries(X) for X in (A11 - Z @ A21, Z, A22inv, T))
        guess = tuple(sum(Ainv[i][j] * m[j] for j in range(6)) for i in range(6))
        x, iterations, norm, _, off = solve_increment(
            self.chart, m, A, C, guess, tolerance, self._fixed(), self.max_steps, jnp.asarray(True)
        )
        finite = jnp.isfinite(norm)
        for y in x:
            finite = finite & jnp.isfinite(y)
        root = jnp.stack([jnp.where(finite, y, y0) for y, y0 in zip(x, guess)], -1)
        return root, iterations, norm, off

    def _fixed(self) -> int:
        """The fixed Newton iterations of a step: as set, or the default."""
        fixed = self.fixed_iterations
        return DEFAULT_FIXED_ITERATIONS[self.chart] if fixed is None else fixed
