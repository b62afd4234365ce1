"""The Lie-group Runge–Kutta methods (RKMK4, RKMK5, RKMK8): the order of their tableau in
`g` and `m` on either side, with a potential and with forcing, and `g` on the group to
round-off (where the embedded `RK4` drifts off it)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_generalized_body
from lievi import diagnostics as dg

RKMK4 = lievi.RKMK4()
ORDER_TOLERANCE = 0.1  # on the slope of log error against log h over a factor 4 in h


def final_errors(system, g0, m0, T, hs, integrator=RKMK4, forcing=None):
    """The final error in `g` and `m` (∞-norm, against DOP853 at 1e-13) for each `h`."""
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, [0.0, T], forcing=forcing)
    errors = []
    for h in hs:
        n = int(round(T / h))
        sol = lievi.simulate(system, integrator, g0, m0, h=h, n_steps=n, forcing=forcing)
        assert int(sol.result) == lievi.RESULTS.successful, h
        errors.append(
            max(np.max(np.abs(sol.m[-1] - m_ref[-1])), np.max(np.abs(sol.g[-1] - g_ref[-1])))
        )
    return errors


def observed_order(system, g0, m0, T, hs, forcing=None, integrator=RKMK4):
    """The slope of log error against log h, and the errors."""
    errors = final_errors(system, g0, m0, T, hs, integrator, forcing)
    return np.polyfit(np.log(hs), np.log(errors), 1)[0], errors


HS = [0.2 / 2**k for k in range(3)]


@pytest.mark.extended  # 8–11 s each
@pytest.mark.parametrize("side", ["left", "right"])
def test_fourth_order_and_more_accurate_than_embedded_rk4(side):
    """HLW's free rigid body, T = 2: order 4.0 ± 0.1 on both sides, and at equal step more
    accurate than classical RK4 in the matrix embedding (measured 11×)."""
    body, g0, m0 = hlw_problem()
    system = body if side == "left" else lievi.LieLagrangian(lievi.SO3, body.lagrangian, side=side)
    order, errors = observed_order(system, g0, m0, 2.0, HS)
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)
    (rk4_error,) = final_errors(system, g0, m0, 2.0, HS[:1], lievi.RK4())
    assert errors[0] < rk4_error / 5, (errors[0], rk4_error)


@pytest.mark.extended  # 13 s
def test_fourth_order_heavy_top_with_control():
    """A heavy top (a potential) driven by a time-varying control torque: order 4."""
    top = lievi.heavy_top(jnp.array([2.0, 1.0, 2 / 3]), 1.0, jnp.array([0.1, 0.05, 0.4]), 1.0)
    g0 = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.1]))
    m0 = jnp.array([0.4, -0.2, 1.1])
    forcing = lievi.ForceLaw(lambda t, g, m, args: 0.1 * jnp.array([jnp.sin(t), 0.0, jnp.cos(t)]))
    order, errors = observed_order(top, g0, m0, 2.0, HS, forcing=forcing)
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)


def _heavy_top_with_control():
    top = lievi.heavy_top(jnp.array([2.0, 1.0, 2 / 3]), 1.0, jnp.array([0.1, 0.05, 0.4]), 1.0)
    g0 = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.1]))
    forcing = lievi.ForceLaw(lambda t, g, m, args: 0.1 * jnp.array([jnp.sin(t), 0.0, jnp.cos(t)]))
    return top, g0, jnp.array([0.4, -0.2, 1.1]), forcing


# (integrator, steps for HLW's free body, steps for the forced heavy top): each range is
# where the error is past its pre-asymptotic part and above round-off (measured slopes
# between halvings: RKMK5 5.11, 5.03 and 5.05, 4.94; RKMK8 7.88, 7.99 and 7.95, 8.03).
HIGHER_ORDERS = [
    (lievi.RKMK5(), [0.1, 0.05, 0.025], [0.05, 0.025, 0.0125]),
    (lievi.RKMK8(), [1.0, 0.5, 0.25], [0.5, 0.25, 0.125]),
]


@pytest.mark.extended  # 15–16 s each
@pytest.mark.parametrize("integrator, free_hs, forced_hs", HIGHER_ORDERS, ids=["rkmk5", "rkmk8"])
def test_order_of_the_tableau(integrator, free_hs, forced_hs):
    """RKMK5 and RKMK8 have the order of their tableau (± 0.1) in `g` and `m` together,
    T = 2, against DOP853 at 1e-13: on HLW's free rigid body (the kernel, through
    `simulate`) and on a heavy top driven by a time-varying torque (the generic step with
    forcing, the stage times `t + c_i h`). A tableau whose nodes or weights were off would
    drop to order ≤ 4."""
    assert integrator.order() in (5, 8)
    body, g0, m0 = hlw_problem()
    order, errors = observed_order(body, g0, m0, 2.0, free_hs, integrator=integrator)
    assert abs(order - integrator.order()) <= ORDER_TOLERANCE, (order, errors)
    top, g0, m0, forcing = _heavy_top_with_control()
    order, errors = observed_order(top, g0, m0, 2.0, forced_hs, forcing, integrator)
    assert abs(order - integrator.order()) <= ORDER_TOLERANCE, (order, errors)


@pytest.mark.parametrize("integrator", [lievi.RKMK4(), lievi.RKMK5(), lievi.RKMK8()], ids=str)
def test_step_bound_is_the_tableaus_stability(integrator):
    """`step_bound` is where the tableau's stability polynomial `R(iy)` (computed here from
    its coefficients) stops having `|R| ≤ 1` on the imaginary axis, or the chart's bound 3
    (`|u| < π`). RKMK8 is capped by the chart (DOP853's `|R(iy)| ≤ 1` reaches 5.96)."""
    tableau = integrator.tableau()
    s = len(tableau.b)
    A = np.zeros((s, s))
    for i, row in enumerate(tableau.a):
        A[i, : len(row)] = row
    np.testing.assert_allclose(A.sum(axis=1), tableau.c, atol=1e-15)  # c = row sums

    def amplification(y):
        return abs(
            1 + 1j * y * np.asarray(tableau.b) @ np.linalg.solve(np.eye(s) - 1j * y * A, np.ones(s))
        )

    ys = np.linspace(0, tableau.imaginary_stability, 2001)
    assert max(amplification(y) for y in ys) <= 1 + 1e-12
    assert amplification(tableau.imaginary_stability + 0.05) > 1
    assert integrator.step_bound() == min(tableau.imaginary_stability, 3.0)


@pytest.mark.parametrize(
    "integrator",
    [lievi.RKMK4(), pytest.param(lievi.RKMK8(), marks=pytest.mark.extended)],  # RKMK8: 8 s
    ids=str,
)
def test_stays_on_the_group_where_rk4_drifts(integrator):
    """Heavy top, h = 0.1, 1e4 steps: ‖gᵀg − I‖ stays at round-off (the attitude moves only
    by exponentials), while the embedded RK4's drifts by orders of magnitude more."""
    top = lievi.heavy_top(jnp.array([2.0, 1.0, 2 / 3]), 1.0, jnp.array([0.1, 0.05, 0.4]), 1.0)
    g0, m0 = jnp.eye(3), jnp.array([0.4, -0.2, 1.1])
    kwargs = dict(h=0.1, n_steps=10_000, save=lievi.Save(every=10_000))
    sol = lievi.simulate(top, integrator, g0, m0, **kwargs)
    assert int(sol.result) == lievi.RESULTS.successful
    assert dg.orthogonality_defect(top, sol.g[-1]) <= ROUNDOFF
    embedded = lievi.simulate(top, lievi.RK4(), g0, m0, **kwargs)
    assert dg.orthogonality_defect(top, embedded.g[-1]) >= 1e3 * ROUNDOFF


@pytest.mark.slow
def test_fourth_order_on_so4_and_se3():
    body, g0, m0 = random_generalized_body(np.random.default_rng(4), 4)
    order, errors = observed_order(body, g0, m0, 1.0, [0.1 / 2**k for k in range(3)])
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)
    se3 = lievi.RigidBodySE3(
        jnp.array([1.0, 1.5, 2.0]), 2.0, potential=lievi.UniformGravitySE3(2.0)
    )
    g0 = lievi.SE3.exp(jnp.array([0.2, -0.1, 0.3, 0.5, 0.0, -0.4]))
    m0 = jnp.array([0.5, -0.3, 0.8, 1.0, 0.2, -0.5])
    order, errors = observed_order(se3, g0, m0, 1.0, [0.1 / 2**k for k in range(3)])
    assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)


