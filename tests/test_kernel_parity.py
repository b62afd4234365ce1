"""Every fast kernel against the independent reference path.

`reference_path()` turns every kernel off, so the generic step runs: the residual built
from the group and the Lagrangian, its Jacobian by `jax.jacfwd`, the Newton system by
`linalg.solve`, the potential's force by autodiff. The kernels (closed forms on
structure of arrays) must give the same iterates (to 1e-12) and the same gradients (to
1e-10), one body (`simulate`) and batched (`simulate_batch`).

`REGISTRY` lists each (integrator, system) pair that has a kernel; the last test fails if
an integrator gains a kernel for a system that is not registered here.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi._kernels._base import reference_path

ITERATES = 1e-12  # g and m, relative to the momentum scale (float64)
GRADIENTS = 1e-10  # gradients of a loss of the final state, relative
STEPS, H = 12, 0.1

INERTIA = jnp.array([2.0, 1.0, 2 / 3])
SYMMETRIC_INERTIA = jnp.array([1.0, 1.0, 2 / 3])  # `SymmetricTopSplitting`'s bodies
M0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
SE3_TENSOR = lievi._systems._se3_body.rigid_body_tensor(jnp.array([0.5, 0.7, 0.9]), 2.0)
SE3_M0 = jnp.array([0.3, -0.2, 0.5, 0.4, 0.1, -0.3])


def _rigid_body(inertia):
    return lievi.RigidBody(inertia)


def _heavy_top(inertia):
    return lievi.heavy_top(inertia, 1.0, jnp.array([0.1, 0.05, 0.4]), gravity=1.0)


def _se3(tensor):
    return lievi.RigidBodySE3(tensor=tensor)


def _se3_gravity(tensor):
    gravity = lievi.UniformGravitySE3(2.0, 1.0, jnp.array([0.1, 0.05, 0.4]))
    return lievi.RigidBodySE3(tensor=tensor, potential=gravity)


def _rkmk_entries(name, integrator):
    """The four systems with a Lie-group Runge–Kutta kernel: free and heavy-top SO(3),
    free and gravity SE(3)."""
    se3_g0 = lievi.SE3.exp(jnp.array([0.3, -0.2, 0.1, 0.5, 0.0, -0.4]))
    return [
        (name, integrator, _rigid_body, INERTIA, jnp.eye(3), M0, "RKMKKernel"),
        (f"{name}-heavy-top", integrator, _heavy_top, INERTIA, jnp.eye(3), M0, "RKMKKernel"),
        (f"{name}-se3", integrator, _se3, SE3_TENSOR, jnp.eye(4), SE3_M0, "RKMKSE3Kernel"),
        (
            f"{name}-se3-gravity",
            integrator,
            _se3_gravity,
            SE3_TENSOR,
            se3_g0,
            SE3_M0,
            "RKMKSE3Kernel",
        ),
    ]


RKMK_ENTRIES = [
    entry
    for name, integrator in (
        ("rkmk4", lievi.RKMK4()),
        ("rkmk5", lievi.RKMK5()),
        ("rkmk8", lievi.RKMK8()),
    )
    for entry in _rkmk_entries(name, integrator)
]

# (name, integrator, system builder from its parameter, parameter, g0, m0, kernel class)
REGISTRY = [
    ("dep-exp", lievi.DEP(), _rigid_body, INERTIA, jnp.eye(3), M0, "NewtonKernel"),
    ("dep-cayley", lievi.DEP(chart="cayley"), _rigid_body, INERTIA, jnp.eye(3), M0, "NewtonKernel"),
    ("moser-veselov", lievi.MoserVeselov(), _rigid_body, INERTIA, jnp.eye(3), M0, "NewtonKernel"),
    (
        "splitting",
        lievi.LiePoissonSplitting(),
        _rigid_body,
        INERTIA,
        jnp.eye(3),
        M0,
        "SplittingKernel",
    ),
    ("rk4", lievi.RK4(), _rigid_body, INERTIA, jnp.eye(3), M0, "RK4Kernel"),
    (
        "preprocessed-8",
        lievi.PreprocessedMoserVeselov(8),
        _rigid_body,
        INERTIA,
        jnp.eye(3),
        M0,
        "PreprocessedKernel",
    ),
    *RKMK_ENTRIES,
    (
        "composition-splitting-6",
        lievi.Composition(lievi.LiePoissonSplitting(), order=6),
        _rigid_body,
        INERTIA,
        jnp.eye(3),
        M0,
        "CompositionKernel",
    ),
    (
        "composition-dep-4-heavy-top",
        lievi.Composition(lievi.DEP(), order=4),
        _heavy_top,
        INERTIA,
        jnp.eye(3),
        M0,
        "CompositionKernel",
    ),
    (
        "composition-dep-4-se3",
        lievi.Composition(lievi.DEP(), order=4),
        _se3,
        SE3_TENSOR,
        jnp.eye(4),
        SE3_M0,
        "CompositionKernel",
    ),
    ("dep-exp-heavy-top", lievi.DEP(), _heavy_top, INERTIA, jnp.eye(3), M0, "KickKernel"),
    (
        "dep-cayley-heavy-top",
        lievi.DEP(chart="cayley"),
        _heavy_top,
        INERTIA,
        jnp.eye(3),
        M0,
        "KickKernel",
    ),
    (
        "moser-veselov-heavy-top",
        lievi.MoserVeselov(),
        _heavy_top,
        INERTIA,
        jnp.eye(3),
        M0,
        "KickKernel",
    ),
    (
        "splitting-heavy-top",
        lievi.LiePoissonSplitting(),
        _heavy_top,
        INERTIA,
        jnp.eye(3),
        M0,
        "KickKernel",
    ),
    (
        "symmetric-top-6-heavy-top",  # an axisymmetric body; its own scheme's kicks
        lievi.SymmetricTopSplitting(6),
        _heavy_top,
        SYMMETRIC_INERTIA,
        jnp.eye(3),
        M0,
        "SchemeKernel",
    ),
    ("dep-exp-se3", lievi.DEP(), _se3, SE3_TENSOR, jnp.eye(4), SE3_M0, "SE3NewtonKernel"),
    (
        "dep-cayley-se3",
        lievi.DEP(chart="cayley"),
        _se3,
        SE3_TENSOR,
        jnp.eye(4),
        SE3_M0,
        "SE3NewtonKernel",
    ),
]
IDS = [entry[0] for entry in REGISTRY]
# The batched comparison of every entry runs with `-m slow`; `-m extended` batches one
# entry per kernel class (each kernel's batched loop, reduced state included).
BATCH_EXTENDED = (
    "dep-exp",  # 13 s
    "moser-veselov",  # 13 s
    "splitting",  # 14 s
    "rk4",  # 10 s
    "dep-exp-heavy-top",  # 18 s
    "dep-exp-se3",  # 39 s
    "rkmk4-se3-gravity",  # 24 s
    "rkmk8-heavy-top",  # 14 s
    "composition-splitting-6",  # 19 s
)
BATCHED = [
    pytest.param(
        entry, marks=pytest.mark.extended if entry[0] in BATCH_EXTENDED else pytest.mark.slow
    )
    for entry in REGISTRY
]


def _run(integrator, build, g0):
    """The trajectory and the gradients of a loss of its final state with respect to the
    system's parameter and `m0`, in one compiled program."""

    def loss(param, m0):
        sol = lievi.simulate(build(param), integrator, g0, m0, h=H, n_steps=STEPS)
        value = jnp.sum(sol.m[-1] ** 2) + jnp.sum(sol.g[-1] * jnp.arange(sol.g.shape[-1]))
        return value, sol

    return jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))


