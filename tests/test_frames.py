"""The frame convention (`g` maps body to world) and the `Solution` helpers built on it:
`angular_velocity(system, frame=...)` and `spatial_momentum(system)`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_generalized_body


@pytest.mark.extended  # 9 s
def test_angular_velocity_matches_the_motion_of_g():
    """Central differences of the computed attitudes: `gᵀġ = Ω̂` (body), `ġgᵀ = ω̂` (world)."""
    body, g0, m0 = hlw_problem()
    h = 1e-3
    sol = lievi.simulate(body, lievi.DEP(), g0, m0, h=h, n_steps=200)
    omega_body = sol.angular_velocity(body)
    omega_world = sol.angular_velocity(body, frame="spatial")
    np.testing.assert_allclose(omega_body, sol.m / body.inertia, rtol=1e-14)
    np.testing.assert_allclose(omega_world, jnp.einsum("tab,tb->ta", sol.g, omega_body), atol=1e-14)
    gdot = (sol.g[2:] - sol.g[:-2]) / (2 * h)
    g = sol.g[1:-1]
    body_fd = lievi.SO3.vee(jnp.swapaxes(g, -1, -2) @ gdot)
    world_fd = lievi.SO3.vee(gdot @ jnp.swapaxes(g, -1, -2))
    # Second-order differences and a second-order method: O(h²) ≈ 1e-6 here.
    np.testing.assert_allclose(body_fd, omega_body[1:-1], atol=1e-5)
    np.testing.assert_allclose(world_fd, omega_world[1:-1], atol=1e-5)
    # ... and the other assignment of frames is visibly wrong (the test can fail).
    assert jnp.max(jnp.abs(body_fd - omega_world[1:-1])) > 1e-2


def test_spatial_momentum_is_g_pi_and_conserved():
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, lievi.MoserVeselov(), g0, m0, h=0.1, n_steps=300)
    pi = sol.spatial_momentum(body)
    np.testing.assert_allclose(pi, jnp.einsum("tab,tb->ta", sol.g, sol.m), atol=1e-15)
    np.testing.assert_allclose(
        pi, lievi.diagnostics.spatial_momentum(body, sol.g, sol.m), atol=1e-15
    )
    assert lievi.diagnostics.relative_drift(pi) < ROUNDOFF


def test_generalized_body_and_batches():
    body, g0, m0 = random_generalized_body(np.random.default_rng(3), 4)
    sol = lievi.simulate(body, lievi.LiePoissonSplitting(), g0, m0, h=0.05, n_steps=100)
    assert lievi.diagnostics.relative_drift(sol.spatial_momentum(body)) < ROUNDOFF
    # spatial velocity ω̂ = g ξ̂ gᵀ on SO(n)
    xi = sol.angular_velocity(body)
    world = sol.angular_velocity(body, frame="spatial")
    G = lievi.SOn(4)
    np.testing.assert_allclose(
        G.hat(world), sol.g @ G.hat(xi) @ jnp.swapaxes(sol.g, -1, -2), atol=1e-13
    )
    # A batched Solution (as from `jax.vmap(simulate)`) keeps its batch axis.
    batch = jax.tree.map(lambda x: jnp.stack([x, x]), sol)
    assert batch.angular_velocity(body, frame="spatial").shape == (2, 101, 6)
    np.testing.assert_allclose(
        batch.spatial_momentum(body)[1], sol.spatial_momentum(body), atol=1e-15
    )


def test_right_invariant_system_carries_spatial_momentum():
    """A right-invariant system carries the spatial momentum `μ`; the momentum its symmetry
    conserves is the body momentum `Ad_gᵀμ`, which `Solution.spatial_momentum` returns (the
    same quantity as `diagnostics.spatial_momentum`), kept to round-off."""
    left, g0, m0 = hlw_problem()
    right = lievi.LieLagrangian(lievi.SO3, left.lagrangian, side="right")
    sol = lievi.simulate(right, lievi.DEP(), g0, m0, h=0.1, n_steps=20)
    conserved = sol.spatial_momentum(right)
    np.testing.assert_allclose(
        conserved, lievi.diagnostics.spatial_momentum(right, sol.g, sol.m), rtol=0, atol=1e-15
    )
    np.testing.assert_allclose(conserved, conserved[:1].repeat(len(conserved), 0), atol=1e-13)
    assert np.abs(sol.m - sol.m[:1]).max() > 1e-2  # μ itself moves
    body_velocity = sol.angular_velocity(right, frame="body")
    np.testing.assert_allclose(
        body_velocity,
        jnp.einsum("tba,tb->ta", sol.g, sol.angular_velocity(right, "spatial")),
        atol=1e-12,
    )


def test_bad_frame():
    body, g0, m0 = hlw_problem()
    sol = lievi.Solution(jnp.zeros(1), g0[None], m0[None], jnp.array(0), {})
    with pytest.raises(ValueError, match="`frame`"):
        sol.angular_velocity(body, frame="world")
