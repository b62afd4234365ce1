"""The implicit equations of a step on SO(3) with principal moments, as structure of
arrays: `DEP`'s (4.8) in the exp or Cayley chart and `MoserVeselov`'s (5.4)–(5.6), each an
object owning its closed-form residual and Jacobian (derived in `_so3.py`'s docstring),
its Newton start, the increment of its root and its branch rule. `_so3.py` solves them.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp

from .._groups._charts import AbstractChart
from ._soa import C_SERIES, P_SERIES, S_SERIES, cross, dot, horner, horner_with_derivative, solve3


def _residual_moser_veselov(x, m, A, with_jacobian: bool):
    """`r = I x/h − Π − ½ Π×x − ¼ (x·Π) x` and its Jacobian `A − ½Π̂ − ¼((x·Π)1 + xΠᵀ)`.

    `MoserVeselov`'s residual `J(X)/h − vee((1 − X/2) Π̂ (1 + X/2))` on SO(3) written out
    (`vee([Π̂, X̂]) = Π×x`, `vee(X̂Π̂X̂) = −(x·Π)x`); `F = cay(x)`.
    """
    px = cross(m, x)
    d = dot(x, m)
    r = tuple(A[i] * x[i] - m[i] - px[i] / 2 - d * x[i] / 4 for i in range(3))
    if not with_jacobian:
        return r, None
    P = (0, -m[2], m[1], m[2], 0, -m[0], -m[1], m[0], 0)
    rows = []
    for i in range(3):
        row = []
        for j in range(3):
            entry = -P[3 * i + j] / 2 - x[i] * m[j] / 4
            if i == j:
                entry = entry + A[i] - d / 4
            row.append(entry)
        rows.append(tuple(row))
    return r, tuple(rows)


def _dep_residual(chart, xi, m, A, with_jacobian: bool):
    """`r = dφ⁻¹(ξ)ᵀ Aξ − Π` and its Jacobian, for the exp or Cayley chart (derivation above)."""
    w = tuple(A[i] * xi[i] for i in range(3))
    d = dot(xi, w)
    t = dot(xi, xi)
    xw = cross(xi, w)
    if chart == "exp":
        u = t / 4
        if with_jacobian:
            S, dS = horner_with_derivative(S_SERIES, u)
            P, dP = horner_with_derivative(P_SERIES, u)
            dc = (dP * S - P * dS) / (16 * S * S)
        else:
            S, P = horner(S_SERIES, u), horner(P_SERIES, u)
        c = P / (4 * S)
        v = tuple(xi[i] * d - t * w[i] for i in range(3))
        r = tuple(w[i] + xw[i] / 2 + c * v[i] - m[i] for i in range(3))
    else:
        r = tuple(w[i] + xw[i] / 2 + xi[i] * d / 4 - m[i] for i in range(3))
    if not with_jacobian:
        return r, None

    def hat(x, i, j):
        return (0, -x[2], x[1], x[2], 0, -x[0], -x[1], x[0], 0)[3 * i + j]

    rows = []
    for i in range(3):
        row = []
        for j in range(3):
            entry = (hat(xi, i, j) * A[j] - hat(w, i, j)) / 2
            if chart == "exp":
                diagonal = (d - t * A[i]) if i == j else 0
                entry = (
                    entry
                    + 2 * dc * v[i] * xi[j]
                    + c * (diagonal + 2 * xi[i] * w[j] - 2 * w[i] * xi[j])
                )
            else:
                diagonal = d if i == j else 0
                entry = entry + (diagonal + 2 * xi[i] * w[j]) / 4
            if i == j:
                entry = entry + A[i]
            row.append(entry)
        rows.append(tuple(row))
    return r, tuple(rows)


def explicit_euler_guess(m, A):
    """The Newton start `h·I⁻¹Π = Π/A`, as `DEP.solve_increment` and `MoserVeselov`'s."""
    return tuple(m[i] / A[i] for i in range(3))


def iterate(step, x, iterations: int, rolled: bool):
    """`step` applied `iterations` times to `x`: written out, or `rolled` into one
    `fori_loop` (the same operations in the same order, so the same iterates)."""
    if rolled and iterations > 1:
        return jax.lax.fori_loop(0, iterations, lambda _, x: step(x), x)
    for _ in range(iterations):
        x = step(x)
    return x


