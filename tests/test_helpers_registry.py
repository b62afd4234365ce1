"""Every public helper around `simulate` against every kind of state: one body, a batch of
bodies, and a system of several bodies (`lievi.RigidRotors` free, `lievi.RigidBodies`
coupled by a spring).

Each pair either runs and returns values of the right shapes (finite, and where cheap
checked against a second computation), or raises a `ValueError` whose message names the
argument and the shape it expects — never a raw `TypeError`, an einsum or a reshape
error. The helpers that compile a solver of their own (`suggest_integrator`'s pilot,
`fit_system`, `solve_optimal_control`) run tiny problems, under `-m extended`; their
refusals of a batch are in the default suite.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem
from lievi import diagnostics as dg

SE3, SO3 = lievi.SE3, lievi.SO3
H = 0.1
EXTENDED = pytest.mark.extended


def one():
    return hlw_problem()


def batch():
    body, g0, m0 = hlw_problem()
    return body, jnp.stack([g0, SO3.exp(jnp.array([0.1, 0.2, 0.3]))]), jnp.stack([m0, 2 * m0])


def rotors():
    system = lievi.RigidRotors(jnp.array([[1.0, 2.0, 3.0], [2.0, 2.5, 3.0]]))
    g0 = SO3.exp(jnp.array([[0.2, 0.0, -0.1], [0.0, 0.3, 0.1]]))
    return system, g0, jnp.array([[0.5, -0.3, 0.8], [0.2, 0.6, -0.4]])


def spring(g):
    return 0.5 * jnp.sum((SE3.translation(g[0]) - SE3.translation(g[1])) ** 2)


def bodies():
    system = lievi.RigidBodies(
        jnp.array([[1.0, 2.0, 3.0], [2.0, 2.5, 3.0]]), jnp.array([1.0, 2.0]), potential=spring
    )
    R = SO3.exp(jnp.array([[0.1, -0.2, 0.3], [0.4, 0.1, -0.2]]))
    g0 = SE3.from_rotation_translation(R, jnp.array([[0.0, 0.0, 0.0], [1.5, 0.2, 0.0]]))
    m0 = jnp.array([[0.3, -0.2, 0.5, 0.1, 0.2, 0.0], [-0.1, 0.4, 0.2, 0.0, -0.3, 0.1]])
    return system, g0, m0


KINDS = {"one": one, "batch": batch, "rotors": rotors, "bodies": bodies}


def _leading(system, m):
    """The batch axes of `m` in front of one state's momentum."""
    return m.shape[: m.ndim - len(system.momentum_shape())]


def _trajectory(system, g0, m0, n_steps=4):
    """`(T, *element_shape)`, or `(B, T, …)` for a batch of states."""
    if _leading(system, m0):
        return lievi.simulate_batch(
            system,
            lievi.DEP(),
            g0,
            m0,
            h=H,
            n_steps=n_steps,
            save=lievi.Save(m=False, stats=False),
        ).g
    return lievi.simulate(system, lievi.DEP(), g0, m0, h=H, n_steps=n_steps, save=lievi.Save()).g


# ---- the diagnostics and the reference solution ------------------------------------------


def energy(system, g0, m0, kind):
    E = dg.energy(system, g0, m0)
    assert E.shape == _leading(system, m0) and np.all(np.isfinite(E))
    if kind == "batch":  # each state's own
        np.testing.assert_allclose(E[1], dg.energy(system, g0[1], m0[1]), rtol=ROUNDOFF)


def total_momentum(system, g0, m0, kind):
    total = dg.total_momentum(system, g0, m0)
    d = system.group.algebra_dim
    assert total.shape == _leading(system, m0) + (d,) and np.all(np.isfinite(total))
    spatial = dg.spatial_momentum(system, g0, m0)
    # The sum over the bodies of each body's spatial momentum (one body: itself).
    bodies = spatial.reshape(*_leading(system, m0), -1, d)
    np.testing.assert_allclose(total, bodies.sum(axis=-2), rtol=0, atol=ROUNDOFF)


def poisson_defect(system, g0, m0, kind):
    if kind == "batch":
        with pytest.raises(ValueError, match=r"`g` must have shape \(3, 3\)"):
            dg.poisson_defect(system, lievi.DEP(), g0, m0, H)
        return
    defect = dg.poisson_defect(system, lievi.DEP(), g0, m0, H)
    assert defect.shape == ()
    if system.potential is None:  # a free system's DLP map is Poisson (Proposition 3.1)
        assert defect <= ROUNDOFF