@pytest.mark.parametrize("entry", REGISTRY, ids=IDS)
def test_kernel_runs(entry):
    """The registered pair really has the registered kernel (so the parity below compares a
    kernel with the generic path, not the generic path with itself)."""
    _, integrator, build, param, *_, kernel_name = entry
    assert type(integrator.batch_kernel(build(param))).__name__ == kernel_name
    with reference_path():
        assert integrator.batch_kernel(build(param)) is None


# The slowest compilations under -m slow (the RKMK methods share one tableau-driven step,
# so one order-5 and one order-8 entry stay, under -m extended; RKMK4 in gravity is also
# checked against DOP853 by its order test, through the kernel, in the default suite, and on
# SE(3) batched against the generic path's gradients, `tests/test_rkmk.py`; the SE(3)
# composition stays: its negative stage exercises the SE(3) kernel at h < 0; the
# splitting's composition is compared batched).
ONE_BODY_SLOW = (
    "dep-cayley-se3",
    "rkmk4-heavy-top",
    "rkmk4-se3-gravity",
    "rkmk5-heavy-top",
    "rkmk5-se3",
    "rkmk5-se3-gravity",
    "rkmk8",
    "rkmk8-se3",
    "rkmk8-se3-gravity",
    "composition-dep-4-heavy-top",
    "composition-splitting-6",
)


