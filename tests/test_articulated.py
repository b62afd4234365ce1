"""Articulated bodies (`lievi.ArticulatedBodies`) stepped by `lievi.RATTLE`.

The joints at position and velocity level, the momenta of the symmetries, bounded energy,
the order against an independent Newton–Euler reference (tests/articulated_problems.py),
the heavy top as a one-link chain, gradients, batches and bad input.
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
from helpers import dop853_final, final_state, programs_compiled
from lievi._systems._base import AbstractLieSystem

JOINTS = 1e-12  # joints, relative to the link length, at every step
MOMENTUM = 1e-12  # conserved momenta, relative
HUGE_STEP = 10.0  # a step the RATTLE iteration cannot solve (the links' periods are ~1)


@pytest.fixture(scope="module")
def pendulum_run():
    """The triple spherical pendulum in gravity, 1000 steps of h = 0.005."""
    system, g0, m0 = triple_pendulum()
    sol = lievi.simulate(system, lievi.RATTLE(), g0, m0, h=0.005, n_steps=1000)
    return system, sol


@pytest.fixture(scope="module")
def floating_run():
    """A floating base with two hinged panels (a root with two children) in free space,
    1000 steps of h = 0.01."""
    system, g0, m0 = satellite()
    sol = lievi.simulate(system, lievi.RATTLE(), g0, m0, h=0.01, n_steps=1000)
    return system, sol


def test_pendulum_joints_hold_at_every_step(pendulum_run):
    system, sol = pendulum_run
    assert bool(jnp.all(sol.result == lievi.RESULTS.successful))
    assert float(jnp.max(joint_defects(system, sol.g))) <= JOINTS
    assert float(velocity_defect(system, sol.g, sol.m)) <= JOINTS


def test_pendulum_keeps_vertical_angular_momentum_about_pivot(pendulum_run):
    # Gravity and the pivot's reaction exert no torque about the vertical through the
    # pivot (the origin): the third component of the total angular momentum is conserved.
    system, sol = pendulum_run
    vertical = lievi.diagnostics.total_momentum(system, sol.g, sol.m)[:, 2]
    scale = jnp.max(jnp.abs(lievi.diagnostics.total_momentum(system, sol.g, sol.m)[0, :3]))
    assert float(jnp.max(jnp.abs(vertical - vertical[0])) / scale) <= MOMENTUM


def test_pendulum_energy_bounded(pendulum_run):
    # Symplectic on the constraint manifold: the energy error oscillates at O(h²), no drift.
    system, sol = pendulum_run
    energy = lievi.diagnostics.energy(system, sol.g, sol.m)
    kinetic = jax.vmap(system.energy)(sol.m)
    error = jnp.abs(energy - energy[0]) / jnp.max(kinetic)
    assert float(jnp.max(error)) < 1e-3
    half = error.shape[0] // 2
    assert float(jnp.mean(error[half:])) <= 1.5 * float(jnp.mean(error[:half])) + 1e-6


def test_floating_tree_keeps_total_momentum(floating_run):
    system, sol = floating_run
    assert bool(jnp.all(sol.result == lievi.RESULTS.successful))
    total = lievi.diagnostics.total_momentum(system, sol.g, sol.m)
    scale = jnp.max(jnp.abs(total[0]))
    assert float(jnp.max(jnp.abs(total - total[0])) / scale) <= MOMENTUM
    assert float(jnp.max(joint_defects(system, sol.g))) <= JOINTS
    assert float(velocity_defect(system, sol.g, sol.m)) <= JOINTS
    # Without a potential the energy is the kinetic energy: bounded.
    kinetic = jax.vmap(system.energy)(sol.m)
    assert float(jnp.max(jnp.abs(kinetic - kinetic[0])) / kinetic[0]) < 1e-3


def test_one_link_chain_is_the_heavy_top():
    # A body on a ball joint at its pivot: the SE(3) increment of a turn about the pivot is
    # a pure twist, so the constrained DEP step is the heavy top's DEP step with the inertia
    # about the pivot (parallel axes).
    inertia_pivot, mass, rho = jnp.array([1.0, 1.5, 0.7]), 1.3, jnp.array([0.1, -0.2, 0.8])
    top = lievi.heavy_top(inertia_pivot, mass, rho, 9.81)
    R0, Pi0 = lievi.SO3.exp(jnp.array([0.3, -0.5, 0.2])), jnp.array([0.4, -0.2, 0.9])
    inertia_center = jnp.diag(inertia_pivot) - mass * (rho @ rho * jnp.eye(3) - jnp.outer(rho, rho))
    chain = lievi.ArticulatedBodies(
        inertia_center[None],
        jnp.array([mass]),
        [-1],
        [lievi.BallJoint(jnp.zeros(3), -rho)],
        gravity=9.81,
    )
    g0 = chain.place(R0[None])
    m0 = chain.momentum(g0, (R0 @ jnp.linalg.solve(jnp.diag(inertia_pivot), Pi0))[None])
    h, n = 0.01, 200
    top_sol = lievi.simulate(top, lievi.DEP(), R0, Pi0, h=h, n_steps=n)
    sol = lievi.simulate(chain, lievi.RATTLE(), g0, m0, h=h, n_steps=n)
    rotation = sol.g[:, 0, :3, :3]
    # The angular momentum about the pivot: Π_C + ρ × P.
    pivot_momentum = sol.m[:, 0, :3] + jnp.cross(rho, sol.m[:, 0, 3:])
    scale = float(jnp.max(jnp.abs(top_sol.m)))
    assert float(jnp.max(jnp.abs(rotation - top_sol.g))) <= 1e-13
    assert float(jnp.max(jnp.abs(pivot_momentum - top_sol.m))) <= 1e-13 * scale


def test_simulate_batch_runs_states_and_reports_broken_joints():
    # A batch through `simulate_batch` (`jax.vmap` of the step): each good state as
    # `simulate` runs it, and a state whose joint is broken reported as invalid input
    # under `jit`; an eager call raises the chain's own check, naming the state and the
    # joint (it once fell back to a generic error: the batch's check knew only the group).
    system, g0, m0 = hinge_chain(1)
    broken = g0.at[0, 0, 3].add(0.1)
    kwargs = dict(h=0.01, n_steps=20, throw=False, save=lievi.Save(every=20))
    states, momenta = jnp.stack([g0, broken]), jnp.stack([m0, m0])
    batch = eqx.filter_jit(
        lambda g, m: lievi.simulate_batch(system, lievi.RATTLE(), g, m, **kwargs)
    )(states, momenta)
    one = lievi.simulate(system, lievi.RATTLE(), g0, m0, h=0.01, n_steps=20)
    assert int(batch.result[0]) == lievi.RESULTS.successful
    assert int(batch.result[1]) == lievi.RESULTS.invalid_input
    np.testing.assert_allclose(batch.g[0, -1], one.g[-1], rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"`g0\[1\]` does not satisfy `joints\[0\]`"):
        lievi.simulate_batch(system, lievi.RATTLE(), states, momenta, **kwargs)


@pytest.mark.parametrize("chart", ["exp", pytest.param("cayley", marks=pytest.mark.extended)])
def test_rattle_is_symmetric(chart):
    # Φ_{−h} ∘ Φ_h = id (what `Composition` needs): the step back with −h returns to the
    # start, joints and momenta, to round-off.
    system, g0, m0 = triple_pendulum()
    method = lievi.RATTLE(chart=chart)
    step = eqx.filter_jit(method.step)
    g1, m1, info = step(system, g0, m0, 0.02)
    g2, m2, info_back = step(system, g1, m1, -0.02)
    assert int(info.result) == int(info_back.result) == lievi.RESULTS.successful
    assert float(jnp.max(jnp.abs(g1 - g0))) > 1e-3  # it moved
    assert float(jnp.max(jnp.abs(g2 - g0))) <= 1e-14
    assert float(jnp.max(jnp.abs(m2 - m0))) <= 1e-14 * float(jnp.max(jnp.abs(m0)))
    assert float(system.joint_defect(g1)) <= JOINTS


@eqx.filter_jit
def _one_step(method, system, g, m, h):
    return method.step(system, g, m, h)


def test_structured_iteration_reaches_newtons_root():
    # The default iteration (the Jacobian once per step, solved by its block structure)
    # and Newton's method with the whole autodiff Jacobian at every iteration solve the
    # same equations: the same step, to round-off, poses and momenta.
    system, g0, m0 = triple_pendulum()
    h = jnp.asarray(0.02)
    g1, m1, info = _one_step(lievi.RATTLE(), system, g0, m0, h)
    g2, m2, info_full = _one_step(lievi.RATTLE(full_newton=True), system, g0, m0, h)
    assert int(info.result) == int(info_full.result) == lievi.RESULTS.successful
    assert float(jnp.max(jnp.abs(g1 - g0))) > 1e-3  # it moved
    assert float(jnp.max(jnp.abs(g1 - g2))) <= 1e-14
    assert float(jnp.max(jnp.abs(m1 - m2))) <= 1e-14 * float(jnp.max(jnp.abs(m0)))


def test_impossible_step_is_reported_not_converged():
    # A step far too long for the joints' equations to have a root near the guess: the
    # iteration must say so, not hand back a number.
    system, g0, m0 = triple_pendulum()
    # The same compiled step as the test above (`h` traced).
    g1, m1, info = _one_step(lievi.RATTLE(), system, g0, m0, jnp.asarray(HUGE_STEP))
    assert int(info.result) == lievi.RESULTS.newton_not_converged


def _hinge_torque(system, torque):
    """Control rows `(n_steps, 2, 6)` of a torque `τ_k` about the hinge of body 1: `+τ n_c` on
    the child, `−τ n_p` on the parent, each in its own frame (the hinge keeps
    `R_1 n_c = R_0 n_p`, so the pair is internal)."""
    hinge = system.joints[1]
    n_c = hinge.axis / jnp.linalg.norm(hinge.axis)
    n_p = hinge.parent_axis / jnp.linalg.norm(hinge.parent_axis)
    u = jnp.zeros((torque.shape[0], 2, 6))
    return u.at[:, 0, :3].set(-torque[:, None] * n_p).at[:, 1, :3].set(torque[:, None] * n_c)


@pytest.mark.extended
def test_joint_torque_keeps_total_momentum_of_floating_chain():
    # A joint torque is a pair of opposite torques (discrete Lagrange–d'Alembert forces):
    # it does work, but the total linear and angular momentum stay.
    system, g0, m0 = hinge_chain(2, gravity=None, fixed=False)
    n = 200
    torque = 0.5 * jnp.sin(0.05 * jnp.arange(n))
    forcing = lievi.Control(_hinge_torque(system, torque))
    sol = lievi.simulate(system, lievi.RATTLE(), g0, m0, h=0.01, n_steps=n, forcing=forcing)
    assert bool(jnp.all(sol.result == lievi.RESULTS.successful))
    total = lievi.diagnostics.total_momentum(system, sol.g, sol.m)
    assert float(jnp.max(jnp.abs(total - total[0])) / jnp.max(jnp.abs(total[0]))) <= MOMENTUM
    assert float(jnp.max(joint_defects(system, sol.g))) <= JOINTS
    assert float(velocity_defect(system, sol.g, sol.m)) <= JOINTS
    kinetic = jax.vmap(system.energy)(sol.m)
    assert float(jnp.max(jnp.abs(kinetic - kinetic[0])) / kinetic[0]) > 1e-2


@pytest.mark.extended
def test_gradient_with_respect_to_joint_torques():
    system, g0, m0 = hinge_chain(2, gravity=None, fixed=False)
    n = 20
    weights = jnp.array([[1.0, -0.5, 0.3], [0.2, 0.7, -1.0]])

    def final(torque):
        forcing = lievi.Control(_hinge_torque(system, torque))
        sol = lievi.simulate(system, lievi.RATTLE(), g0, m0, h=0.01, n_steps=n, forcing=forcing)
        return jnp.sum(sol.g[-1, :, :3, 3] * weights) + jnp.sum(sol.g[-1, :, :3, 0])

    torque = 0.5 * jnp.cos(0.3 * jnp.arange(n))
    grad = jax.grad(final)(torque)
    eps = 1e-6
    for k in (0, 7, n - 1):
        plus, minus = torque.at[k].add(eps), torque.at[k].add(-eps)
        difference = (final(plus) - final(minus)) / (2 * eps)
        # Relative to the gradient's size: a central difference of an O(1) function at
        # ε = 1e-6 carries ~1e-10 of round-off, whatever the component.
        scale = float(jnp.max(jnp.abs(grad)))
        assert abs(float(grad[k]) - float(difference)) <= 1e-6 * scale


@pytest.mark.slow
def test_gradient_from_rest_is_finite():
    # From rest with zero torque the step's momenta are all zero; the gradient with
    # respect to the torques (what `solve_optimal_control` starts from with `u0 = 0`) must
    # be finite. It was NaN: the residual's momentum scale, floored at `tiny`, made the
    # Jacobian's momentum rows overflow.
    system, g0, m0 = hinge_chain(2, gravity=None)

    def final(torque):
        forcing = lievi.Control(_hinge_torque(system, torque))
        rest = jnp.zeros_like(m0)
        sol = lievi.simulate(system, lievi.RATTLE(), g0, rest, h=0.1, n_steps=2, forcing=forcing)
        return jnp.sum(sol.g[-1, :, :3, 3])

    grad = jax.grad(final)(jnp.zeros(2))
    assert bool(jnp.all(jnp.isfinite(grad)))
    assert float(jnp.max(jnp.abs(grad))) > 0.0


# ---- order against the Newton–Euler reference ---------------------------------------------


def _order(system, g0, m0, method, steps):
    T = 2.0
    reference = dop853_final(reference_rhs(system), reference_state(system, g0, m0), T)
    R_ref, x_ref = reference_poses(system, reference)
    errors = []
    for h in steps:
        g, _, ok = final_state(system, method, g0, m0, jnp.asarray(h), jnp.asarray(round(T / h)))
        assert bool(ok)
        errors.append(
            max(
                float(jnp.max(jnp.abs(g[:, :3, :3] - R_ref))),
                float(jnp.max(jnp.abs(g[:, :3, 3] - x_ref))),
            )
        )
    return np.polyfit(np.log(steps), np.log(errors), 1)[0]


@pytest.mark.extended
@pytest.mark.parametrize("problem", [triple_pendulum, hinge_chain], ids=["triple-ball", "hinge-5"])
def test_order_two(problem):
    system, g0, m0 = problem()
    assert abs(_order(system, g0, m0, lievi.RATTLE(), [0.02, 0.01, 0.005]) - 2.0) <= 0.1


@pytest.mark.extended
@pytest.mark.parametrize("problem", [triple_pendulum, hinge_chain], ids=["triple-ball", "hinge-5"])
def test_composition_order_four(problem):
    system, g0, m0 = problem()
    method = lievi.Composition(lievi.RATTLE(), 4)
    # Past the pre-asymptotic range of the triple pendulum's fast links (h ≤ 0.01).
    assert abs(_order(system, g0, m0, method, [0.01, 0.005, 0.0025]) - 4.0) <= 0.1


# ---- gradients -------------------------------------------------------------------------------


@pytest.mark.extended
def test_gradients_match_central_differences():
    # Through the Newton solves by the implicit function theorem: the final positions of a
    # triple pendulum with respect to the link masses and a joint point.
    base, g0, m0 = triple_pendulum()

    def final(mass, point):
        joints = list(base.joints)
        joints[1] = lievi.BallJoint(point, joints[1].child_point)
        system = lievi.ArticulatedBodies(base.inertia, mass, base.parents, joints, gravity=9.81)
        g = system.place(g0[:, :3, :3])
        m = system.momentum(g, jnp.array([[0.0, 0.5, 0.3], [0.8, 0.0, -0.4], [-0.3, 1.0, 0.5]]))
        # A Python int step count: a scan, which reverse mode goes through.
        g, _, _ = final_state(system, lievi.RATTLE(), g, m, jnp.asarray(0.01), 20)
        return jnp.sum(g[:, :3, 3] * jnp.array([1.0, -0.5, 0.3]))

    mass, point = base.mass, base.joints[1].parent_point
    grad_mass, grad_point = jax.grad(final, argnums=(0, 1))(mass, point)
    eps = 1e-6
    for grad, arg, index in ((grad_mass, 0, 1), (grad_point, 1, 2)):
        args = [mass, point]
        plus, minus = list(args), list(args)
        plus[arg] = args[arg].at[index].add(eps)
        minus[arg] = args[arg].at[index].add(-eps)
        difference = (final(*plus) - final(*minus)) / (2 * eps)
        assert abs(float(grad[index]) - float(difference)) <= 1e-6 * abs(float(difference))


def test_masses_are_one_leaf_for_inertia_and_weight():
    # A fit of the masses replaces `bodies.mass`; gravity must weigh the new masses.
    system, g0, _ = triple_pendulum()
    heavier = eqx.tree_at(lambda s: s.bodies.mass, system, 2.0 * system.mass)
    weight = 9.81 * jnp.sum(2.0 * system.mass * g0[:, 2, 3])
    assert abs(float(heavier.potential_energy(g0)) - float(weight)) <= 1e-12 * abs(float(weight))


@pytest.mark.slow
def test_fit_system_identifies_link_masses():
    # Poses observed every 5 steps; the model's masses 10 % off, the rest known.
    system, g0, m0 = triple_pendulum()
    observed = lievi.simulate(system, lievi.RATTLE(), g0, m0, h=0.02, n_steps=20)
    guess = eqx.tree_at(lambda s: s.bodies.mass, system, 1.1 * system.mass)
    fit = lievi.fit_system(
        guess, observed.g[::5], h=0.02, sample_every=5, params=lambda s: s.bodies.mass,
        m0=m0, g0=g0, integrator=lievi.RATTLE(), max_iters=100,
    )  # fmt: skip
    assert np.allclose(np.asarray(fit.system.mass), np.asarray(system.mass), rtol=1e-6)


@pytest.mark.slow
def test_solve_optimal_control_reaches_a_pose_of_the_chain():
    # A reachable target: the pose two hinged rods reach, from rest, under a hinge torque.
    system, g0, m0 = hinge_chain(2, gravity=0.0)
    rest, n, h = jnp.zeros_like(m0), 6, 0.1
    tau = jnp.concatenate([jnp.full(3, 0.5), jnp.full(3, -0.5)])[:, None]
    wrench = jnp.zeros((n, 2, 6))
    wrench = wrench.at[:, 1, :3].set(tau * system.joints[1].axis)
    wrench = wrench.at[:, 0, :3].set(-tau * system.joints[1].parent_axis)
    target = lievi.simulate(system, lievi.RATTLE(), g0, rest, h=h, n_steps=n,
                            forcing=lievi.Control(wrench)).g[-1]  # fmt: skip
    # A nonzero first guess: from rest with zero controls the gradient is still NaN.
    u0 = jnp.full((n, 2, 6), 1e-3)
    out = lievi.solve_optimal_control(
        system, lievi.RATTLE(), g0, rest, (target, None), n, h, u0=u0, max_iterations=5
    )
    assert out.converged
    assert float(jnp.max(jnp.abs(out.solution.g[-1] - target))) <= 1e-10
    assert float(joint_defects(system, out.solution.g).max()) <= JOINTS


# ---- long runs -------------------------------------------------------------------------------


@pytest.mark.slow
def test_long_run_joints_and_vertical_momentum():
    system, g0, m0 = triple_pendulum()
    sol = lievi.simulate(
        system, lievi.RATTLE(), g0, m0, h=0.005, n_steps=100_000, save=lievi.Save(every=100)
    )
    assert bool(jnp.all(sol.result == lievi.RESULTS.successful))
    assert float(jnp.max(joint_defects(system, sol.g))) <= JOINTS
    assert float(velocity_defect(system, sol.g, sol.m)) <= JOINTS
    total = lievi.diagnostics.total_momentum(system, sol.g, sol.m)
    scale = jnp.max(jnp.abs(total[0, :3]))
    assert float(jnp.max(jnp.abs(total[:, 2] - total[0, 2])) / scale) <= MOMENTUM


# ---- bad input --------------------------------------------------------------------------------


def _rods(n):
    return jnp.ones((n, 3)), jnp.ones(n)


def test_cycle_in_tree_is_rejected():
    joint = lievi.BallJoint(jnp.zeros(3), jnp.array([0.0, 0.0, 0.5]))
    with pytest.raises(ValueError, match=r"`parents` has a cycle \(0 → 1 → 0\)"):
        lievi.ArticulatedBodies(*_rods(2), [1, 0], [joint, joint])


def test_zero_hinge_axis_is_rejected():
    with pytest.raises(ValueError, match="`axis` has zero length"):
        lievi.HingeJoint(jnp.zeros(3), jnp.ones(3), jnp.zeros(3))


def test_massless_body_is_rejected():
    joint = lievi.BallJoint(jnp.zeros(3), jnp.array([0.0, 0.0, 0.5]))
    with pytest.raises(ValueError, match="`mass` must be > 0"):
        lievi.ArticulatedBodies(jnp.ones((2, 3)), jnp.array([1.0, 0.0]), [-1, 0], [joint, joint])


def test_joint_points_that_do_not_connect_are_rejected():
    system, g0, m0 = triple_pendulum()
    apart = g0.at[2, :3, 3].add(jnp.array([0.0, 0.3, 0.0]))
    with pytest.raises(ValueError, match=r"`g0` does not satisfy `joints\[2\]` \(ball joint"):
        lievi.simulate(system, lievi.RATTLE(), apart, m0, h=0.01, n_steps=2)


def test_eager_helpers_and_run_compile_their_programs_only():
    """`place` and `momentum` are one program each (their operations one by one were 12
    and 98 small programs), and an eager run of a chain in gravity its two: reading
    a save's shapes once built the gravity potential from concrete masses, whose eager
    check compiled three more. NumPy inputs: the test's own arithmetic compiles nothing."""
    rods = np.array([[0.084, 0.084, 0.00125], [0.084, 0.084, 0.00125]])
    joints = [
        lievi.BallJoint(np.zeros(3), np.array([0.0, 0.0, 0.5])),
        lievi.BallJoint(np.array([0.0, 0.0, -0.5]), np.array([0.0, 0.0, 0.5])),
    ]
    system = lievi.ArticulatedBodies(rods, np.array([1.0, 1.0]), [-1, 0], joints, gravity=9.81)
    turned = np.stack([np.eye(3), np.array([[1.0, 0, 0], [0, 0.6, -0.8], [0, 0.8, 0.6]])])
    spin = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    assert len(programs_compiled(lambda: system.place(turned))) <= 1
    g0 = system.place(turned)
    assert len(programs_compiled(lambda: system.momentum(g0, spin))) <= 1
    m0 = system.momentum(g0, spin)
    assert programs_compiled(lambda: system.momentum(g0, 2.0 * spin)) == []
    run = lambda h, n: lievi.simulate(system, lievi.RATTLE(), g0, m0, h=h, n_steps=n)  # noqa: E731
    assert len(programs_compiled(lambda: run(0.01, 4))) <= 2
    assert programs_compiled(lambda: run(0.02, 7)) == []