def del_residual(system, g0, m0, kind):
    g = _trajectory(system, g0, m0)
    if kind == "batch":
        with pytest.raises(ValueError, match=r"one trajectory of shape \(T, 3, 3\)"):
            dg.del_residual(system, lievi.DEP(), g, H)
        return
    residual = dg.del_residual(system, lievi.DEP(), g, H)
    assert residual.shape == (g.shape[0] - 2, *system.momentum_shape())
    assert float(jnp.max(jnp.abs(residual))) <= ROUNDOFF  # DEP is variational (Theorem 2.1)


def reference_solution(system, g0, m0, kind):
    if kind == "batch":
        with pytest.raises(ValueError, match=r"`g0` must have shape \(3, 3\)"):
            lievi.reference_solution(system, g0, m0, [0.0, H])
        return
    g, m = lievi.reference_solution(system, g0, m0, [0.0, H, 2 * H])
    assert g.shape == (3, *system.element_shape()) and m.shape == (3, *system.momentum_shape())
    # Against two steps of RK4 at h/10 (fourth order: 1e-9 of the motion).
    sol = lievi.simulate(system, lievi.RK4(), g0, m0, h=H / 10, n_steps=20)
    np.testing.assert_allclose(g[-1], sol.g[-1], rtol=0, atol=1e-8)
    np.testing.assert_allclose(m[-1], sol.m[-1], rtol=0, atol=1e-8)


# ---- the helpers that compile a solver of their own ------------------------------------


def suggest_integrator(system, g0, m0, kind):
    options = dict(horizon=0.4, tolerance=1e-4, candidates=(lievi.DEP(),), batch=2)
    if kind == "batch":
        with pytest.raises(ValueError, match=r"`g0` must have shape \(3, 3\)"):
            lievi.suggest_integrator(system, g0, m0, **options)
        return
    s = lievi.suggest_integrator(system, g0, m0, **options)
    assert s.n_steps * s.h == pytest.approx(0.4, rel=1e-12)
    assert 0 < s.predicted_error <= 1e-4 * (1 + 1e-9)


def fit_system(system, g0, m0, kind):
    """Two iterations from the truth's own parameters, `g0` and `m0` known: the samples
    are read as samples (shapes), and the fit stays at the data (loss at round-off)."""
    n_steps, every = 4, 2
    trajectory = _trajectory(system, g0, m0, n_steps)
    samples = jnp.arange(0, n_steps + 1, every)
    g = jnp.take(trajectory, samples, axis=len(_leading(system, m0)))
    params = (lambda s: s.mass) if isinstance(system, lievi.RigidBodies) else (lambda s: s.inertia)
    fit = lievi.fit_system(
        system, g, h=H, sample_every=every, params=params, g0=g0, m0=m0, max_iters=2
    )
    assert fit.m0.shape == m0.shape
    assert jnp.shape(params(fit.system)) == _leading(system, m0) + jnp.shape(params(system))
    assert np.all(np.asarray(fit.loss) <= ROUNDOFF)


def solve_optimal_control(system, g0, m0, kind):
    target = (g0, jnp.zeros_like(m0))
    options = dict(max_iterations=1, max_inner_iterations=2)
    if kind == "batch":
        with pytest.raises(ValueError, match=r"`g0` must have shape \(3, 3\)"):
            lievi.solve_optimal_control(system, lievi.DEP(), g0, m0, target, 2, H, **options)
        return
    r = lievi.solve_optimal_control(system, lievi.DEP(), g0, m0, target, 2, H, **options)
    assert r.controls.shape == (2, *system.momentum_shape())
    assert r.solution.g.shape == (3, *system.element_shape())
    assert np.isfinite(r.constraint_violation) and r.iterations == 1


CHEAP = (energy, total_momentum, poisson_defect, del_residual, reference_solution)
COMPILING = (suggest_integrator, fit_system, solve_optimal_control)


def _cases():
    for helper in CHEAP + COMPILING:
        for kind in KINDS:
            # A refusal is cheap; a run of a compiling helper is extended.
            refused = kind == "batch" and helper is not fit_system
            # The Jacobian and the DEL gradient through the coupled SE(3) step compile for
            # a minute on a loaded 2-core machine: extended too.
            heavy = (helper in COMPILING and not refused) or (
                kind == "bodies" and helper in (poisson_defect, del_residual)
            )
            marks = (EXTENDED,) if heavy else ()
            yield pytest.param(helper, kind, marks=marks, id=f"{helper.__name__}-{kind}")


@pytest.mark.parametrize("helper, kind", list(_cases()))
def test_helper_on_kind(helper, kind):
    system, g0, m0 = KINDS[kind]()
    helper(system, g0, m0, kind)
