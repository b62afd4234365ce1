"""N interacting rigid rotors on SO(3)ᴺ (`lievi.RigidRotors`) and `lievi.DipoleCoupling`.

Decided by checks that do not depend on lievi's own derivation: one rotor equals
`RigidBody`; the order against DOP853 on Euler's equations written here with the world
rotation matrices (torques from the Euclidean gradient `∂V/∂R`); exact conservation of
the total spatial angular momentum `Σ R_i Π_i` for a coupling of the relative rotations
(and of its axial component for dipoles on one line); the gradient against central
differences. Float64. Long runs are in the slow set.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, dop853_final, final_state
from lievi import diagnostics as dg

SO3 = lievi.SO3
SLOW = pytest.mark.slow


def _rotations(rng, n):
    return jnp.stack([SO3.exp(jnp.asarray(rng.normal(size=3))) for _ in range(n)])


# Three rotors with generic inertias, the second a full tensor (the others principal
# moments are written as diagonal tensors, so one array holds them all).
INERTIA = jnp.array(
    [
        [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]],
        [[2.0, 0.3, -0.1], [0.3, 2.5, 0.2], [-0.1, 0.2, 1.5]],
        [[1.2, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2.0]],
    ]
)
# Body-frame axes of the alignment coupling, one pair per coupled pair of rotors.
AXES = jnp.asarray(np.random.default_rng(7).normal(size=(3, 2, 3)))
PAIRS = ((0, 1), (1, 2), (0, 2))


def alignment(k):
    """`V = −Σ_(i,j) k_ij (R_i a_ij)·(R_j b_ij)`: a coupling of the relative rotations
    `R_iᵀR_j` only, invariant under `R_i ↦ Q R_i` (diagonal SO(3))."""
    k = jnp.broadcast_to(jnp.asarray(k, float), (len(PAIRS),))

    def V(g):
        return -sum(
            k[p] * jnp.dot(g[i] @ AXES[p, 0], g[j] @ AXES[p, 1]) for p, (i, j) in enumerate(PAIRS)
        )

    return V


def alignment_problem(k=(1.0, 0.7, 0.4)):
    rng = np.random.default_rng(1)
    system = lievi.RigidRotors(INERTIA, potential=alignment(k))
    return system, _rotations(rng, 3), jnp.asarray(rng.normal(size=(3, 3)))


def dipole_problem(strength=1.0):
    """Three dipoles on rotors pivoted along the x axis (spacing 1, 1.2)."""
    rng = np.random.default_rng(2)
    positions = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.2, 0.0, 0.0]])
    dipoles = jnp.asarray(rng.normal(size=(3, 3)))
    coupling = lievi.DipoleCoupling(positions, dipoles, strength)
    system = lievi.RigidRotors(
        jnp.array([[1.0, 2.0, 3.0], [2.0, 2.5, 1.5], [1.2, 1.0, 2.0]]), coupling
    )
    return system, _rotations(rng, 3), jnp.asarray(rng.normal(size=(3, 3)))


PROBLEMS = {"alignment": alignment_problem, "dipoles": dipole_problem}


# ---- an independent reference: Euler's equations with world rotation matrices -------------


@functools.cache
def euler_reference(problem, T):
    """`(g, m)` at `T` by DOP853 (rtol = atol = 1e-13) on `J ω̇ = Jω × ω + τ`, `Ṙ = R ω̂`,
    with the body torque `τ = −vee(RᵀG − GᵀR)` from the Euclidean gradient `G = ∂V/∂R`
    (`d/dε V(R(1 + εê)) = tr(GᵀRê)`)."""
    system, g0, m0 = PROBLEMS[problem]()
    n = g0.shape[0]
    J = system.inertia_tensor

    @jax.jit
    def rhs(y):
        R, w = y[: 9 * n].reshape(n, 3, 3), y[9 * n :].reshape(n, 3)
        G = jax.grad(system.potential)(R)
        A = jnp.einsum("nji,njk->nik", R, G)
        S = A - jnp.swapaxes(A, 1, 2)
        torque = -jnp.stack([S[:, 2, 1], S[:, 0, 2], S[:, 1, 0]], axis=1)
        Jw = jnp.einsum("nij,nj->ni", J, w)
        w_dot = jnp.linalg.solve(J, (jnp.cross(Jw, w) + torque)[..., None])[..., 0]
        return jnp.concatenate([(R @ SO3.hat(w)).ravel(), w_dot.ravel()])

    w0 = jnp.linalg.solve(J, m0[..., None])[..., 0]
    y0 = np.concatenate([np.ravel(g0), np.ravel(w0)])
    y = dop853_final(rhs, y0, T)
    R, w = y[: 9 * n].reshape(n, 3, 3), y[9 * n :].reshape(n, 3)
    return R, jnp.einsum("nij,nj->ni", J, w)


ORDER_CASES = [
    pytest.param(lievi.LiePoissonSplitting(), "dipoles", 2, marks=pytest.mark.extended),  # 19 s
    pytest.param(lievi.DEP(chart="cayley"), "alignment", 2, marks=SLOW),
    pytest.param(lievi.DEP(chart="exp"), "dipoles", 2, marks=SLOW),
    pytest.param(lievi.MoserVeselov(), "alignment", 2, marks=SLOW),
    pytest.param(
        lievi.Composition(lievi.LiePoissonSplitting(), order=4),
        "alignment",
        4,
        marks=pytest.mark.extended,  # 10 s
    ),
    pytest.param(lievi.Composition(lievi.DEP(chart="exp"), order=4), "dipoles", 4, marks=SLOW),
    pytest.param(lievi.RK4(), "alignment", 4, marks=SLOW),
    (lievi.RKMK4(), "alignment", 4),  # on the product group: each body's `exp`, `dexpinv`
]


@pytest.mark.parametrize("integrator, problem, expected", ORDER_CASES)
def test_order(integrator, problem, expected):
    """The observed order over h = 0.04, 0.02, 0.01 to T = 0.8 within 5 % of the method's
    (the reference's own error, ~1e-12, is far below the order-4 errors, ~1e-8)."""
    T, hs = 0.8, [0.04 / 2**k for k in range(3)]
    system, g0, m0 = PROBLEMS[problem]()
    g_ref, m_ref = euler_reference(problem, T)
    errors = []
    for h in hs:
        g, m, ok = final_state(system, integrator, g0, m0, jnp.asarray(h), int(round(T / h)))
        assert ok
        errors.append(max(float(jnp.max(jnp.abs(m - m_ref))), float(jnp.max(jnp.abs(g - g_ref)))))
    order = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    assert abs(order - expected) <= 0.1 * expected / 2, (order, errors)


# ---- one rotor -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "integrator",
    (
        pytest.param(lievi.DEP(chart="exp"), marks=pytest.mark.extended),  # 14 s
        lievi.LiePoissonSplitting(),
        pytest.param(lievi.DEP(chart="cayley"), marks=SLOW),
        pytest.param(lievi.MoserVeselov(), marks=SLOW),
    ),
)
def test_one_rotor_equals_rigid_body(integrator):
    """N = 1 is `RigidBody` with the same potential (a heavy top, `V = mγ e_z·Rρ`, written
    as a function of `g`), to round-off: ≤ 1e-13 in `g` and relative to |m| in `m`."""
    rng = np.random.default_rng(5)
    inertia = jnp.array([1.0, 2.0, 3.0])
    rho = jnp.array([0.1, -0.2, 0.5])

    def top(R):
        return 2.0 * 9.81 * (R @ rho)[2]

    one = lievi.RigidBody(inertia, potential=top)
    many = lievi.RigidRotors(inertia[None], potential=lambda g: top(g[0]))
    g0, m0 = SO3.exp(jnp.asarray(rng.normal(size=3))), jnp.asarray(rng.normal(size=3))
    a = lievi.simulate(many, integrator, g0[None], m0[None], h=0.02, n_steps=100)
    b = lievi.simulate(one, integrator, g0, m0, h=0.02, n_steps=100)
    assert a.g.shape == (101, 1, 3, 3) and a.m.shape == (101, 1, 3)
    assert float(jnp.max(jnp.abs(a.g[:, 0] - b.g))) <= 1e-13
    assert float(jnp.max(jnp.abs(a.m[:, 0] - b.m))) <= 1e-13 * float(jnp.max(jnp.abs(b.m)))