def test_float32_stays_on_the_group():
    body, g0, m0 = hlw_problem()
    body32 = lievi.RigidBody(body.inertia.astype(jnp.float32))
    sol = lievi.simulate(
        body32, RKMK4, g0.astype(jnp.float32), m0.astype(jnp.float32), h=0.05, n_steps=2000
    )
    assert sol.m.dtype == jnp.float32 and int(sol.result) == lievi.RESULTS.successful
    # 64 ulps of float32 (the library's membership tolerance for float32).
    assert dg.orthogonality_defect(body32, sol.g[-1]) <= 64 * np.finfo(np.float32).eps


def test_bad_input():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="`m` must have shape"):
        RKMK4.step(body, g0, jnp.ones(4), 0.1)
    with pytest.raises(ValueError, match="`g` must have shape"):
        RKMK4.step(body, jnp.eye(4), m0, 0.1)


def _se3_body(rng, gravity):
    """A Kirchhoff body (a full SPD 6×6 tensor), free or in uniform gravity with its centre
    of mass off the origin (a torque and a force)."""
    A = rng.normal(size=(6, 6))
    tensor = jnp.asarray(A @ A.T / 6 + np.diag([1.0, 1.5, 2.0, 2.0, 2.5, 3.0]))
    potential = lievi.UniformGravitySE3(2.0, 1.0, jnp.array([0.1, -0.2, 0.3])) if gravity else None
    return lievi.RigidBodySE3(tensor=tensor, potential=potential)


