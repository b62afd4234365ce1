"""The explicit Lie–Poisson splitting (paper §6): order, symmetry, conservation, Poisson.

docs/theory/checks.md: order by regression against DOP853, Casimirs / spatial momentum to round-off
over 1e4 steps, the Poisson property of the momentum map, SO(n), full inertia tensors,
bad input, float32, derivatives.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_generalized_body, random_rotation
from lievi import diagnostics as dg
from lievi._kernels._base import reference_path

SPLIT = lievi.LiePoissonSplitting()
H = 0.1
STEPS = 40  # one trajectory length: `simulate` compiles once per system type and length
ORDER_TOLERANCE = 0.1

poisson_defect = eqx.filter_jit(dg.poisson_defect)


def observed_order(system, g0, m0, T, hs):
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, [0.0, T])
    errors = []
    for h in hs:
        sol = lievi.simulate(system, SPLIT, g0, m0, h=h, n_steps=int(round(T / h)))
        errors.append(
            max(np.max(np.abs(sol.m[-1] - m_ref[-1])), np.max(np.abs(sol.g[-1] - g_ref[-1])))
        )
    return np.polyfit(np.log(hs), np.log(errors), 1)[0], errors


def test_second_order_on_hlw():
    body, g0, m0 = hlw_problem()
    order, errors = observed_order(body, g0, m0, 2.0, [0.1 / 2**k for k in range(3)])
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


@pytest.mark.slow
def test_second_order_on_so4():
    body, g0, m0 = random_generalized_body(np.random.default_rng(4), 4)
    order, errors = observed_order(body, g0, m0, 1.0, [0.05 / 2**k for k in range(3)])
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


def test_symmetric_and_explicit():
    """`Φ_{−h} ∘ Φ_h = id` to round-off (so `lievi.Composition` can raise its order)."""
    body, g0, m0 = hlw_problem()
    g1, m1, info = SPLIT.step(body, g0, m0, H)
    g2, m2, _ = SPLIT.step(body, g1, m1, -H)
    np.testing.assert_allclose(g2, g0, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(m2, m0, rtol=0, atol=ROUNDOFF)
    assert info.result == lievi.RESULTS.successful and info.iterations == 0


def test_conservation_over_1e4_steps():
    """Casimirs, spatial momentum and `gᵀg = I` to round-off; energy bounded, O(h²)."""
    body, g0, m0 = hlw_problem()
    sol = lievi.simulate(body, SPLIT, g0, m0, h=H, n_steps=10_000, save=lievi.Save(every=10))
    assert sol.result == lievi.RESULTS.successful
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.spatial_momentum(body, sol.g, sol.m)) <= ROUNDOFF
    assert dg.orthogonality_defect(body, sol.g[-1]) <= ROUNDOFF
    energy = np.asarray(dg.energy(body, sol.g, sol.m))
    error = np.abs(energy / energy[0] - 1)
    tenth = len(error) // 10
    assert np.max(error) <= 1e-2
    assert np.max(error[-tenth:]) <= 1.01 * np.max(error[:tenth])


def test_momentum_map_is_poisson():
    body, g0, m0 = hlw_problem()
    assert poisson_defect(body, SPLIT, g0, m0, H) <= ROUNDOFF


@pytest.mark.parametrize("n", [4, pytest.param(5, marks=pytest.mark.slow)])
def test_generalized_rigid_body(n):
    body, g0, m0 = random_generalized_body(np.random.default_rng(n), n)
    h = 0.05
    sol = lievi.simulate(body, SPLIT, g0, m0, h=h, n_steps=4 * STEPS)
    assert sol.result == lievi.RESULTS.successful
    scale = float(jnp.max(jnp.abs(m0)))
    assert dg.relative_drift(dg.casimirs(body, sol.m)) <= ROUNDOFF
    assert dg.relative_drift(dg.spatial_momentum(body, sol.g, sol.m)) <= ROUNDOFF
    assert dg.orthogonality_defect(body, sol.g[-1]) <= ROUNDOFF
    g_ref, m_ref = lievi.reference_solution(body, g0, m0, [0.0, 4 * STEPS * h])
    assert np.max(np.abs(sol.m[-1] - m_ref[-1])) <= 1e-2 * scale  # O(h²), not garbage


def test_son3_generalized_body_matches_rigid_body():
    Lambda = jnp.array([0.2, 0.9, 1.3])
    inertia = jnp.array([Lambda[1] + Lambda[2], Lambda[0] + Lambda[2], Lambda[0] + Lambda[1]])
    _, g0, m0 = hlw_problem()
    a = lievi.simulate(lievi.RigidBody(inertia), SPLIT, g0, m0, h=H, n_steps=STEPS)
    b = lievi.simulate(lievi.GeneralizedRigidBody(Lambda), SPLIT, g0, m0, h=H, n_steps=STEPS)
    np.testing.assert_allclose(a.g, b.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(a.m, b.m, rtol=0, atol=ROUNDOFF)


def test_full_inertia_tensor_equals_rotated_diagonal_run():
    """`I' = Q I Qᵀ`, `g' = g Qᵀ`, `Π' = QΠ` is the same motion. The diagonal run lists the
    moments in ascending order, the order in which the full tensor's axes are split."""
    body = lievi.RigidBody(jnp.array([2.0 / 3.0, 1.0, 2.0]))
    _, g0, m0 = hlw_problem()
    Q = random_rotation(np.random.default_rng(0), 3)
    full = lievi.RigidBody(Q @ jnp.diag(body.inertia) @ Q.T)
    a = lievi.simulate(body, SPLIT, g0, m0, h=H, n_steps=STEPS)
    b = lievi.simulate(full, SPLIT, g0 @ Q.T, Q @ m0, h=H, n_steps=STEPS)
    np.testing.assert_allclose(b.g @ Q, a.g, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(b.m @ Q, a.m, rtol=0, atol=ROUNDOFF)


def test_full_tensor_steps_by_the_kernel_in_its_principal_frame():
    """A full tensor is stepped in its principal frame by the closed-form kernel (five
    sub-flows as one quaternion product, a hand-written tangent): its iterates and its
    gradients with respect to the tensor and `m0` equal the generic step's five 3×3
    rotations (every kernel off, `reference_path`) to 1e-12 and 1e-10 relative."""
    Q = random_rotation(np.random.default_rng(2), 3)
    tensor = Q @ jnp.diag(jnp.array([2.0 / 3.0, 1.0, 2.0])) @ Q.T
    _, g0, m0 = hlw_problem()
    assert SPLIT.free_kernel(lievi.RigidBody(tensor)) is None  # not the kernel's system

    @jax.jit
    def run(tensor, m0):
        def loss(tensor, m0):
            sol = lievi.simulate(lievi.RigidBody(tensor), SPLIT, g0, m0, h=H, n_steps=12)
            return jnp.sum(sol.m[-1] ** 2) + jnp.sum(sol.g[-1] * jnp.arange(3)), sol

        return jax.value_and_grad(loss, argnums=(0, 1), has_aux=True)(tensor, m0)

    (_, fast), fast_grads = run(tensor, m0)
    with reference_path():
        (_, reference), reference_grads = run(tensor, m0)
    np.testing.assert_array_equal(fast.result, lievi.RESULTS.successful)
    np.testing.assert_array_equal(reference.result, lievi.RESULTS.successful)
    np.testing.assert_allclose(fast.m, reference.m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.g, reference.g, rtol=0, atol=1e-12)
    for a, b in zip(fast_grads, reference_grads):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10 * float(jnp.max(jnp.abs(b))))

    # A system with a principal frame but no `principal_body` is rotated into the frame
    # and stepped by the five rotations: the same run to round-off.
    class FrameOnly(lievi.RigidBody):
        def principal_body(self):
            return None

    a = lievi.simulate(lievi.RigidBody(tensor), SPLIT, g0, m0, h=H, n_steps=12)
    b = lievi.simulate(FrameOnly(tensor), SPLIT, g0, m0, h=H, n_steps=12)
    np.testing.assert_allclose(b.m, a.m, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.g, a.g, rtol=0, atol=1e-12)