# ---- conservation ----------------------------------------------------------------------------


@functools.cache
def _run(problem, integrator, n_steps=3_000):
    system, g0, m0 = PROBLEMS[problem]()
    sol = lievi.simulate(
        system, integrator, g0, m0, h=0.01, n_steps=n_steps, save=lievi.Save(every=10)
    )
    assert sol.result == lievi.RESULTS.successful
    return system, sol


def _momentum_error(system, sol, axis=None):
    """`max_k |J_k − J_0|` relative to the size of its terms `Σ_i |Π_i|` (`J` the total
    spatial angular momentum, or its component along `axis`)."""
    L = dg.total_momentum(system, sol.g, sol.m)
    if axis is not None:
        L = L @ axis
    scale = float(jnp.max(jnp.sum(jnp.linalg.norm(sol.m, axis=-1), axis=-1)))
    return float(jnp.max(jnp.abs(L - L[0]))) / scale


def _energy_error(system, sol):
    energy = np.asarray(dg.energy(system, sol.g, sol.m))
    return np.max(np.abs(energy - energy[0])) / abs(energy[0])


CONSERVATION_CASES = [
    lievi.LiePoissonSplitting(),
    pytest.param(lievi.DEP(chart="cayley"), marks=SLOW),
    pytest.param(lievi.DEP(chart="exp"), marks=SLOW),
    pytest.param(lievi.MoserVeselov(), marks=SLOW),
    pytest.param(lievi.Composition(lievi.DEP(chart="cayley"), order=4), marks=SLOW),
]