def _moser_veselov_by_scalar_newton(m, A, iterations: int):
    """The Moser–Veselov increment `x` from a scalar Newton iteration (a quartic in `s`).

    With `s = x·Π` fixed, the residual `A x − Π − ½ Π×x − ¼ s x` is *linear* in `x`:
    `M(s) x = Π` with `M(s) = D(s) − ½Π̂`, `D(s) = diag(Aᵢ − s/4)`. So the three-dimensional
    equation reduces to the scalar one `s = Πᵀ M(s)⁻¹ Π`. Writing `dᵢ = Aᵢ − s/4` and
    `(i, j, k)` cyclic, `M`'s determinant and adjugate are (checked with sympy)

        det M = d₁d₂d₃ + ¼ Σ dᵢΠᵢ²,
        (adj M · Π)ᵢ = Πᵢ (dⱼdₖ + ¼|Π|²) + ½ ΠⱼΠₖ (Aⱼ − Aₖ),
        Πᵀ adj M Π = Σ dⱼdₖ Πᵢ² + ¼|Π|⁴,

    and `f(s) = s det M(s) − Πᵀ adj M(s) Π` is a quartic. Newton on `f` from the
    explicit-Euler value `s₀ = Σ Πᵢ²/Aᵢ` (the `x·Π` of the guess `x₀ = Π/A` of the
    three-dimensional Newton, O(h²) from the root) costs about 40 operations an iteration
    against about 150 for a Newton step in `x`; then `x = adj M Π / det M`. The caller
    checks the residual of the original equation, so a body for which this lands on
    another root or does not converge is caught there and continues in `x`.
    """
    p2 = tuple(p * p for p in m)
    norm2 = p2[0] + p2[1] + p2[2]
    quarter = norm2 / 4
    s = p2[0] / A[0] + p2[1] / A[1] + p2[2] / A[2]

    def minors(s):
        """`(d, (d₂d₃, d₃d₁, d₁d₂), det M(s))`."""
        d = tuple(a - s / 4 for a in A)
        dd = (d[1] * d[2], d[2] * d[0], d[0] * d[1])
        return d, dd, d[0] * dd[0] + (d[0] * p2[0] + d[1] * p2[1] + d[2] * p2[2]) / 4

    def newton(s):
        d, dd, det = minors(s)
        quadratic = dd[0] * p2[0] + dd[1] * p2[1] + dd[2] * p2[2] + quarter * norm2
        d_det = -(dd[0] + dd[1] + dd[2]) / 4 - norm2 / 16
        d_quadratic = -((d[1] + d[2]) * p2[0] + (d[2] + d[0]) * p2[1] + (d[0] + d[1]) * p2[2]) / 4
        f = s * det - quadratic
        return s - f / (det + s * d_det - d_quadratic)

    # In a loop for one body and for a batch: written out, its divisions were recomputed
    # in fusions of their own (ns per body-step, 4096 random bodies at h = 0.1, one core:
    # 55 written out, 46 rolled; one body 1120, 1080).
    s = iterate(newton, s, iterations, rolled=True)
    _, dd, det = minors(s)
    inverse_det = 1 / det
    return tuple(
        (
            m[i] * (dd[i] + quarter)
            + m[(i + 1) % 3] * m[(i + 2) % 3] * (A[(i + 1) % 3] - A[(i + 2) % 3]) / 2
        )
        * inverse_det
        for i in range(3)
    )


def moser_veselov_on_branch(x, m, A):
    """`MoserVeselov.on_branch` in closed form: the symmetric part of the Jacobian,
    `B = A − ¼(x·Π)1 − ⅛(xΠᵀ + Πxᵀ)`, is positive definite (Sylvester's criterion)."""
    s = dot(x, m)
    # Times sign(h) (the sign of `A = I/h`): a negative step, e.g. an inner stage of
    # `Composition`, has `J ≈ A` negative definite on its branch.
    sign = jnp.sign(A[0])
    b = [[-sign * (x[i] * m[j] + m[i] * x[j]) / 8 for j in range(3)] for i in range(3)]
    for i in range(3):
        b[i][i] = b[i][i] + sign * (A[i] - s / 4)
    minor2 = b[0][0] * b[1][1] - b[0][1] * b[1][0]
    det = (
        b[0][0] * (b[1][1] * b[2][2] - b[1][2] * b[2][1])
        - b[0][1] * (b[1][0] * b[2][2] - b[1][2] * b[2][0])
        + b[0][2] * (b[1][0] * b[2][1] - b[1][1] * b[2][0])
    )
    return (b[0][0] > 0) & (minor2 > 0) & (det > 0)


# Newton iterations every body takes before the one convergence check, per chart. From
# the explicit-Euler guess (O(h²) off the root) three quadratic steps reach 64 ulps for
# nearly every body at |ξ| = h|Ω| ≲ 0.3; the Cayley-chart DEP needs a fourth for a few
# bodies in 10⁴ (h = 0.1, the random bodies of `benchmarks/throughput.py`), and as one
# such body sends the whole batch into the tail, four fixed iterations are faster there
# (measured). Moser–Veselov's fixed iterations are scalar Newton steps on a quartic
# (`_moser_veselov_by_scalar_newton`, ~40 operations each): four reach 64 ulps for every
# one of 10⁵ such bodies. Bodies that need more continue in a `while_loop` up to
# `max_steps`.