def test_floating_joint_only_at_a_root():
    joint = lievi.BallJoint(jnp.zeros(3), jnp.array([0.0, 0.0, 0.5]))
    with pytest.raises(ValueError, match=r"`joints\[1\]` is None"):
        lievi.ArticulatedBodies(*_rods(2), [-1, 0], [joint, None])


@pytest.fixture(scope="module")
def two_hinges():
    return hinge_chain(2)


def test_other_methods_refuse_the_joints(two_hinges):
    system, g0, m0 = two_hinges
    with pytest.raises(ValueError, match="only lievi.RATTLE and the RKMK methods enforce"):
        lievi.simulate(system, lievi.DEP(), g0, m0, h=0.01, n_steps=2)


def test_embedded_runge_kutta_refuses_the_joints(two_hinges):
    """`lievi.RK4` in the matrix embedding integrates the free bodies' equations (its `g`
    leaves the group, so no projection onto the joints applies): on an articulated system
    it refuses, naming itself and the methods that enforce the joints (raised while
    tracing: nothing is compiled). The RKMK methods run: tests/test_articulated_explicit.py."""
    system, g0, m0 = two_hinges
    with pytest.raises(ValueError, match=r"RKMK methods enforce; RK4 would step"):
        lievi.simulate(system, lievi.RK4(), g0, m0, h=0.01, n_steps=2)
    with pytest.raises(ValueError, match="RK4 would step"):
        lievi.simulate_batch(system, lievi.RK4(), g0[None], m0[None], h=0.01, n_steps=2)