@pytest.mark.parametrize("integrator", CONSERVATION_CASES)
def test_total_momentum_and_energy(integrator):
    """A coupling of the relative rotations, 3000 steps of h = 0.01: the total spatial
    angular momentum `Σ R_i Π_i` to ≤ 1e-12 relative (discrete Noether), the energy error
    within its O(h²) amplitude, ≤ 1e-3 relative."""
    system, sol = _run("alignment", integrator)
    assert _momentum_error(system, sol) <= ROUNDOFF
    assert _energy_error(system, sol) <= 1e-3


@pytest.mark.parametrize("integrator", (lievi.LiePoissonSplitting(),))
def test_dipoles_on_a_line_conserve_the_axial_momentum_only(integrator):
    """Dipoles pivoted on the x axis: the V is invariant under rotations about x only, so
    `e_x · Σ R_i Π_i` is conserved to ≤ 1e-12 and the other components are not."""
    system, sol = _run("dipoles", integrator)
    assert _momentum_error(system, sol, axis=jnp.array([1.0, 0.0, 0.0])) <= ROUNDOFF
    assert _momentum_error(system, sol, axis=jnp.array([0.0, 1.0, 0.0])) > 1e-3
    assert _energy_error(system, sol) <= 1e-3


@pytest.mark.extended  # 11 s
def test_free_rotors_keep_each_body_casimir_and_momentum():
    """Without a coupling every rotor is a free rigid body: its |Π_i| and its `R_i Π_i`
    conserved to round-off, and `total_momentum` is the sum of the `spatial_momentum`s."""
    system, g0, m0 = alignment_problem()
    free = lievi.RigidRotors(system.inertia)
    sol = lievi.simulate(free, lievi.DEP(chart="cayley"), g0, m0, h=0.01, n_steps=500)
    norms = jnp.linalg.norm(sol.m, axis=-1)
    assert float(jnp.max(jnp.abs(norms - norms[0]))) <= ROUNDOFF * float(jnp.max(norms))
    spatial = jnp.einsum("tnij,tnj->tni", sol.g, sol.m)
    assert float(jnp.max(jnp.abs(spatial - spatial[0]))) <= ROUNDOFF * float(jnp.max(norms))
    each = [lievi.RigidBody(INERTIA[i]) for i in range(3)]
    assert jnp.allclose(
        dg.total_momentum(free, g0, m0),
        sum(dg.spatial_momentum(b, g0[i], m0[i]) for i, b in enumerate(each)),
        rtol=ROUNDOFF,
        atol=ROUNDOFF,
    )
    assert jnp.allclose(
        dg.energy(free, None, m0), sum(b.energy(m0[i]) for i, b in enumerate(each)), rtol=ROUNDOFF
    )


# ---- gradients -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "integrator",
    (
        pytest.param(lievi.LiePoissonSplitting(), marks=pytest.mark.extended),  # 17 s
        pytest.param(lievi.DEP(chart="cayley"), marks=SLOW),
    ),
)
def test_gradient_of_coupling_parameter(integrator):
    """d(final state)/d(dipole strength) equals central differences (step 1e-5) to ≤ 1e-6
    relative (through the implicit differentiation of each body's Newton solve, for DEP)."""
    _, g0, m0 = dipole_problem()

    @jax.jit
    def loss(strength):
        system, _, _ = dipole_problem(strength)
        sol = lievi.simulate(
            system, integrator, g0, m0, h=0.02, n_steps=50, save=lievi.Save(every=50)
        )
        return jnp.sum(sol.m[-1] ** 2) + jnp.sum(sol.g[-1, :, :, 0] ** 2)

    strength, step = 1.0, 1e-5
    gradient = float(jax.grad(loss)(strength))
    central = (float(loss(strength + step)) - float(loss(strength - step))) / (2 * step)
    assert abs(gradient - central) <= 1e-6 * abs(central)


