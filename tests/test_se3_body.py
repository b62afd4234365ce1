"""Rigid bodies on SE(3): Kirchhoff's equations, free fall, the full body problem.

Decided by the checks that do not depend on a hand derivation: the DEL residual of the
discrete Lagrangian by autodiff (Theorem 2.1), the order against DOP853, and exact
conservation of the Casimirs `|P|²`, `P·Π` and of the momentum of the symmetry
(spatial momentum for the free body, total angular momentum about the planet for the full
body problem). Float64 unless stated. Long runs (1e5 steps) are in the slow set.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, final_state
from lievi import diagnostics as dg

SE3 = lievi.SE3
CHARTS = ("exp", "cayley")
ORDER_TOLERANCE = 0.1


def kirchhoff_problem():
    """A body in a fluid: a full SPD 6×6 tensor (added mass couples rotation and
    translation), a generic initial state."""
    rng = np.random.default_rng(11)
    A = rng.normal(size=(6, 6))
    tensor = jnp.asarray(A @ A.T / 6 + np.diag([1.0, 1.5, 2.0, 3.0, 4.0, 5.0]))
    body = lievi.RigidBodySE3(tensor=tensor)
    g0 = SE3.exp(jnp.asarray(rng.normal(size=6)))
    m0 = jnp.asarray(rng.normal(size=6))
    return body, g0, m0


def satellite_problem():
    """A four-mass satellite (size 0.1) on a near-circular orbit of radius 1 about a
    planet with μ = 1, spinning about a generic axis: orbit and attitude exchange angular
    momentum through the gravity gradient."""
    points = 0.3 * jnp.array([[0.3, 0, 0], [-0.3, 0, 0], [0, 0.1, 0.05], [0, -0.1, -0.05]])
    body = lievi.full_body_problem(1.0, jnp.array([1.0, 1.0, 0.5, 0.5]), points)
    R0 = lievi.SO3.exp(jnp.array([0.2, 0.1, 0.3]))
    g0 = SE3.from_rotation_translation(R0, jnp.array([1.0, 0.0, 0.0]))
    xi0 = jnp.concatenate([jnp.array([0.5, -0.3, 1.2]), R0.T @ jnp.array([0.0, 1.0, 0.0])])
    return body, g0, body.tensor @ xi0


def falling_problem():
    """A tumbling body in free fall, its centre of mass off the body origin."""
    body = lievi.RigidBodySE3(
        jnp.array([1.0, 2.0, 3.0]),
        2.0,
        potential=lievi.UniformGravitySE3(2.0, 9.81, jnp.array([0.1, 0.0, 0.05])),
    )
    m0 = body.tensor @ jnp.array([1.0, 3.0, -0.5, 1.0, 0.0, 5.0])
    return body, SE3.identity(), m0


PROBLEMS = {
    "kirchhoff": kirchhoff_problem,
    "satellite": satellite_problem,
    "falling": falling_problem,
}


def observed_order(system, integrator, g0, m0, T, hs):
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, [0.0, T])
    errors = []
    for h in hs:
        g, m, ok = final_state(system, integrator, g0, m0, jnp.asarray(h), int(round(T / h)))
        assert ok
        errors.append(max(np.max(np.abs(m - m_ref[-1])), np.max(np.abs(g - g_ref[-1]))))
    return np.polyfit(np.log(hs), np.log(errors), 1)[0], errors


STEP = {"kirchhoff": 0.05, "satellite": 0.01, "falling": 0.05}
DEFAULT_STEPS = 1_000
# The falling body speeds up without bound: after 200 steps (10 s) its step moves it by
# ~5 body lengths. Much further (~500 steps) the Newton residual's round-off floor,
# ~ε·|P|·|h v|, exceeds DEP's default tolerance 64ε·|m| (pass a larger `rtol` there).
FALLING_STEPS = 200


@functools.cache
def _run(problem, chart, n_steps=None, save_every=1):
    """One `simulate` run, shared by the tests that look at the same trajectory (each
    distinct run compiles a solver)."""
    if n_steps is None:
        n_steps = FALLING_STEPS if problem == "falling" else DEFAULT_STEPS
    body, g0, m0 = PROBLEMS[problem]()
    sol = lievi.simulate(
        body,
        lievi.DEP(chart=chart),
        g0,
        m0,
        h=STEP[problem],
        n_steps=n_steps,
        save=lievi.Save(every=save_every),
    )
    assert sol.result == lievi.RESULTS.successful
    return body, sol


# ---- variational structure ------------------------------------------------------------------


# Each case compiles its own solver: the extended set covers both charts and all three
# problems in three cases, the slow set every combination.
SLOW, EXTENDED = pytest.mark.slow, pytest.mark.extended
DEL_CASES = [
    pytest.param("exp", "kirchhoff", marks=EXTENDED),  # 14 s
    pytest.param("cayley", "satellite", marks=EXTENDED),  # 18 s
    pytest.param("exp", "falling", marks=EXTENDED),  # 10 s
    pytest.param("cayley", "kirchhoff", marks=SLOW),
    pytest.param("exp", "satellite", marks=SLOW),
    pytest.param("cayley", "falling", marks=SLOW),
]


@pytest.mark.parametrize("chart, problem", DEL_CASES)
def test_del_residual(chart, problem):
    """The DEP trajectory on SE(3) is a critical point of the action sum (Theorem 2.1),
    with and without a potential."""
    body, sol = _run(problem, chart)
    residual = dg.del_residual(body, lievi.DEP(chart=chart), sol.g[:41], STEP[problem])
    scale = max(1.0, float(jnp.max(jnp.abs(sol.m))))
    assert float(jnp.max(jnp.abs(residual))) <= ROUNDOFF * scale


# ---- order --------------------------------------------------------------------------------


ORDER_CASES = [
    pytest.param("exp", "satellite", marks=EXTENDED),  # 22 s
    pytest.param("cayley", "kirchhoff", marks=SLOW),
    pytest.param("exp", "kirchhoff", marks=SLOW),
    pytest.param("cayley", "satellite", marks=SLOW),
]


@pytest.mark.parametrize("chart, problem", ORDER_CASES)
def test_dep_second_order(chart, problem):
    body, g0, m0 = PROBLEMS[problem]()
    T, h0 = (0.5, 0.01) if problem == "satellite" else (1.0, 0.05)
    order, errors = observed_order(
        body, lievi.DEP(chart=chart), g0, m0, T, [h0 / 2**k for k in range(3)]
    )
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


@pytest.mark.slow
@pytest.mark.parametrize(
    "integrator, expected",
    [(lievi.RK4(), 4), (lievi.Composition(lievi.DEP(chart="exp"), order=4), 4)],
    ids=("rk4", "composition-dep-exp"),
)
def test_higher_order_integrators(integrator, expected):
    body, g0, m0 = falling_problem()
    order, errors = observed_order(body, integrator, g0, m0, 1.0, [0.1 / 2**k for k in range(3)])
    assert abs(order - expected) <= 0.25, (order, errors)


@pytest.mark.slow
def test_falling_body_second_order():
    body, g0, m0 = falling_problem()
    order, errors = observed_order(body, lievi.DEP(), g0, m0, 1.0, [0.05 / 2**k for k in range(3)])
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


# ---- conservation ---------------------------------------------------------------------------


def _energy_bounded(body, sol, amplitude, growth=True):
    energy = np.asarray(dg.energy(body, sol.g, sol.m))
    error = (energy - energy[0]) / abs(energy[0])
    tenth = len(error) // 10
    first, last = np.max(np.abs(error[:tenth])), np.max(np.abs(error[-tenth:]))
    assert np.max(np.abs(error)) <= amplitude
    if growth:  # bounded: no growth of the oscillation (needs a first tenth long enough
        # to contain the oscillation's slowest modulation)
        assert last <= 1.5 * first + 10 * ROUNDOFF


@pytest.mark.parametrize(
    "chart",
    (pytest.param("exp", marks=EXTENDED), pytest.param("cayley", marks=SLOW)),  # exp: 23 s
)
def test_kirchhoff_conservation(chart, n_steps=None, save_every=1):
    """Casimirs |P|², P·Π and the spatial momentum to round-off; energy bounded; g rigid.

    The angular part of the spatial momentum, `RΠ + p × RP`, is measured against the size
    of its terms, `|p|·|P|`: a body in a fluid drifts away (|p| ≈ 2100 after 1e5 steps
    here) and the position `p = Σ R_k t_k` carries one rounding of `ε|p|` per step, which
    no integrator can avoid in floating point (measured: 7e-11 relative to |L|, 3e-14
    relative to `|p|·|P|`, after 1e5 steps).
    """
    body, sol = _run("kirchhoff", chart, n_steps, save_every)
    assert float(dg.relative_drift(dg.casimirs(body, sol.m))) <= ROUNDOFF
    spatial = np.asarray(dg.spatial_momentum(body, sol.g, sol.m))
    assert float(dg.relative_drift(spatial[:, 3:])) <= ROUNDOFF  # linear momentum RP
    scale = np.max(np.linalg.norm(np.asarray(sol.g[:, :3, 3]), axis=-1)) * np.linalg.norm(
        spatial[0, 3:]
    )
    scale = max(scale, np.max(np.abs(spatial[0, :3])))
    assert np.max(np.abs(spatial[:, :3] - spatial[0, :3])) <= ROUNDOFF * scale
    assert float(jnp.max(dg.orthogonality_defect(body, sol.g))) <= ROUNDOFF
    _energy_bounded(body, sol, 1e-2)


@pytest.mark.parametrize("chart", (pytest.param("exp", marks=SLOW), "cayley"))
def test_full_body_angular_momentum(chart, n_steps=None, save_every=1):
    """Total angular momentum about the planet (orbit + spin) to round-off, while the
    orbital part alone changes; energy bounded.

    The rotation block stays orthogonal to a few ulps at every step, not a random walk
    of them (`SE3.compose` re-orthonormalises): the spatial torque `Rτ + p × Rf` of
    central gravity vanishes only for orthogonal `R`, so an accumulated defect `δ` makes
    every kick inject ~`δ·h|p||f|` of angular momentum, coherently (measured before
    the fix: defect 25 ulps after 1e3 steps, drift 5.6e-12 after 1e5)."""
    body, sol = _run("satellite", chart, n_steps, save_every)
    total = dg.spatial_momentum(body, sol.g, sol.m)[:, :3]
    assert float(dg.relative_drift(total)) <= ROUNDOFF
    R = np.asarray(sol.g[:, :3, :3])
    defect = np.abs(np.einsum("kji,kjl->kil", R, R) - np.eye(3)).max()
    assert defect <= 4 * np.finfo(np.float64).eps
    p, R, P = sol.g[:, :3, 3], sol.g[:, :3, :3], sol.m[:, 3:]
    orbital = jnp.cross(p, jnp.einsum("tij,tj->ti", R, P))
    assert float(dg.relative_drift(orbital)) >= 1e-3  # the exchange is real
    # The satellite's energy error is modulated over ~2e4 steps (Cayley, measured: window
    # maxima 5e-5 … 1.3e-4 over 4e4 steps, up and down again), so first-vs-last-tenth growth
    # is judged only over 1e5 steps (`test_full_body_angular_momentum_1e5_steps`).
    _energy_bounded(body, sol, 1e-3, growth=False)


@pytest.mark.extended  # 21 s
def test_free_fall_momenta():
    """Uniform gravity: the spatial linear momentum falls by exactly m γ h per step and
    the vertical angular momentum is conserved (rotations about e₃ leave V unchanged)."""
    body, sol = _run("falling", "exp")
    spatial = dg.spatial_momentum(body, sol.g, sol.m)
    linear = spatial[:, 3:] - spatial[0, 3:]
    expected = -2.0 * 9.81 * np.asarray(sol.ts)[:, None] * np.array([0.0, 0.0, 1.0])
    assert float(jnp.max(jnp.abs(linear - expected))) <= ROUNDOFF * float(jnp.max(jnp.abs(spatial)))
    # Angular momentum about the world's vertical through the origin, L₃ = e₃·(RΠ + p × RP).
    assert float(dg.relative_drift(spatial[:, 2])) <= ROUNDOFF * 10


@pytest.mark.slow
@pytest.mark.parametrize("chart", CHARTS)
def test_kirchhoff_conservation_1e5_steps(chart):
    test_kirchhoff_conservation(chart, n_steps=100_000, save_every=100)


@pytest.mark.slow
@pytest.mark.parametrize("chart", CHARTS)
def test_full_body_angular_momentum_1e4_steps(chart):
    test_full_body_angular_momentum(chart, n_steps=10_000, save_every=10)


@pytest.mark.slow
@pytest.mark.parametrize("chart", CHARTS)
def test_full_body_angular_momentum_1e5_steps(chart):
    """Over 1e5 steps (160 orbits) the total angular momentum holds 1e-12 relative
    (measured at step 1e5: 2.3e-14 exp chart, 2.9e-14 Cayley: a random walk of round-off)."""
    body, sol = _run("satellite", chart, 100_000, 100)
    total = dg.spatial_momentum(body, sol.g, sol.m)[:, :3]
    assert float(dg.relative_drift(total)) <= ROUNDOFF
    _energy_bounded(body, sol, 1e-3)


@pytest.mark.slow  # float32 values and gradients of SE3 itself stay in test_se3.py
def test_float32_kirchhoff():
    """A float32 run stays finite, on its coadjoint orbit to float32 round-off."""
    body, g0, m0 = kirchhoff_problem()
    body32 = lievi.RigidBodySE3(tensor=body.tensor.astype(jnp.float32))
    sol = lievi.simulate(
        body32,
        lievi.DEP(),
        g0.astype(jnp.float32),
        m0.astype(jnp.float32),
        h=jnp.float32(0.05),
        n_steps=200,
    )
    assert sol.m.dtype == jnp.float32
    assert float(dg.relative_drift(dg.casimirs(body32, sol.m))) <= 1e-5


# ---- bad input --------------------------------------------------------------------------------


def test_bad_tensor_is_rejected():
    M = np.diag([1.0, 1.0, 1.0, 1.0, 1.0, -1.0])
    with pytest.raises(ValueError, match="`tensor` must be positive definite"):
        lievi.RigidBodySE3(tensor=jnp.asarray(M))
    N = np.eye(6)
    N[0, 5] = 0.5
    with pytest.raises(ValueError, match="`tensor` must be symmetric"):
        lievi.RigidBodySE3(tensor=jnp.asarray(N))
    with pytest.raises(ValueError, match=r"`tensor` must be a \(6, 6\)"):
        lievi.RigidBodySE3(tensor=jnp.eye(3))
    with pytest.raises(ValueError, match="`mass` must be > 0"):
        lievi.RigidBodySE3(jnp.ones(3), -1.0)
    with pytest.raises(ValueError, match="`inertia` must be positive definite"):
        lievi.RigidBodySE3(jnp.array([1.0, -1.0, 1.0]), 1.0)
    with pytest.raises(ValueError, match="Give `inertia` and `mass`"):
        lievi.RigidBodySE3(jnp.ones(3))


def test_positive_definite_check_agrees_with_eigenvalues():
    """The traced positive-definiteness test of `spd_conditions` against `eigvalsh`, on a
    batch of symmetric matrices of every size it unrolls or loops over (definite and
    indefinite, the smallest eigenvalue well away from 0), and NaN or 0 rejected."""
    from lievi._checks import _positive_definite

    rng = np.random.default_rng(3)
    for k in (1, 2, 3, 6, 8):
        A = rng.normal(size=(64, k, k))
        S = A @ np.swapaxes(A, -1, -2) - rng.uniform(0, 2, size=(64, 1, 1)) * np.eye(k)
        smallest = np.linalg.eigvalsh(S)[:, 0]
        keep = np.abs(smallest) > 1e-6
        assert keep.sum() > 40 and 0 < (smallest[keep] > 0).sum() < keep.sum()
        got = np.asarray(jax.vmap(_positive_definite)(jnp.asarray(S[keep])))
        np.testing.assert_array_equal(got, smallest[keep] > 0)
    assert not _positive_definite(jnp.full((6, 6), jnp.nan))
    assert not _positive_definite(jnp.zeros((6, 6)))


def test_positive_definite_check_is_one_small_program():
    """The check loops over the columns (one elimination step compiled once): its program
    does not grow with `k`, and the 6×6 one of `RigidBodySE3` stays small (unrolled, it
    was 254 instructions before optimisation, with a fused loop per division)."""
    from lievi._checks import _positive_definite

    def size(k):
        return jax.jit(_positive_definite).lower(jnp.eye(k)).as_text().count(" = ")

    assert size(6) == size(3) == size(8)
    assert size(6) <= 100


@pytest.mark.parametrize(
    "g0",
    [
        np.diag([1.0, 1.0, 1.01, 1.0]),  # rotation block not orthogonal
        np.diag([1.0, 1.0, -1.0, 1.0]),  # a reflection
        np.array([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0.5, 0, 0, 1]]),  # last row
    ],
    ids=("not-orthogonal", "reflection", "last-row"),
)
def test_non_rigid_g0_is_rejected(g0):
    body, _, m0 = kirchhoff_problem()
    with pytest.raises(ValueError, match=r"`g0` is not in the group.*last row \(0, 0, 0, 1\)"):
        lievi.simulate(body, lievi.DEP(), jnp.asarray(g0), m0, h=0.1, n_steps=1)


# ---- the closed-form DEP step ---------------------------------------------------------------


@pytest.mark.parametrize(
    "chart, gradients",
    [
        pytest.param("exp", False, marks=EXTENDED),  # 15 s
        pytest.param("exp", True, marks=SLOW),
        pytest.param("cayley", True, marks=SLOW),
    ],
)
def test_closed_form_step_equals_generic(chart, gradients):
    """`RigidBodySE3`'s DEP step (closed forms, the batch kernel `_kernels/_se3.py` on one
    body) against the generic path (`jax.jacfwd` of the residual built from
    `SE3.dexpinv`/`dcayinv`, `linalg.solve`): the 6×6 residual, Jacobian and block solve at
    rotation angles 1e-9 … 2.5, the step, and (slow set) gradients through the implicit
    derivative."""
    from lievi._kernels import _se3, _se3_residual

    rng = np.random.default_rng(3)
    B = rng.normal(size=(6, 6))
    M = jnp.asarray(B @ B.T / 6 + np.eye(6))
    body, h = lievi.RigidBodySE3(tensor=M), 0.1
    dchart_inverse = SE3.dexpinv if chart == "exp" else SE3.dcayinv
    A = tuple(tuple(M[i, j] / h for j in range(6)) for i in range(6))

    @jax.jit
    @jax.vmap
    def errors(xi, m):
        def generic(x):
            return dchart_inverse(x).T @ (M @ x / h) - m

        r, J = _se3_residual.residual(chart, tuple(xi), tuple(m), A, True)
        solved = jnp.stack(_se3_residual.solve6(_se3_residual.factor(J), r))
        r, J = jnp.stack(r), jnp.stack([jnp.stack(row) for row in J])
        return (
            jnp.max(jnp.abs(r - generic(xi))),
            jnp.max(jnp.abs(J - jax.jacfwd(generic)(xi))) / jnp.max(jnp.abs(J)),
            jnp.max(jnp.abs(solved - jnp.linalg.solve(J, r))),
        )

    angles = jnp.array([1e-9, 1e-3, 0.3, 2.5])
    xi = jnp.asarray(rng.normal(size=(4, 6)))
    xi = xi.at[:, :3].set(
        angles[:, None] * xi[:, :3] / jnp.linalg.norm(xi[:, :3], axis=-1)[:, None]
    )
    for error in errors(xi, jnp.asarray(rng.normal(size=(4, 6)))):
        assert float(jnp.max(error)) <= ROUNDOFF

    dep = lievi.DEP(chart=chart)
    phi = SE3.exp if chart == "exp" else SE3.cay
    g = SE3.exp(jnp.asarray(rng.normal(size=6)))
    weights = jnp.arange(16.0).reshape(4, 4)

    def fast(m, M):
        g1, m1, info = dep.free_step(lievi.RigidBodySE3(tensor=M), g, m, h)
        return jnp.sum(jnp.sin(m1)) + jnp.sum(weights * g1**2), (g1, m1, info)

    def reference(m, M):
        xi, info = dep.solve_increment(lievi.RigidBodySE3(tensor=M), m, h)
        F = phi(xi)
        g1, m1 = SE3.compose(g, F), SE3.Ad(F).T @ m
        return jnp.sum(jnp.sin(m1)) + jnp.sum(weights * g1**2), (g1, m1, info)

    m = body.tensor @ jnp.asarray(rng.normal(size=6))
    if gradients:  # the implicit derivative (slow set: compiling both reverse passes)
        (_, (g1, m1, info)), grads = jax.jit(jax.value_and_grad(fast, (0, 1), has_aux=True))(m, M)
        (_, (g2, m2, info2)), grads2 = jax.jit(jax.value_and_grad(reference, (0, 1), has_aux=True))(
            m, M
        )
    else:
        (_, (g1, m1, info)), (_, (g2, m2, info2)) = jax.jit(fast)(m, M), jax.jit(reference)(m, M)
        grads = grads2 = ()
    assert info.result == lievi.RESULTS.successful
    # A chord step and two Newton steps (`_se3.DEFAULT_FIXED_ITERATIONS`), where the
    # generic path stops at convergence.
    assert int(info.iterations) == _se3.DEFAULT_FIXED_ITERATIONS[chart]
    assert int(info2.iterations) >= 2
    assert float(jnp.max(jnp.abs(g1 - g2))) <= ROUNDOFF
    assert float(jnp.max(jnp.abs(m1 - m2))) <= ROUNDOFF
    for a, b in zip(grads, grads2):
        assert float(jnp.max(jnp.abs(a - b))) <= ROUNDOFF * float(jnp.max(jnp.abs(b)))