def test_reference_solution_refuses_the_joints(two_hinges):
    system, g0, m0 = two_hinges
    with pytest.raises(ValueError, match="lievi.reference_solution would step"):
        lievi.reference_solution(system, g0, m0, [0.0, 0.1])


def test_constraint_jacobian_closed_form_matches_autodiff():
    """`C(g)` from the joints' closed-form rows (`AbstractJoint.jacobian`) equals autodiff
    of the joints' equations along `g_i (1 + ε η̂_i)`, off the constraint manifold too:
    ball and hinge joints, to the world and between bodies, a floating root."""
    for system, g, _ in (triple_pendulum(), hinge_chain(2), hinge_chain(2, fixed=False)):
        n = system.n_bodies
        turn = 0.3 * jax.random.normal(jax.random.key(n), (n, 6))
        g = lievi.SE3.compose(g, lievi.SE3.exp(turn))
        along = jax.jit(lambda eta, g: system.constraints(g + g @ lievi.SE3.hat(eta)))
        autodiff = jax.jacfwd(along)(jnp.zeros((n, 6)), g)
        C = jax.jit(lambda g: system.constraint_jacobian(g))(g)
        assert C.shape == autodiff.shape
        assert float(jnp.max(jnp.abs(C - autodiff))) <= 1e-14