def _one_body_case(entry):
    """The plain splitting's entry is the default suite's one fast-against-reference case;
    the others that are not slow are extended (8–76 s each, the SE(3) ones the slowest)."""
    if entry[0] == "splitting":
        return entry
    return pytest.param(
        entry, marks=pytest.mark.slow if entry[0] in ONE_BODY_SLOW else pytest.mark.extended
    )


ONE_BODY = [_one_body_case(entry) for entry in REGISTRY]


@pytest.mark.parametrize("entry", ONE_BODY, ids=IDS)
def test_iterates_and_gradients_equal_reference(entry):
    _, integrator, build, param, g0, m0, _ = entry
    (_, fast), fast_grads = _run(integrator, build, g0)(param, m0)
    with reference_path():
        (_, reference), reference_grads = _run(integrator, build, g0)(param, m0)
    np.testing.assert_array_equal(fast.result, 0)
    np.testing.assert_array_equal(reference.result, 0)
    scale = float(jnp.max(jnp.abs(reference.m)))
    np.testing.assert_allclose(fast.m, reference.m, rtol=0, atol=ITERATES * scale)
    np.testing.assert_allclose(fast.g, reference.g, rtol=0, atol=ITERATES)
    for a, b in zip(fast_grads, reference_grads):
        np.testing.assert_allclose(
            a, b, rtol=GRADIENTS, atol=GRADIENTS * float(jnp.max(jnp.abs(b)))
        )


@pytest.mark.parametrize("entry", BATCHED, ids=IDS)
def test_batch_equals_reference(entry):
    """`simulate_batch`'s kernel (three bodies, one per-body parameter each) against the
    generic batched path; saving only `m` takes the reduced `(Π, Γ)` kernel where one exists."""
    _, integrator, build, param, g0, m0, _ = entry
    scales = jnp.array([1.0, 1.3, 0.8])
    params = jax.vmap(lambda s: param * s)(scales)
    systems = jax.vmap(build)(params)
    g0s, m0s = jnp.stack([g0] * 3), jnp.stack([m0 * s for s in scales])

    def run(save):
        return lievi.simulate_batch(
            systems, integrator, g0s, m0s, h=H, n_steps=STEPS, system_axis=0, save=save
        )

    fast, fast_reduced = run(lievi.Save(stats=False)), run(lievi.Save(g=False, stats=False))
    with reference_path():
        reference = run(lievi.Save(stats=False))
    np.testing.assert_array_equal(fast.result, 0)
    scale = float(jnp.max(jnp.abs(reference.m)))
    for solution in (fast, fast_reduced):
        np.testing.assert_allclose(solution.m, reference.m, rtol=0, atol=ITERATES * scale)
    np.testing.assert_allclose(fast.g, reference.g, rtol=0, atol=ITERATES)


def test_every_kernel_is_registered():
    """Each public integrator on each kind of system: a kernel that applies must be in
    `REGISTRY` (a new kernel enters the registry, so the parity tests above cover it)."""
    integrators = [
        lievi.DEP(),
        lievi.DEP(chart="cayley"),
        lievi.MoserVeselov(),
        lievi.LiePoissonSplitting(),
        lievi.RK4(),
        lievi.RKMK4(),
        lievi.RKMK5(),
        lievi.RKMK8(),
        lievi.Composition(lievi.DEP(), order=4),
        lievi.PreprocessedMoserVeselov(),
    ]
    systems = {
        "rigid body": lievi.RigidBody(INERTIA),
        "rigid body, full tensor": lievi.RigidBody(jnp.diag(INERTIA)),
        "heavy top": _heavy_top(INERTIA),
        "generalized rigid body": lievi.GeneralizedRigidBody(jnp.array([0.5, 1.0, 1.5, 2.0])),
        "SE(3) body": _se3(SE3_TENSOR),
        "SE(3) body in gravity": lievi.RigidBodySE3(
            tensor=SE3_TENSOR, potential=lievi.UniformGravitySE3(2.0)
        ),
        "Lie Lagrangian": lievi.LieLagrangian(lievi.SO3, lambda xi: xi @ (INERTIA * xi) / 2),
    }
    registered = {
        (
            type(entry[1]).__name__,
            getattr(entry[1], "chart", None),
            type(entry[2](entry[3])).__name__,
            entry[2](entry[3]).potential is None,
        )
        for entry in REGISTRY
    }
    for integrator in integrators:
        for name, system in systems.items():
            if integrator.batch_kernel(system) is None:
                continue
            key = (
                type(integrator).__name__,
                getattr(integrator, "chart", None),
                type(system).__name__,
                system.potential is None,
            )
            assert key in registered, (
                f"{type(integrator).__name__} has a kernel for {name}: register it"
            )
