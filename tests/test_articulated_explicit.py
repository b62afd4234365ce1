"""The explicit Lie-group methods (`lievi.RKMK4`, `lievi.RKMK8`) on articulated bodies: the
joints' reaction in the rate (index reduction) and the state projected back onto the
joints after each step (lievi/_systems/_joint_dynamics.py).

The joints at position and velocity level at every step, the order against the
independent Newton–Euler reference (tests/articulated_problems.py), batches, gradients,
float32 and a step too long for the projection.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from articulated_problems import (
    hinge_chain,
    joint_defects,
    reference_poses,
    reference_rhs,
    reference_state,
    satellite,
    triple_pendulum,
    velocity_defect,
)

import lievi
from helpers import dop853_final, final_state

JOINTS = 1e-12  # joints and velocity constraints, relative, at every step


@pytest.mark.parametrize(
    "problem, method, h",
    [
        (hinge_chain, lievi.RKMK4(), 0.01),
        pytest.param(satellite, lievi.RKMK8(), 0.05, marks=pytest.mark.extended),
    ],
    ids=["hinge-5-RKMK4", "satellite-RKMK8"],
)
def test_joints_hold_at_every_step(problem, method, h):
    """A fixed chain of hinges in gravity and a floating tree (a root with two children):
    both levels of the joints to round-off at every step, where the index-reduced
    equations alone would let them drift by the local error each step."""
    system, g0, m0 = problem()
    sol = lievi.simulate(system, method, g0, m0, h=h, n_steps=400)
    assert bool(jnp.all(sol.result == lievi.RESULTS.successful))
    joints, velocity = jnp.max(joint_defects(system, sol.g)), velocity_defect(system, sol.g, sol.m)
    assert float(joints) <= JOINTS
    assert float(velocity) <= JOINTS


@pytest.mark.extended
def test_floating_tree_momentum_error_is_the_methods():
    """Not a variational method: the total momentum of a floating tree is kept to the
    method's accuracy (`RKMK4`, h = 0.02: 7.5e-10 relative over 500 steps; bound 1e-8),
    not to round-off as by `lievi.RATTLE`."""
    system, g0, m0 = satellite()
    sol = lievi.simulate(system, lievi.RKMK4(), g0, m0, h=0.02, n_steps=500)
    total = lievi.diagnostics.total_momentum(system, sol.g, sol.m)
    drift = float(jnp.max(jnp.abs(total - total[0])) / jnp.max(jnp.abs(total[0])))
    assert drift <= 1e-8


def test_batch_is_each_run():
    """`simulate_batch` (the step under `jax.vmap`) gives each body's `simulate` run."""
    system, g0, m0 = hinge_chain(2)
    g = jnp.stack([g0, g0])
    m = jnp.stack([m0, 0.5 * m0])
    batch = lievi.simulate_batch(system, lievi.RKMK4(), g, m, h=0.01, n_steps=20)
    for k in range(2):
        one = lievi.simulate(system, lievi.RKMK4(), g[k], m[k], h=0.01, n_steps=20)
        np.testing.assert_allclose(batch.g[k], one.g, rtol=0, atol=1e-13)
        np.testing.assert_allclose(batch.m[k], one.m, rtol=0, atol=1e-13)


def test_projection_that_cannot_close_the_joints_is_reported():
    """From poses whose joint points are a link length apart (far beyond any step's local
    error) the projection's iteration does not reach round-off within its iterations: the
    step reports `newton_not_converged`, not a state that looks fine. (From 5 % apart it
    does reach it; a step too long for the method is refused before, by its step bound:
    `step_too_large`.)"""
    system, g0, m0 = triple_pendulum()
    apart = g0.at[1, :3, 3].add(system.length_scale())
    g, _, info = lievi.RKMK4().step(system, apart, m0, 0.01)
    assert int(info.result) == lievi.RESULTS.newton_not_converged
    assert float(system.joint_defect(g)) > 1e-12
    near = g0.at[1, :3, 3].add(0.05 * system.length_scale())
    g, _, info = lievi.RKMK4().step(system, near, m0, 0.01)
    assert int(info.result) == lievi.RESULTS.successful
    assert float(system.joint_defect(g)) <= JOINTS
    sol = lievi.simulate(system, lievi.RKMK4(), g0, m0, h=10.0, n_steps=3, throw=False)
    assert int(sol.result) == lievi.RESULTS.step_too_large