# ---- batches of systems ----------------------------------------------------------------------


@pytest.mark.extended  # 13 s
def test_simulate_batch_of_systems():
    """`simulate_batch` over independent rotor systems (a sweep of the dipole strength,
    built with `jax.vmap`, each from its own state) equals one `simulate` each, to
    round-off."""
    system, g0, m0 = dipole_problem()
    strengths = jnp.array([0.5, 1.0, 2.0])
    systems = jax.vmap(lambda s: dipole_problem(s)[0])(strengths)
    m0s = jnp.stack([m0, 0.5 * m0, -m0])
    g0s = jnp.broadcast_to(g0, (3, *g0.shape))
    integrator = lievi.LiePoissonSplitting()
    batch = lievi.simulate_batch(systems, integrator, g0s, m0s, h=0.01, n_steps=20, system_axis=0)
    assert batch.g.shape == (3, 21, 3, 3, 3) and batch.m.shape == (3, 21, 3, 3)
    assert jnp.all(batch.result == lievi.RESULTS.successful)
    for b in range(3):
        one = lievi.simulate(
            dipole_problem(strengths[b])[0], integrator, g0, m0s[b], h=0.01, n_steps=20
        )
        assert float(jnp.max(jnp.abs(batch.m[b] - one.m))) <= ROUNDOFF
        assert float(jnp.max(jnp.abs(batch.g[b] - one.g))) <= ROUNDOFF


# ---- bad input -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "build, match",
    [
        (lambda: lievi.RigidRotors(jnp.ones((2, 2))), "inertia"),
        (lambda: lievi.RigidRotors(jnp.ones(3)), "inertia"),
        (lambda: lievi.RigidRotors(jnp.ones((0, 3))), "inertia"),
        (lambda: lievi.RigidRotors(jnp.array([[1.0, -1.0, 1.0]])), "positive definite"),
        (
            lambda: lievi.RigidRotors(jnp.array([[[1.0, 0.5, 0], [0, 1, 0], [0, 0, 1]]])),
            "symmetric",
        ),
        (lambda: lievi.RigidRotors(jnp.ones((2, 3)) * 1j), "inertia"),
        (lambda: lievi.RigidRotors(jnp.ones((2, 3)), potential=lambda g: g[:, 0, 0]), "potential"),
        (
            lambda: lievi.RigidRotors(
                jnp.ones((3, 3)), lievi.DipoleCoupling(jnp.eye(2, 3), jnp.ones((2, 3)))
            ),
            "potential",
        ),
        (lambda: lievi.DipoleCoupling(jnp.eye(3), jnp.ones((2, 3))), "dipoles"),
        (lambda: lievi.DipoleCoupling(jnp.ones((1, 3)), jnp.ones((1, 3))), "positions"),
        (lambda: lievi.DipoleCoupling(jnp.ones((2, 3)), jnp.ones((2, 3))), "positions"),
        (lambda: lievi.DipoleCoupling(jnp.eye(3), jnp.ones((3, 3)), jnp.ones(2)), "strength"),
    ],
)
def test_bad_input(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_bad_state_shapes():
    system, g0, m0 = alignment_problem()
    with pytest.raises(ValueError, match="g0"):
        lievi.simulate(system, lievi.DEP(), g0[:2], m0, h=0.01, n_steps=1)
    with pytest.raises(ValueError, match="g0"):
        lievi.simulate(
            system, lievi.DEP(), jnp.broadcast_to(jnp.eye(4), (3, 4, 4)), m0, h=0.01, n_steps=1
        )
    with pytest.raises(ValueError, match="m0"):
        lievi.simulate(system, lievi.DEP(), g0, m0[:, :2], h=0.01, n_steps=1)
    with pytest.raises(ValueError, match="g0"):
        lievi.simulate(system, lievi.DEP(), g0.at[1, 0, 0].set(2.0), m0, h=0.01, n_steps=1)