def test_principal_planes_of_a_full_tensor():
    """`RigidBody.principal_planes`: the moments in ascending order and a proper rotation
    `Q` with `Q diag(moments) Qᵀ = I`; principal moments are returned as given."""
    moments = jnp.array([2.0 / 3.0, 1.0, 2.0])
    Q0 = random_rotation(np.random.default_rng(1), 3)
    full = lievi.RigidBody(Q0 @ jnp.diag(moments) @ Q0.T)
    found, Q = full.principal_planes()
    np.testing.assert_allclose(found, moments, rtol=1e-14)
    np.testing.assert_allclose(Q @ jnp.diag(found) @ Q.T, full.inertia, rtol=0, atol=1e-14)
    np.testing.assert_allclose(jnp.linalg.det(Q), 1.0, rtol=1e-14)
    found, Q = lievi.RigidBody(moments).principal_planes()
    assert Q is None
    np.testing.assert_array_equal(found, moments)


def test_a_system_is_a_rigid_body_by_its_methods():
    """The rigid-body methods ask the system for its `Λ` and plane moments, not its class:
    a new system that has them runs (here the generalized body on SO(3) re-declared), and
    one that has none is rejected."""

    class Spinner(lievi.LieLagrangian):
        Lambda: jax.Array
        moments: jax.Array

        def __init__(self, Lambda, moments, l):
            super().__init__(lievi.SOn(3), l)
            self.Lambda, self.moments = Lambda, moments

        def lambda_matrix(self):
            return jnp.diag(self.Lambda)

        def principal_planes(self):
            return self.moments, None

    reference = lievi.GeneralizedRigidBody(jnp.array([0.5, 0.8, 1.1]))
    spinner = Spinner(reference.Lambda, reference.plane_inertia, reference.lagrangian)
    g0, m0 = jnp.eye(3), jnp.array([0.3, -0.2, 0.5])
    generic = lievi.LieLagrangian(lievi.SOn(3), reference.lagrangian)
    for method in (SPLIT, lievi.MoserVeselov()):
        with pytest.raises(ValueError, match="free rigid body only"):
            lievi.simulate(generic, method, g0, m0, h=H, n_steps=2)
    for method in (SPLIT, lievi.MoserVeselov()):
        a = lievi.simulate(reference, method, g0, m0, h=H, n_steps=20)
        b = lievi.simulate(spinner, method, g0, m0, h=H, n_steps=20)
        np.testing.assert_allclose(b.m, a.m, rtol=0, atol=ROUNDOFF)
        np.testing.assert_allclose(b.g, a.g, rtol=0, atol=ROUNDOFF)