class AbstractSO3Equation(eqx.Module):
    """The implicit equation of a step on SO(3) with principal moments, and what goes with
    it: its closed-form residual and Jacobian, the Newton start, the increment
    `F = 1 + a ξ̂ + b ξ̂²` of its root, and its branch rule."""

    @abc.abstractmethod
    def fixed_iterations(self) -> int:
        """Newton iterations every body takes before the convergence check (see above)."""

    def restartable(self) -> bool:
        """Whether a body left off the branch by `start` restarts from the explicit-Euler
        guess in the tail (default: no)."""
        return False

    @abc.abstractmethod
    def residual(self, xi, m, A, with_jacobian: bool):
        """`(r, ∂r/∂ξ)` (the Jacobian `None` without `with_jacobian`)."""

    def solve(self, J, r):
        """`J⁻¹r` by Cramer's rule (the Newton step and the implicit derivative)."""
        return solve3(J, r)

    @abc.abstractmethod
    def start(self, m, A, iterations: int):
        """The iterate after `iterations` fixed Newton steps from the start."""

    @abc.abstractmethod
    def increment_coefficients(self, t):
        """`(a, b)` of `F = 1 + a ξ̂ + b ξ̂²` at `t = |ξ|²`."""

    @abc.abstractmethod
    def off_branch(self, xi, m, A, t, converged):
        """Whether the iterate `ξ` is not on the branch continued from `h → 0` (reported
        `step_too_large`); the same rule as the integrator's generic step."""


class DEPEquation(AbstractSO3Equation):
    """`DEP`'s equation `dφ⁻¹(ξ)ᵀ Iξ/h = Π` (4.8) in the chart `chart`."""

    chart: AbstractChart = eqx.field(static=True)

    def fixed_iterations(self) -> int:
        return _DEP_FIXED_ITERATIONS[self.chart.name]

    def residual(self, xi, m, A, with_jacobian: bool):
        return _dep_residual(self.chart, xi, m, A, with_jacobian)

    def start(self, m, A, iterations: int):
        def newton(xi):
            r, J = self.residual(xi, m, A, True)
            delta = solve3(J, r)
            return tuple(xi[i] - delta[i] for i in range(3))

        # Written out for a batch, where XLA fuses across the iterations; in a loop for one
        # body (every component a scalar: `simulate`, and each lane of `jax.vmap` of it),
        # whose step written out was slower than a test after every iteration. Measured
        # (ns per body-step, random bodies at h = 0.1, one core; exp, then Cayley): 4096
        # bodies 105, 76 written out and 107, 81 rolled; one body 1600, 1190 written out,
        # 1250, 1040 with no fixed iterations and a test after each, 1130, 960 rolled.
        one_body = all(jnp.size(p) <= 1 for p in m)
        return iterate(newton, explicit_euler_guess(m, A), iterations, rolled=one_body)

    def increment_coefficients(self, t):
        if self.chart == "exp":
            u = t / 4
            S, C = horner(S_SERIES, u), horner(C_SERIES, u)
            return S * C, S * S / 2
        a = 4 / (4 + t)
        return a, a / 2

    def off_branch(self, xi, m, A, t, converged):
        # `DEP.on_branch`: `det J` of the sign of `det A` (the branch continued from h → 0
        # has not crossed a fold), and the chart's own rule.
        _, J = self.residual(xi, m, A, True)
        (a, b, c), (d, e, f), (g, h, i) = J
        det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
        folded = ~(det * (A[0] * A[1] * A[2]) > 0)
        return folded | self.chart.beyond_branch(t, math.pi)


class MoserVeselovEquation(AbstractSO3Equation):
    """`MoserVeselov`'s equation (5.4)–(5.6) in Cayley coordinates (`F = cay(x)`)."""

    def fixed_iterations(self) -> int:
        return 4

    def restartable(self) -> bool:
        return True

    def residual(self, xi, m, A, with_jacobian: bool):
        return _residual_moser_veselov(xi, m, A, with_jacobian)

    def start(self, m, A, iterations: int):
        return _moser_veselov_by_scalar_newton(m, A, iterations)

    def increment_coefficients(self, t):
        a = 4 / (4 + t)
        return a, a / 2

    def off_branch(self, xi, m, A, t, converged):
        return converged & ~moser_veselov_on_branch(xi, m, A)


_DEP_FIXED_ITERATIONS = {"exp": 3, "cayley": 4}