def test_reaction_carried_over_saves_iterations_not_the_root():
    """A run's steps start their reaction from the last step's projection impulse
    (`cached_step`): fewer iterations than `step`'s zero-reaction guess, the same states
    to the Newton tolerance."""
    system, g0, m0 = hinge_chain(5)
    method = lievi.RATTLE()
    plain = jax.jit(lambda g, m: method.step(system, g, m, 0.01))
    cached = jax.jit(lambda g, m, c: method.cached_step(system, g, m, 0.01, c))
    g, m, gc, mc = g0, m0, g0, m0
    cache = method.step_cache(system, g0)
    plain_iterations = cached_iterations = 0
    for _ in range(20):
        g, m, info = plain(g, m)
        gc, mc, info_c, cache = cached(gc, mc, cache)
        plain_iterations += int(info.iterations)
        cached_iterations += int(info_c.iterations)
        assert int(info_c.result) == 0
    assert cached_iterations <= 0.85 * plain_iterations
    np.testing.assert_allclose(gc, g, rtol=0, atol=1e-12)
    np.testing.assert_allclose(mc, m, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(m))))


def test_gravity_wrench_closed_form_matches_autodiff():
    """Gravity's wrenches in closed form (`ArticulatedBodies.force`) equal the autodiff
    force of the same potential (`AbstractLieSystem.force`) to 1e-13 relative, off the
    constraint manifold too; with a further potential that has no closed form the whole
    force is autodiff's."""
    system, g, _ = triple_pendulum()
    turn = 0.3 * jax.random.normal(jax.random.key(3), (system.n_bodies, 6))
    g = lievi.SE3.compose(g, lievi.SE3.exp(turn))
    spring = eqx.tree_at(
        lambda s: s.applied,
        system,
        lievi.PotentialFunction(lambda g: 0.3 * jnp.sum(g[:, 0, 3] ** 2)),
        is_leaf=lambda x: x is None,
    )
    closed_form = eqx.filter_jit(lambda system, g: system.force(g))
    autodiff = eqx.filter_jit(lambda system, g: AbstractLieSystem.force(system, g))
    for each in (system, spring):
        expected = autodiff(each, g)
        scale = float(jnp.max(jnp.abs(expected)))
        assert float(jnp.max(jnp.abs(closed_form(each, g) - expected))) <= 1e-13 * scale