SE3_G0 = lievi.SE3.exp(jnp.array([0.2, -0.1, 0.3, 0.5, 0.0, -0.4]))
SE3_M0 = jnp.array([0.5, -0.3, 0.8, 1.0, 0.2, -0.5])
HS_SE3 = [0.1 / 2**k for k in range(3)]


@pytest.mark.extended  # 13–14 s each
@pytest.mark.parametrize("gravity", [False, True], ids=["free", "gravity"])
def test_fourth_order_on_se3_through_the_kernel(gravity):
    """`simulate_batch` on SE(3) (the structure-of-arrays kernel): order 4.0 ± 0.1 in `g`
    and in `m` separately, T = 1, h = 0.1 … 0.025, against DOP853 at 1e-13."""
    body = _se3_body(np.random.default_rng(1), gravity)
    assert type(RKMK4.batch_kernel(body)).__name__ == "RKMKSE3Kernel"
    g_ref, m_ref = lievi.reference_solution(body, SE3_G0, SE3_M0, [0.0, 1.0])
    errors = []
    for h in HS_SE3:
        sol = lievi.simulate_batch(
            body,
            RKMK4,
            SE3_G0,
            SE3_M0[None],
            h=h,
            n_steps=int(round(1 / h)),
            save=lievi.Save(stats=False, every=int(round(1 / h))),
        )
        errors.append(
            (np.max(np.abs(sol.g[0, -1] - g_ref[-1])), np.max(np.abs(sol.m[0, -1] - m_ref[-1])))
        )
    for column in zip(*errors):
        order = np.polyfit(np.log(HS_SE3), np.log(column), 1)[0]
        assert abs(order - 4) <= ORDER_TOLERANCE, (order, errors)


