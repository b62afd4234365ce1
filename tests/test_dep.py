"""The DEP/DLP integrator against the checks of docs/theory/checks.md (float64).

DEL residual by autodiff (Theorem 2.1 / 2.3), the right/left mirror, conservation of
Casimirs and spatial momentum (§3, §6), the Poisson property (Proposition 3.1), and
starting from two configurations (§2).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import (
    INTEGRATOR_IDS,
    INTEGRATORS,
    INTEGRATORS_EXP_EXTENDED,
    ROUNDOFF,
    hlw_problem,
    random_generalized_body,
)
from lievi import diagnostics as dg


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 11 s
def test_del_residual_hlw(integrator):
    body, g0, m0 = hlw_problem()
    h = 0.1
    sol = lievi.simulate(body, integrator, g0, m0, h=h, n_steps=100)
    residual = dg.del_residual(body, integrator, sol.g, h)
    assert residual.shape == (99, 3)
    assert jnp.max(jnp.abs(residual)) <= ROUNDOFF * jnp.max(jnp.abs(m0))


@pytest.mark.parametrize(
    "n",
    [
        pytest.param(4, marks=pytest.mark.extended),  # 18 s (exp), 9 s (cayley)
        pytest.param(5, marks=pytest.mark.slow),
    ],
)
@pytest.mark.parametrize("integrator", INTEGRATORS, ids=INTEGRATOR_IDS)
def test_del_residual_generalized_rigid_body(integrator, n):
    body, g0, m0 = random_generalized_body(np.random.default_rng(n), n)
    h = 0.05
    sol = lievi.simulate(body, integrator, g0, m0, h=h, n_steps=100)
    residual = dg.del_residual(body, integrator, sol.g, h)
    assert jnp.max(jnp.abs(residual)) <= ROUNDOFF * jnp.max(jnp.abs(m0))


def _skewed_lagrangian(xi):
    # Not even in ξ, so a sign error between the left and right forms cannot cancel.
    inertia = jnp.array([2.0, 1.0, 2.0 / 3.0])
    return 0.5 * jnp.dot(xi, inertia * xi) + 0.3 * xi[0] * xi[1] * xi[2] + 0.1 * xi[0] ** 3


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 10 s
def test_right_invariant_is_mirrored_left_invariant(integrator):
    """Right run of (g, μ) under l = left run of (g⁻¹, −μ) under l̃(ξ) = l(−ξ) (docs/theory/conventions.md)."""
    _, g0, m0 = hlw_problem()
    g0 = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.5]))
    m0 = 0.5 * m0
    right = lievi.LieLagrangian(lievi.SO3, _skewed_lagrangian, side="right")
    left = lievi.LieLagrangian(lievi.SO3, lambda xi: _skewed_lagrangian(-xi), side="left")
    h = 0.1
    sol_r = lievi.simulate(right, integrator, g0, m0, h=h, n_steps=50)
    sol_l = lievi.simulate(left, integrator, g0.T, -m0, h=h, n_steps=50)
    np.testing.assert_allclose(jnp.swapaxes(sol_r.g, -1, -2), sol_l.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(sol_r.m, -sol_l.m, rtol=0, atol=ROUNDOFF)
    # And the right-invariant run is itself variational.
    assert jnp.max(jnp.abs(dg.del_residual(right, integrator, sol_r.g, h))) <= ROUNDOFF


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 11 s
def test_generic_lagrangian_matches_rigid_body(integrator):
    body, g0, m0 = hlw_problem()
    generic = lievi.LieLagrangian(lievi.SO3, body.lagrangian)
    a = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=30)
    b = lievi.simulate(generic, integrator, g0, m0, h=0.1, n_steps=30)
    np.testing.assert_allclose(a.g, b.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(a.m, b.m, rtol=0, atol=ROUNDOFF)


@pytest.mark.extended  # 10 s
def test_son3_generalized_body_matches_rigid_body():
    """Λ ↦ (Λ₂+Λ₃, Λ₁+Λ₃, Λ₁+Λ₂) maps the generalized body on SO(3) to the rigid body."""
    Lambda = jnp.array([0.2, 0.9, 1.3])
    inertia = jnp.array([Lambda[1] + Lambda[2], Lambda[0] + Lambda[2], Lambda[0] + Lambda[1]])
    _, g0, m0 = hlw_problem()
    integrator = lievi.DEP()
    a = lievi.simulate(lievi.RigidBody(inertia), integrator, g0, m0, h=0.1, n_steps=30)
    b = lievi.simulate(lievi.GeneralizedRigidBody(Lambda), integrator, g0, m0, h=0.1, n_steps=30)
    np.testing.assert_allclose(a.g, b.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(a.m, b.m, rtol=0, atol=ROUNDOFF)


def test_full_inertia_tensor_is_a_change_of_body_frame():
    """With I = Q diag(I) Qᵀ the motion is the principal-axes motion seen in a rotated frame."""
    body, g0, m0 = hlw_problem()
    Q = lievi.SO3.exp(jnp.array([0.4, 0.1, -0.7]))
    tensor = lievi.RigidBody(Q @ jnp.diag(body.inertia) @ Q.T)
    integrator = lievi.DEP()
    a = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=30)
    b = lievi.simulate(tensor, integrator, g0 @ Q.T, Q @ m0, h=0.1, n_steps=30)
    np.testing.assert_allclose(b.g, a.g @ Q.T, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(b.m, a.m @ Q.T, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 14 s
def test_start_from_two_configurations(integrator):
    """Paper §2: the discrete trajectory through (g0, g1) is the one with m0 = −D₁L_d(g0, g1)."""
    body, g0, m0 = hlw_problem()
    h = 0.1
    a = lievi.simulate(body, integrator, g0, m0, h=h, n_steps=20)
    b = lievi.simulate(body, integrator, g0, h=h, n_steps=20, g1=a.g[1])
    np.testing.assert_allclose(b.m[0], m0, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(b.g, a.g, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("integrator", INTEGRATORS, ids=INTEGRATOR_IDS)
def test_conservation_over_1e4_steps(integrator):
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=10_000, save=lievi.Save(every=10))
    assert sol.result == lievi.RESULTS.successful
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.spatial_momentum(body, sol.g, sol.m)) <= ROUNDOFF
    assert jnp.max(dg.orthogonality_defect(body, sol.g)) <= ROUNDOFF


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 13 s
def test_conservation_generalized_rigid_body(integrator):
    body, g0, m0 = random_generalized_body(np.random.default_rng(7), 5)
    sol = lievi.simulate(body, integrator, g0, m0, h=0.05, n_steps=2000, save=lievi.Save(every=10))
    assert sol.result == lievi.RESULTS.successful
    assert dg.casimirs(body, sol.m).shape == (201, 2)  # tr Π̂², tr Π̂⁴
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.spatial_momentum(body, sol.g, sol.m)) <= ROUNDOFF


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 20 s
def test_dlp_map_is_poisson(integrator):
    """Proposition 3.1: D B(Π_k) Dᵀ = B(Π_{k+1}) for the Jacobian D of Π_k ↦ Π_{k+1}."""
    body, g0, m0 = hlw_problem()
    for m in (m0, jnp.array([0.3, -1.2, 0.8])):
        assert dg.poisson_defect(body, integrator, g0, m, 0.1) <= ROUNDOFF
    gen, g0n, m0n = random_generalized_body(np.random.default_rng(3), 4)
    assert dg.poisson_defect(gen, integrator, g0n, m0n, 0.05) <= ROUNDOFF


def test_poisson_defect_detects_a_non_poisson_map():
    """The check can fail: a map that rescales momentum is not Poisson."""

    class Scaled(lievi.DEP):
        def step(self, system, g, m, h):
            g1, m1, info = super().step(system, g, m, h)
            return g1, 1.01 * m1, info

    body, g0, m0 = hlw_problem()
    assert dg.poisson_defect(body, Scaled(), g0, m0, 0.1) > 1e-4


@pytest.mark.parametrize("integrator", INTEGRATORS_EXP_EXTENDED)  # dep-exp: 14 s
def test_batched_equals_per_body(integrator):
    rng = np.random.default_rng(11)
    inertias = jnp.asarray(rng.uniform(0.5, 2.0, size=(4, 3)))
    momenta = jnp.asarray(rng.normal(size=(4, 3)))

    def run(inertia, m0):
        sol = lievi.simulate(
            lievi.RigidBody(inertia), integrator, jnp.eye(3), m0, h=0.1, n_steps=20, throw=False
        )
        return sol.g, sol.m, sol.result

    gs, ms, results = jax.vmap(run)(inertias, momenta)
    for k in range(4):
        g, m, r = run(inertias[k], momenta[k])
        np.testing.assert_allclose(gs[k], g, rtol=0, atol=ROUNDOFF)
        np.testing.assert_allclose(ms[k], m, rtol=0, atol=ROUNDOFF)
        assert results[k] == r == lievi.RESULTS.successful


def test_implicit_derivative_matches_finite_differences():
    """The Newton solve differentiates by the implicit function theorem (custom_root)."""
    body, g0, m0 = hlw_problem()

    def final_momentum(m):
        return lievi.simulate(body, lievi.DEP(), g0, m, h=0.1, n_steps=10).m[-1]

    jac = jax.jacfwd(final_momentum)(m0)
    jac_rev = jax.jacrev(final_momentum)(m0)
    eps = 1e-6
    fd = jnp.stack(
        [
            (final_momentum(m0 + eps * e) - final_momentum(m0 - eps * e)) / (2 * eps)
            for e in jnp.eye(3)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(jac, fd, rtol=0, atol=1e-8)
    np.testing.assert_allclose(jac, jac_rev, rtol=0, atol=1e-12)


@pytest.mark.extended  # 50 s
def test_generalized_rigid_body_increments_that_need_scaling():
    """SO(4), exp chart, steps long enough that `dexp(ξ) = φ₁(ad_ξ)` scales `ad_ξ` and
    doubles back (the branch of `lievi._groups._expm` that a short step skips): the DEL
    residual is at round-off, and the implicit derivative (reverse mode through the masked
    doubling loop) equals central differences."""
    body, g0, m0 = random_generalized_body(np.random.default_rng(7), 4)
    h, n_steps = 1.0, 6
    group = body.group
    xi = jax.jit(lambda m: lievi.DEP().solve_increment(body, m, h)[0])(m0)
    # ‖ad_ξ‖_∞ above twice the Taylor polynomial's 1/2: at least two doublings.
    assert jnp.max(jnp.sum(jnp.abs(group.ad(xi)), -1)) > 1.0
    sol = lievi.simulate(body, lievi.DEP(), g0, m0, h=h, n_steps=n_steps)
    assert jnp.all(sol.result == lievi.RESULTS.successful)
    residual = dg.del_residual(body, lievi.DEP(), sol.g, h)
    assert jnp.max(jnp.abs(residual)) <= ROUNDOFF * jnp.max(jnp.abs(m0))

    @jax.jit
    def final_momentum(m):
        return lievi.simulate(body, lievi.DEP(), g0, m, h=h, n_steps=n_steps).m[-1]

    jac = jax.jacrev(final_momentum)(m0)
    eps = 1e-6
    steps = eps * jnp.eye(6)
    fd = (jax.vmap(final_momentum)(m0 + steps) - jax.vmap(final_momentum)(m0 - steps)).T / (2 * eps)
    np.testing.assert_allclose(jac, fd, rtol=0, atol=1e-7 * jnp.max(jnp.abs(fd)))