def test_bad_input():
    body, g0, m0 = hlw_problem()
    with pytest.raises(ValueError, match="free rigid body only"):
        generic = lievi.LieLagrangian(lievi.SO3, body.lagrangian)
        SPLIT.step(generic, g0, m0, H)
    bad = eqx.tree_at(
        lambda b: b.Lambda,
        lievi.GeneralizedRigidBody(jnp.ones(4)),
        jnp.array([1.0, -1.5, 2.0, 1.0]),
    )
    with pytest.raises(ValueError, match="Λᵢ \\+ Λⱼ > 0"):
        SPLIT.step(bad, jnp.eye(4), jnp.ones(6), H)
    with pytest.raises(ValueError, match="`m` must have shape"):
        SPLIT.step(body, g0, jnp.ones(4), H)
    with pytest.raises(ValueError, match="`g` must have shape"):
        SPLIT.step(body, jnp.eye(4), m0, H)


def test_float32_run():
    body, g0, m0 = hlw_problem()
    body32 = lievi.RigidBody(body.inertia.astype(jnp.float32))
    g32, m32 = g0.astype(jnp.float32), m0.astype(jnp.float32)
    sol32 = lievi.simulate(body32, SPLIT, g32, m32, h=np.float32(H), n_steps=STEPS)
    sol64 = lievi.simulate(body, SPLIT, g0, m0, h=H, n_steps=STEPS)
    assert sol32.m.dtype == jnp.float32 and sol32.g.dtype == jnp.float32
    assert sol32.result == lievi.RESULTS.successful
    assert dg.relative_drift(dg.casimirs(body32, sol32.m)) <= 1e-5
    np.testing.assert_allclose(sol32.m, sol64.m, rtol=0, atol=1e-4)


@pytest.mark.parametrize(
    "tensor",
    [
        pytest.param(False, marks=pytest.mark.extended),  # 12 s
        pytest.param(True, marks=pytest.mark.slow),
    ],
)
def test_derivative_matches_finite_differences(tensor):
    """Explicit, so reverse mode goes straight through the sub-rotations (and `eigh`)."""
    body, g0, m0 = hlw_problem()
    Q = random_rotation(np.random.default_rng(1), 3)
    inertia = Q @ jnp.diag(body.inertia) @ Q.T if tensor else body.inertia

    def loss(inertia, h):
        sol = lievi.simulate(lievi.RigidBody(inertia), SPLIT, g0, m0, h=h, n_steps=STEPS)
        return jnp.sum(sol.m[-1] ** 2 * jnp.array([1.0, 2.0, 3.0])) + sol.g[-1, 0, 1]

    grad_inertia, grad_h = jax.grad(loss, argnums=(0, 1))(inertia, jnp.asarray(H))
    eps = 1e-6
    basis = np.eye(inertia.size).reshape((-1,) + inertia.shape)
    if tensor:  # symmetric perturbations of a tensor
        basis = [(e + e.T) / 2 for e in basis]
    fd = [(loss(inertia + eps * e, H) - loss(inertia - eps * e, H)) / (2 * eps) for e in basis]
    np.testing.assert_allclose([jnp.sum(grad_inertia * e) for e in basis], fd, rtol=1e-6, atol=1e-8)
    fd_h = (loss(inertia, H + eps) - loss(inertia, H - eps)) / (2 * eps)
    np.testing.assert_allclose(grad_h, fd_h, rtol=1e-6, atol=1e-8)


@pytest.mark.slow
@pytest.mark.parametrize("n", [4, 5])
def test_generalized_rigid_body_poisson(n):
    """The momentum map on so(n)* is Poisson (the SO(3) case runs by default)."""
    body, g0, m0 = random_generalized_body(np.random.default_rng(n), n)
    scale = float(jnp.max(jnp.abs(m0)))
    assert poisson_defect(body, SPLIT, g0, m0, 0.05) <= ROUNDOFF * scale