# Slow: the generic path's reverse mode on SE(3) in gravity compiles for minutes on a
# loaded 2-core CPU (measured 11.6 min for this test); the free SE(3) kernel's gradients are
# compared with the generic path's in the default suite (`test_kernel_parity.py`).
@pytest.mark.slow
def test_se3_kernel_gradient_equals_generic_and_differences():
    """The gradient of a loss of a short batched run on SE(3) in gravity (three bodies,
    each its own tensor) with respect to the tensors, `m0` and the initial pose (along the
    group, `g0 exp(ζ)`): the kernel's (JAX's autodiff of the structure-of-arrays step)
    equals the generic path's to 1e-10 (relative), and central differences along a random
    direction to 1e-7. (Off the group the two differ by design: the generic step projects
    the rotation at every stage, the kernel only at the end of the step.)"""
    from lievi._kernels._base import reference_path

    rng = np.random.default_rng(2)
    bodies = [_se3_body(rng, True) for _ in range(3)]
    m0 = jnp.stack([SE3_M0 * s for s in (1.0, 1.3, 0.8)])
    potential = bodies[0].potential

    def loss(params):
        systems = jax.vmap(lambda M: lievi.RigidBodySE3(tensor=M, potential=potential))(
            params["tensor"]
        )
        g0 = SE3_G0 @ lievi.SE3.exp(params["zeta"])
        sol = lievi.simulate_batch(
            systems,
            RKMK4,
            g0,
            params["m0"],
            h=0.1,
            n_steps=6,
            system_axis=0,
            save=lievi.Save(every=6),
        )
        return jnp.sum(sol.m[:, -1] ** 2) + jnp.sum(sol.g[:, -1] * jnp.arange(4.0))

    params = {
        "tensor": jnp.stack([b.tensor for b in bodies]),
        "m0": m0,
        "zeta": jnp.zeros((3, 6)),
    }
    fast = jax.jit(jax.grad(loss))(params)
    with reference_path():
        generic = jax.jit(jax.grad(loss))(params)
    for key in params:
        scale = float(jnp.max(jnp.abs(generic[key])))
        np.testing.assert_allclose(fast[key], generic[key], rtol=0, atol=1e-10 * scale)
    direction = jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape)), params)
    # Symmetric tensor directions (the loss reads the tensor's symmetric part).
    direction["tensor"] = (direction["tensor"] + jnp.swapaxes(direction["tensor"], -1, -2)) / 2
    eps = 1e-5
    shifted = [jax.tree.map(lambda x, d: x + s * eps * d, params, direction) for s in (1, -1)]
    difference = (loss(shifted[0]) - loss(shifted[1])) / (2 * eps)
    derivative = sum(jnp.vdot(fast[k], direction[k]) for k in params)
    assert abs(difference - derivative) <= 1e-7 * abs(derivative), (difference, derivative)


@pytest.mark.extended  # 11–15 s each
@pytest.mark.parametrize("integrator", [lievi.RKMK4(), lievi.RKMK8()], ids=str)
def test_saves_the_advected_parameter(integrator):
    """`simulate_batch(..., save=Save(g=False, advected=True))` on the heavy top: `Γ = gᵀe₃` from the
    kernel's carried `g` equals the last row of the saved `g` of the same run (exactly: the
    same kernel, the same arithmetic). It used to raise a `TypeError` (the kernel had no
    `advected`)."""
    top = lievi.heavy_top(jnp.array([2.0, 1.0, 2 / 3]), 1.0, jnp.array([0.1, 0.05, 0.4]), 1.0)
    g0 = lievi.SO3.exp(jnp.array([0.3, -0.2, 0.1]))
    m0 = jnp.array([[0.4, -0.2, 1.1], [0.1, 0.3, -0.5]])
    kwargs = dict(h=0.1, n_steps=20)
    reduced = lievi.simulate_batch(
        top, integrator, g0, m0, save=lievi.Save(g=False, stats=False, advected=True), **kwargs
    )
    full = lievi.simulate_batch(top, integrator, g0, m0, save=lievi.Save(stats=False), **kwargs)
    np.testing.assert_array_equal(reduced.advected, full.g[..., 2, :])
    np.testing.assert_array_equal(reduced.m, full.m)