def test_float32_run_holds_the_joints():
    """In float32 the joints hold to round-off of float32 (64 ulps of the link length)."""
    system, g0, m0 = triple_pendulum()
    system = jax.tree.map(lambda x: x.astype(jnp.float32) if eqx.is_inexact_array(x) else x, system)
    g0, m0 = g0.astype(jnp.float32), m0.astype(jnp.float32)
    sol = lievi.simulate(system, lievi.RKMK4(), g0, m0, h=0.01, n_steps=200)
    assert sol.g.dtype == jnp.float32
    assert bool(jnp.all(sol.result == lievi.RESULTS.successful))
    joints, velocity = jnp.max(joint_defects(system, sol.g)), velocity_defect(system, sol.g, sol.m)
    assert float(joints) <= 64 * float(jnp.finfo(jnp.float32).eps) * 4
    assert float(velocity) <= 1e-5


@pytest.mark.extended
def test_gradient_matches_central_differences():
    """Through the stages, the reaction's solves and the projection's iterations: the
    final positions of a triple pendulum with respect to the link masses."""
    base, g0, m0 = triple_pendulum()

    def final(mass):
        system = lievi.ArticulatedBodies(
            base.inertia, mass, base.parents, base.joints, gravity=9.81
        )
        m = system.momentum(g0, jnp.array([[0.0, 0.5, 0.3], [0.8, 0.0, -0.4], [-0.3, 1.0, 0.5]]))
        g, _, _ = final_state(system, lievi.RKMK4(), g0, m, jnp.asarray(0.01), 20)
        return jnp.sum(g[:, :3, 3] * jnp.array([1.0, -0.5, 0.3]))

    grad = jax.grad(final)(base.mass)
    eps = 1e-6
    for index in range(3):
        plus, minus = base.mass.at[index].add(eps), base.mass.at[index].add(-eps)
        difference = (final(plus) - final(minus)) / (2 * eps)
        assert abs(float(grad[index]) - float(difference)) <= 1e-6 * abs(float(difference))


# ---- order against the Newton–Euler reference ---------------------------------------------


def _errors(problem, method, steps):
    system, g0, m0 = problem()
    T = 2.0
    R_ref, x_ref = reference_poses(
        system, dop853_final(reference_rhs(system), reference_state(system, g0, m0), T)
    )
    errors = []
    for h in steps:
        g, _, ok = final_state(system, method, g0, m0, jnp.asarray(h), jnp.asarray(round(T / h)))
        assert bool(ok)
        rotation = float(jnp.max(jnp.abs(g[:, :3, :3] - R_ref)))
        errors.append(max(rotation, float(jnp.max(jnp.abs(g[:, :3, 3] - x_ref)))))
    return np.array(errors)


@pytest.mark.extended
def test_rkmk4_order_four():
    """The projection keeps the tableau's order: 4.0 ± 0.1 on the 5-link hinge chain.
    (The triple pendulum's fast links are still pre-asymptotic there: its error ratios
    are 10.7, 12.7, 14.5 for h = 0.005 … 0.000625, rising towards 16.)"""
    steps = [0.005, 0.0025, 0.00125]
    order = np.polyfit(np.log(steps), np.log(_errors(hinge_chain, lievi.RKMK4(), steps)), 1)[0]
    assert abs(order - 4.0) <= 0.1


@pytest.mark.extended
@pytest.mark.parametrize("problem", [triple_pendulum, hinge_chain], ids=["triple-ball", "hinge-5"])
def test_rkmk8_order_eight(problem):
    """`RKMK8` halving the step from 0.04 to 0.02 divides the error by at least `2⁸`
    (pre-asymptotically more), and reaches 1e-8 at h = 0.02."""
    errors = _errors(problem, lievi.RKMK8(), [0.04, 0.02])
    assert np.log2(errors[0] / errors[1]) >= 8.0 - 0.1
    assert errors[1] <= 1e-8
