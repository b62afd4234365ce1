"""The helpers built around `simulate` on systems of several bodies (`lievi.RigidBodies`,
`lievi.RigidRotors`) and on batches of them: `suggest_integrator`, `fit_system`,
`solve_optimal_control`, the Poisson and DEL diagnostics, and `simulate_batch`'s inference
of a batch of systems built with `jax.vmap`.

Decided by checks that do not depend on the helpers' own code: the suggested step's
error against a run at a quarter of it; the fitted masses against the ones that made the
data; the optimal controls' trajectory at the target; the DEL residual and the Poisson
defect at round-off, and a perturbed trajectory far from it; a batch of systems against
each system alone. Float64, two bodies, a few steps each.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF
from lievi import diagnostics as dg

SE3, SO3 = lievi.SE3, lievi.SO3
INERTIA = jnp.array([[1.0, 2.0, 3.0], [2.0, 2.5, 3.0]])
MASS = jnp.array([1.0, 2.0])


def spring(g):
    """A spring between the two centres of mass: a coupling of the relative poses."""
    return 0.5 * jnp.sum((SE3.translation(g[0]) - SE3.translation(g[1])) ** 2)


def bodies_state():
    rotations = SO3.exp(jnp.array([[0.1, -0.2, 0.3], [0.4, 0.1, -0.2]]))
    g0 = SE3.from_rotation_translation(rotations, jnp.array([[0.0, 0.0, 0.0], [1.5, 0.2, 0.0]]))
    m0 = jnp.array([[0.3, -0.2, 0.5, 0.1, 0.2, 0.0], [-0.1, 0.4, 0.2, 0.0, -0.3, 0.1]])
    return g0, m0


def rotors_state():
    g0 = SO3.exp(jnp.array([[0.2, 0.0, -0.1], [0.0, 0.3, 0.1]]))
    m0 = jnp.array([[0.5, -0.3, 0.8], [0.2, 0.6, -0.4]])
    return g0, m0


@pytest.mark.extended  # four pilot compilations of a coupled SE(3) run
def test_suggest_integrator_on_rigid_bodies_with_a_position_tolerance():
    """Per-body speeds set the pilot's step (no `float` of an array), and `tolerance_on`
    bounds the error of the positions alone: the suggested run is within 3× the
    tolerance of a run at a quarter of its step (Richardson, the pilot's own estimate)."""
    system = lievi.RigidBodies(INERTIA, MASS, potential=spring)
    g0, m0 = bodies_state()
    tolerance, horizon = 1e-5, 2.0
    s = lievi.suggest_integrator(
        system,
        g0,
        m0,
        horizon=horizon,
        tolerance=tolerance,
        candidates=(lievi.DEP(),),
        batch=2,
        tolerance_on="position",
    )
    assert s.n_steps * s.h == pytest.approx(horizon, rel=1e-12)
    assert s.predicted_error <= tolerance * (1 + 1e-9)
    coarse = lievi.simulate(system, s.integrator, g0, m0, h=s.h, n_steps=s.n_steps)
    fine = lievi.simulate(system, s.integrator, g0, m0, h=s.h / 4, n_steps=4 * s.n_steps)
    error = np.linalg.norm(SE3.translation(coarse.g[-1]) - SE3.translation(fine.g[-1]))
    assert 0 < error <= 3 * tolerance, (error, s.table)


def test_suggest_integrator_tolerance_on_is_checked():
    system = lievi.RigidRotors(INERTIA)
    g0, m0 = rotors_state()
    with pytest.raises(ValueError, match="tolerance_on='position'.*no such part"):
        lievi.suggest_integrator(
            system, g0, m0, horizon=1.0, tolerance=1e-6, tolerance_on="position"
        )
    with pytest.raises(ValueError, match="`tolerance_on` must be one of"):
        lievi.suggest_integrator(system, g0, m0, horizon=1.0, tolerance=1e-6, tolerance_on="x")
    with pytest.raises(ValueError, match="`g0` must have shape"):
        lievi.suggest_integrator(system, g0[None], m0[None], horizon=1.0, tolerance=1e-6)


def test_poisson_defect_on_several_bodies():
    """The DLP map of the product group is Poisson for the block-diagonal structure; a
    map that scales the momentum is not."""
    rotors = lievi.RigidRotors(INERTIA)
    g0, m0 = rotors_state()
    B = dg.lie_poisson_tensor(rotors, m0)
    assert B.shape == (6, 6)
    np.testing.assert_allclose(B[3:, 3:], dg.lie_poisson_tensor(lievi.RigidBody(INERTIA[1]), m0[1]))
    np.testing.assert_allclose(B[:3, 3:], 0.0)
    assert dg.poisson_defect(rotors, lievi.DEP(), g0, m0, 0.1) <= ROUNDOFF
    assert dg.poisson_defect(rotors, Scaled(), g0, m0, 0.1) > 1e-4


class Scaled(lievi.DEP):
    """Not Poisson: the DEP step with the momenta rescaled."""

    def step(self, system, g, m, h):
        g1, m1, info = super().step(system, g, m, h)
        return g1, 1.01 * m1, info


@pytest.mark.extended  # the Jacobian of a step of two SE(3) bodies: a long compilation
def test_poisson_defect_moser_veselov_on_rigid_bodies():
    bodies = lievi.RigidBodies(INERTIA, MASS)
    g0, m0 = bodies_state()
    assert dg.poisson_defect(bodies, lievi.MoserVeselov(), g0, m0, 0.1) <= ROUNDOFF


def test_del_residual_moser_veselov_on_rigid_bodies():
    """`simulate` runs Moser–Veselov on each body (its rotation; the drift exactly): the
    trajectory is a critical point of the sum of the bodies' discrete Lagrangians and the
    spring's trapezoid, and moving one pose off it shows."""
    system = lievi.RigidBodies(INERTIA, MASS, potential=spring)
    g0, m0 = bodies_state()
    h = 0.1
    sol = lievi.simulate(system, lievi.MoserVeselov(), g0, m0, h=h, n_steps=6, save=lievi.Save())
    residual = dg.del_residual(system, lievi.MoserVeselov(), sol.g, h)
    assert residual.shape == (5, 2, 6)
    assert float(jnp.max(jnp.abs(residual))) <= ROUNDOFF
    moved = sol.g.at[3, 1].set(SE3.compose(sol.g[3, 1], SE3.exp(jnp.full(6, 1e-4))))
    off = dg.del_residual(system, lievi.MoserVeselov(), moved, h)
    assert float(jnp.max(jnp.abs(off))) > 1e-6


def test_del_residual_refuses_a_batch():
    system = lievi.RigidRotors(INERTIA)
    g = jnp.broadcast_to(jnp.eye(3), (4, 3, 2, 3, 3))
    with pytest.raises(ValueError, match=r"one trajectory of shape \(T, 2, 3, 3\)"):
        dg.del_residual(system, lievi.DEP(), g, 0.1)


@pytest.mark.parametrize("batch", [pytest.param(2, marks=pytest.mark.extended), 3])
def test_simulate_batch_infers_a_vmapped_batch_of_rotors(batch):
    """`jax.vmap(RigidRotors)` of `(B, N, 3)` moments is a batch of `B` systems (its
    energy of one state sums to a scalar, but its velocity is not one state's)."""
    scale = jnp.arange(1.0, batch + 1.0)[:, None, None]
    systems = jax.vmap(lievi.RigidRotors)(scale * INERTIA)
    g0, m0 = rotors_state()
    gs, ms = jnp.stack([g0] * batch), jnp.stack([m0] * batch)
    sol = lievi.simulate_batch(
        systems, lievi.DEP(), gs, ms, h=0.1, n_steps=3, save=lievi.Save(every=3)
    )
    for b in range(batch):
        alone = lievi.simulate(
            lievi.RigidRotors(scale[b] * INERTIA), lievi.DEP(), g0, m0, h=0.1, n_steps=3
        )
        np.testing.assert_allclose(sol.m[b, -1], alone.m[-1], rtol=0, atol=1e-13)
        np.testing.assert_allclose(sol.g[b, -1], alone.g[-1], rtol=0, atol=1e-13)


@pytest.mark.extended  # compiles the solver (about 15 s)
def test_optimal_control_on_several_bodies():
    """The controls have `Control`'s per-body shape `(n_steps, N, d)`, as `u0` and as the
    result. Two free spheres (`J = j 1`), each turned rest to rest about its own axis: the
    discrete optimum costs the sum of the bodies' closed forms `12 j² θ²/T³ (1 + 1/(N² − 1))`
    (docs/optimal-control.md), and the trajectory ends at rest at the targets."""
    j = jnp.array([1.0, 2.0])
    system = lievi.RigidRotors(j[:, None] * jnp.ones(3))
    rotations = jnp.array([[0.3, 0.0, 0.0], [0.0, 0.1, -0.2]])
    target = (SO3.exp(rotations), jnp.zeros((2, 3)))
    n, T = 8, 2.0
    u0 = jnp.asarray(0.1 * np.random.default_rng(0).normal(size=(n, 2, 3)))
    g0 = jnp.broadcast_to(jnp.eye(3), (2, 3, 3))
    r = lievi.solve_optimal_control(
        system, lievi.DEP(), g0, jnp.zeros((2, 3)), target, n, T / n, u0=u0
    )
    assert r.controls.shape == (n, 2, 3)
    assert r.converged and r.constraint_violation <= 1e-12
    theta2 = jnp.sum(rotations**2, axis=-1)
    optimum = float(jnp.sum(12 * j**2 * theta2 / T**3)) * (1 + 1 / (n**2 - 1))
    assert r.cost == pytest.approx(optimum, rel=1e-9)
    np.testing.assert_allclose(r.solution.g[-1], target[0], rtol=0, atol=1e-11)
    np.testing.assert_allclose(r.solution.m[-1], 0.0, rtol=0, atol=1e-11)
    with pytest.raises(ValueError, match=r"`u0` must have shape .*\(8, 2, 3\)"):
        lievi.solve_optimal_control(
            system, lievi.DEP(), g0, jnp.zeros((2, 3)), target, n, T / n, u0=u0[:, 0]
        )


@pytest.mark.extended  # compiles a fit (about 20 s)
def test_fit_system_on_rigid_bodies_reads_samples_as_samples():
    """Observed poses `(S, N, 4, 4)` of two bodies: the masses that made them are
    recovered from a wrong guess, and a batch of two such records fits each."""
    truth = lievi.RigidBodies(INERTIA, MASS, potential=spring)
    g0, m0 = bodies_state()
    h, every, samples = 0.1, 2, 6
    sol = lievi.simulate(
        truth, lievi.DEP(), g0, m0, h=h, n_steps=every * (samples - 1), save=lievi.Save(every=every)
    )
    assert sol.g.shape == (samples, 2, 4, 4)
    guess = lievi.RigidBodies(INERTIA, 1.3 * MASS, potential=spring)
    fit = lievi.fit_system(
        guess, sol.g, h=h, sample_every=every, params=lambda s: s.mass, g0=g0, m0=m0
    )
    assert fit.converged, fit.reason
    np.testing.assert_allclose(fit.system.mass, MASS, rtol=1e-7)
    assert fit.m0.shape == (2, 6)
