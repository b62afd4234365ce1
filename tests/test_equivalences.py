"""The paper's equivalence theorems for the rigid body (docs/theory/checks.md#equivalences).

- Theorem 5.1: the DEP algorithm (5.4), an algorithm on G only, and the Moser–Veselov
  algorithm (5.6) on G and so(n)* give the same iterates. The DEP side is built here
  generically, from `MoserVeselov.discrete_lagrangian` alone: the discrete Legendre
  transform for the first step, then the discrete Euler–Lagrange equations solved for
  `g_{k+1}` by autodiff and Newton — nothing of the integrator's own solve is reused.
- Lewis–Simo (5.7) on SO(3) with `F = cay(x)`: `hΠ_k = 2 skew(F Λ)` becomes the closed
  3-vector equation `h (1 + |x|²/4) Π_k = I x + ½ x × (I x)`.
- Hairer–Vilmart's DMV with `D = diag(d)`, `d₁ + d₂ = I₃` etc.: `h ŷ_n = Ω D − D Ωᵀ` with
  `Ω` the rotation of a unit quaternion `(r₀, r)`, i.e. `h y = 2 (r₀ I r + r × I r)`.

Each is iterated on its own and compared with `lievi.MoserVeselov` to 1e-12 (float64).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_generalized_body

MV = lievi.MoserVeselov()
NEWTON_ITERATIONS = 12  # quadratic convergence from an O(h²) guess: ≥ 2× what is needed
STEPS = 40


def _newton(residual, x):
    def body(_, x):
        return x - jnp.linalg.solve(jax.jacfwd(residual)(x), residual(x))

    x = jax.lax.fori_loop(0, NEWTON_ITERATIONS, body, x)
    return x, jnp.max(jnp.abs(residual(x)))


# --------------------------------------------------------------------- Theorem 5.1 (DEP)


def _del_residual(system, integrator, h, g_prev, g, g_next):
    """`d/dη [L_d(g_{k−1}, g cay(η)) + L_d(g cay(η), g_{k+1})]` at η = 0 (Theorem 2.1).

    Any curve through `g` with velocity `g η̂` gives the same derivative; `cay` compiles
    faster than `exp` on SO(n).
    """
    group = system.group

    def action(eta):
        moved = g @ group.cay(eta)
        return integrator.discrete_lagrangian(
            system, g_prev, moved, h
        ) + integrator.discrete_lagrangian(system, moved, g_next, h)

    return jax.grad(action)(jnp.zeros(group.algebra_dim, g.dtype))


def dep_on_group(system, integrator, g0, m0, h, n_steps):
    """Iterates of the DEP/DEL algorithm on G only, from `L_d` by autodiff + Newton.

    First `g₁ = g₀ cay(x)` with `−D₁L_d(g₀, g₁) = m₀` (discrete Legendre transform), then
    `g_{k+1} = g_k cay(x)` with the DEL residual zero, from the guess `x` = previous
    increment. Returns `(g (n_steps + 1, n, n), worst Newton residual)`.
    """
    group = system.group

    def legendre_residual(x):
        return integrator.momentum_from_configurations(system, g0, g0 @ group.cay(x), h) - m0

    x0, worst = _newton(legendre_residual, h * system.velocity(m0))
    g1 = g0 @ group.cay(x0)

    def step(carry, _):
        g_prev, g, x = carry
        x, residual = _newton(
            lambda x: _del_residual(system, integrator, h, g_prev, g, g @ group.cay(x)), x
        )
        g_next = g @ group.cay(x)
        return (g, g_next, x), (g_next, residual)

    _, (gs, residuals) = jax.lax.scan(step, (g0, g1, x0), None, length=n_steps - 1)
    g = jnp.concatenate([g0[None], g1[None], gs])
    return g, jnp.maximum(worst, jnp.max(residuals))


@pytest.mark.parametrize("case", ["hlw", pytest.param("so4", marks=pytest.mark.slow)])
def test_theorem_5_1_dep_equals_moser_veselov(case):
    if case == "hlw":
        body, g0, m0 = hlw_problem()
        h = 0.1
    else:
        body, g0, m0 = random_generalized_body(np.random.default_rng(4), 4)
        h = 0.05
    sol = lievi.simulate(body, MV, g0, m0, h=h, n_steps=STEPS)
    g, residual = jax.jit(dep_on_group, static_argnums=(1, 5))(body, MV, g0, m0, h, STEPS)
    assert residual <= 1e-13
    np.testing.assert_allclose(g, sol.g, rtol=0, atol=ROUNDOFF)
    # The DLP momenta (5.5) are the discrete Legendre transforms of the DEP trajectory.
    momenta = jax.vmap(lambda a, b: MV.momentum_from_configurations(body, a, b, h))(g[:-1], g[1:])
    np.testing.assert_allclose(momenta, sol.m[:-1], rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("n", [3, pytest.param(4, marks=pytest.mark.extended)])  # 4: 6 s
def test_moser_veselov_iterates_satisfy_5_4(n):
    """(5.4) itself, `fᵀ_{k+1,k}Λ − Λf_{k+1,k} = Λfᵀ_{k,k−1} − f_{k,k−1}Λ`, with
    `f_{k+1,k} = g_{k+1}ᵀ g_k`, and (5.6₂) `M_{k+1} = Π_k = ωᵀΛ − Λω` scaled by h."""
    body, g0, m0 = random_generalized_body(np.random.default_rng(n), n)
    h = 0.05
    sol = lievi.simulate(body, MV, g0, m0, h=h, n_steps=STEPS)
    Lambda = jnp.diag(body.Lambda)
    f = jnp.swapaxes(sol.g[1:], -1, -2) @ sol.g[:-1]  # f_{k+1,k}, k = 0 … STEPS−1
    ft = jnp.swapaxes(f, -1, -2)
    lhs = ft[1:] @ Lambda - Lambda @ f[1:]
    rhs = Lambda @ ft[:-1] - f[:-1] @ Lambda
    np.testing.assert_allclose(lhs, rhs, rtol=0, atol=ROUNDOFF)
    momentum = ft @ Lambda - Lambda @ f  # ω_{k+1}ᵀΛ − Λω_{k+1} = hΠ̂_k
    np.testing.assert_allclose(momentum, h * body.group.hat(sol.m[:-1]), rtol=0, atol=ROUNDOFF)


# --------------------------------------------------------------------- Lewis–Simo (5.7)


def _cayley_matrix(x):
    """`cay(x) = I + 4/(4 + |x|²) (x̂ + x̂²/2)`, written out (not `lievi.SO3.cay`)."""
    X = jnp.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])
    return jnp.eye(3) + 4 / (4 + x @ x) * (X + X @ X / 2)


@jax.jit
def lewis_simo(inertia, g0, m0, h):
    def step(carry, _):
        g, m = carry

        def residual(x):
            return h * (1 + x @ x / 4) * m - (inertia * x + jnp.cross(x, inertia * x) / 2)

        x, res = _newton(residual, h * m / inertia)
        F = _cayley_matrix(x)  # f_{k+1,k} = Fᵀ
        g, m = g @ F, F.T @ m  # (5.7₁), (5.7₂): Π̂_{k+1} = Fᵀ Π̂_k F, i.e. Π_{k+1} = FᵀΠ_k
        return (g, m), (g, m, res)

    _, (g, m, res) = jax.lax.scan(step, (g0, m0), None, length=STEPS)
    return g, m, jnp.max(res)


# --------------------------------------------------------------------- Hairer–Vilmart DMV


def _quaternion_matrix(q):
    """Rotation matrix of the unit quaternion `(r₀, r)`: `I + 2r₀r̂ + 2r̂²`."""
    r0, r = q[0], q[1:]
    R = jnp.array([[0.0, -r[2], r[1]], [r[2], 0.0, -r[0]], [-r[1], r[0], 0.0]])
    return jnp.eye(3) + 2 * r0 * R + 2 * R @ R


@jax.jit
def hairer_vilmart_dmv(inertia, g0, y0, h):
    """DMV as in Hairer–Vilmart (2006): `D = diag(d)`, `d₁ + d₂ = I₃`, `d₁ + d₃ = I₂`,
    `d₂ + d₃ = I₁`; `h ŷ_n = Ω D − D Ωᵀ`, `y_{n+1} = Ωᵀ y_n`, `Q_{n+1} = Q_n Ω`."""
    d = jnp.sum(inertia) / 2 - inertia
    D = jnp.diag(d)

    def step(carry, _):
        Q, y = carry

        def residual(q):
            Omega = _quaternion_matrix(q)
            A = Omega @ D - D @ Omega.T
            return jnp.append(jnp.array([A[2, 1], A[0, 2], A[1, 0]]) - h * y, q @ q - 1)

        guess = jnp.concatenate([jnp.ones(1), h * y / (2 * inertia)])
        q, res = _newton(residual, guess)
        Omega = _quaternion_matrix(q)
        Q, y = Q @ Omega, Omega.T @ y
        return (Q, y), (Q, y, res)

    _, (Q, y, res) = jax.lax.scan(step, (g0, y0), None, length=STEPS)
    return Q, y, jnp.max(res)


@pytest.mark.parametrize("form", ["lewis-simo", "hairer-vilmart"])
@pytest.mark.parametrize("problem", ["hlw", "hv-body", "water-molecule"])
def test_closed_forms_equal_moser_veselov(form, problem):
    if problem == "hlw":
        body, g0, m0 = hlw_problem()
    else:
        moments = (0.6, 0.8, 1.0) if problem == "hv-body" else (0.345, 0.653, 1.0)
        body, g0, m0 = lievi.RigidBody(jnp.array(moments)), jnp.eye(3), jnp.array([1.8, 0.4, -0.9])
    h = 0.1
    sol = lievi.simulate(body, MV, g0, m0, h=h, n_steps=STEPS)
    integrate = lewis_simo if form == "lewis-simo" else hairer_vilmart_dmv
    g, m, residual = integrate(body.inertia, g0, m0, h)
    assert residual <= 1e-13
    np.testing.assert_allclose(g, sol.g[1:], rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(m, sol.m[1:], rtol=0, atol=ROUNDOFF)
