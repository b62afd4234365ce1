"""Conservation and structure diagnostics (docs/theory/checks.md).

- `energy`, `casimirs`, `spatial_momentum`, `total_momentum`, `orthogonality_defect`: quantities the flow
  conserves (paper §3, §6), evaluated along a trajectory;
- `del_residual`: the discrete Euler–Lagrange equations (2.1) checked by autodiff of the
  integrator's discrete Lagrangian (Theorem 2.1), independent of any hand derivation;
- `poisson_defect`: `‖D B(m_k) Dᵀ − B(m_{k+1})‖` for the Jacobian `D` of the DLP map
  (Proposition 3.1: the DLP map is Poisson).

Every function of a state takes `(system, g, m)` in that order. All functions take arrays
with leading batch/time axes unless stated otherwise. Each is
one jit-compiled program (`eqx.filter_jit`, cached per system class and shapes): called
eagerly on a trajectory, JAX would otherwise compile and dispatch each of its operations
as a small program of its own.
"""

from __future__ import annotations

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from ._integrators._base import AbstractIntegrator, AbstractVariationalIntegrator
from ._systems._base import AbstractLieSystem


def _batched(fn, core_ndim: int, x):
    """Apply `fn` (written for one state with `core_ndim` axes) over leading axes."""
    for _ in range(x.ndim - core_ndim):
        fn = jax.vmap(fn)
    return fn(x)


def energy(
    system: AbstractLieSystem,
    g: Float[Array, "*batch n n"] | None,
    m: Float[Array, "*batch d"] | None = None,
) -> Float[Array, "*batch"]:
    """The total energy `H(m) + V(g)` (for the rigid body `½ Πᵀ I⁻¹ Π + V(g)`).

    Takes `(system, g, m)`, as every diagnostic of a state. `g` is needed when the system
    has a potential; for a free system it may be `None`.

    The order of earlier releases, `energy(system, m)` and `energy(system, m, g)`, still
    works for one release with a `DeprecationWarning`: a call with one array is the old
    `energy(system, m)`, and a call with two whose first has the momentum's trailing
    shape (`system.momentum_shape()`) and whose second has the element's
    (`system.element_shape()`) is the old order — the two shapes differ in their number
    of axes on every system, so the two orders are never confused.
    """
    g, m = _state_order(system, g, m)
    return _energy(system, g, m)


def _state_order(system: AbstractLieSystem, g, m):
    """`(g, m)` of a call in the order `(system, g, m)`, or of one in the order of earlier
    releases, `(system, m)` or `(system, m, g)` (told apart by the trailing shapes),
    with a `DeprecationWarning`."""
    element, momentum = system.element_shape(), system.momentum_shape()

    def ends_with(x, shape):
        x_shape = jnp.shape(x)
        return len(x_shape) >= len(shape) and tuple(x_shape[len(x_shape) - len(shape) :]) == shape

    old = m is None or (
        g is not None
        and ends_with(g, momentum)
        and ends_with(m, element)
        and jnp.ndim(g) - len(momentum) == jnp.ndim(m) - len(element)
    )
    if not old:
        return g, m
    warnings.warn(
        "lievi.diagnostics.energy(system, m, g) is deprecated: the order is now "
        "energy(system, g, m), as every diagnostic of a state (g may be None for a free "
        "system).",
        DeprecationWarning,
        stacklevel=3,
    )
    return (None, g) if m is None else (m, g)


@eqx.filter_jit
def _energy(system, g, m):
    # One state has the system's own shapes (`(d,)`, `(n, n)`; per body for several).
    kinetic = _batched(system.energy, len(system.momentum_shape()), m)
    if system.potential is None:
        return kinetic
    if g is None:
        raise ValueError(
            "energy: the system has a potential, so its energy depends on the attitude: pass "
            "`g` (e.g. `energy(system, sol.g, sol.m)`)."
        )
    return kinetic + _batched(system.potential_energy, len(system.element_shape()), g)


@eqx.filter_jit
def casimirs(system: AbstractLieSystem, m: Float[Array, "*batch d"]) -> Float[Array, "*batch k"]:
    """Casimir functions of the Lie–Poisson structure on `g*` (the group's `casimirs`).

    SO(n): `−tr(m̂^{2k})/2` for `k = 1 … ⌊n/2⌋` (on SO(3) the single Casimir `|Π|²`);
    SE(3): `(|P|², P·Π)` for `m = (Π, P)`.
    """
    return system.group.casimirs(m)


@eqx.filter_jit
def spatial_momentum(
    system: AbstractLieSystem, g: Float[Array, "*batch n n"], m: Float[Array, "*batch d"]
) -> Float[Array, "*batch d"]:
    """The conserved Noether momentum.

    Left-invariant: the spatial momentum `Ad*_{g⁻¹} Π = Ad_{g⁻¹}ᵀ Π` (`g Π` on SO(3), `g Π̂ gᵀ`
    on SO(n)). Right-invariant: the body momentum `Ad_gᵀ μ`.
    """
    return system.side.noether_momentum(system.group, g, m)


@eqx.filter_jit
def total_momentum(
    system: AbstractLieSystem, g: Float[Array, "*batch n n"], m: Float[Array, "*batch d"]
) -> Float[Array, "*batch d"]:
    """The momentum of the diagonal symmetry: `spatial_momentum` summed over the bodies.

    For `lievi.RigidBodies` (`g` `(…, N, 4, 4)`, `m` `(…, N, 6)`): the total angular
    momentum about the world origin and the total linear momentum,
    `(Σ R_i Π_i + p_i × R_i P_i, Σ R_i P_i)`, conserved when the coupling depends on the
    relative poses only. For `lievi.RigidRotors` (`g` `(…, N, 3, 3)`, `m` `(…, N, 3)`): the
    total spatial angular momentum `Σ R_i Π_i` (each body's about its own pivot),
    conserved when the coupling depends on the relative rotations only. For one body,
    its `spatial_momentum`.
    """
    each = spatial_momentum(system, g, m)
    bodies = len(system.momentum_shape()) - 1  # 0 for one body, 1 for several
    return jnp.sum(each, axis=tuple(range(-1 - bodies, -1)))


@eqx.filter_jit
def orthogonality_defect(system: AbstractLieSystem, g: Float[Array, "*batch n n"]):
    """Distance of `g` from the group (`‖gᵀg − I‖_F + |det g − 1|` on SO(n))."""
    return system.group.membership_defect(g)


@eqx.filter_jit
def relative_drift(values: Float[Array, "T ..."]) -> Scalar:
    """`max_k |v_k − v_0| / |v_0|` over the first axis (∞-norm over the rest)."""
    v0 = values[0]
    scale = jnp.maximum(jnp.max(jnp.abs(v0)), jnp.finfo(values.dtype).tiny)
    return jnp.max(jnp.abs(values - v0)) / scale


def del_residual(
    system: AbstractLieSystem,
    integrator: AbstractVariationalIntegrator,
    g: Float[Array, "T ..."],
    h,
) -> Float[Array, "T-2 ..."]:
    """The DEL residual `D₂L_d(g_{k−1}, g_k) + D₁L_d(g_k, g_{k+1})`, `k = 1 … T−2`.

    Both derivatives are taken by `jax.grad` along `ε ↦ g_k exp(εη)` (left) or
    `exp(εη) g_k` (right) at `ε = 0`: zero, to round-off, exactly when the trajectory is
    a critical point of the action sum (Theorem 2.1).

    `g` is one trajectory, `(T, *element_shape)` with `T ≥ 3` (`(T, n, n)` for one body;
    `(T, N, 4, 4)` for `lievi.RigidBodies`, one variation per body); the discrete
    Lagrangian is the system's (`AbstractLieSystem.free_discrete_lagrangian`: for several
    bodies, the sum of each body's under `integrator`).
    """
    g = jnp.asarray(g)
    element = tuple(system.element_shape())
    if g.ndim != 1 + len(element) or g.shape[1:] != element or g.shape[0] < 3:
        raise ValueError(
            f"`g` must be one trajectory of shape (T, {', '.join(map(str, element))}) with "
            f"T ≥ 3 (e.g. `simulate(...).g`), got {g.shape}; for a batch of trajectories "
            "call it on each (or `jax.vmap` it)."
        )
    return _del_residual(system, integrator, g, jnp.asarray(h, g.dtype))


# Compiled once per (system, integrator, shape): evaluated op by op, the vmapped gradient
# dispatches thousands of small operations (minutes on SO(n) with the exponential chart).
@eqx.filter_jit
def _del_residual(system, integrator, g, h):
    group = system.group

    def residual(g_prev, g_k, g_next):
        def action(eta):
            e = group.exp(eta)
            moved = system.side.translate(g_k, e)
            return integrator.discrete_lagrangian(
                system, g_prev, moved, h
            ) + integrator.discrete_lagrangian(system, moved, g_next, h)

        # One variation per body where the system has several (`momentum_shape`).
        return jax.grad(action)(jnp.zeros(system.momentum_shape(), g.dtype))

    return jax.vmap(residual)(g[:-2], g[1:-1], g[2:])


def lie_poisson_tensor(
    system: AbstractLieSystem, m: Float[Array, "*momentum"]
) -> Float[Array, "D D"]:
    """`B(m)_{ab} = ⟨m, [e_a, e_b]⟩`, the Lie–Poisson structure matrix at `m`.

    For a system of `N` bodies (`m` of shape `(N, d)`, the dual of the product algebra
    `gᴺ`) the structure is the direct sum of the bodies': `B` is block diagonal,
    `(N·d, N·d)`, in the order of `m.ravel()`.
    """
    group = system.group
    d = group.algebra_dim
    structure = group.ad(jnp.eye(d, dtype=m.dtype))  # [a] = ad_{e_a}
    each = jnp.einsum("nc,acb->nab", jnp.reshape(m, (-1, d)), structure)
    bodies = each.shape[0]
    blocks = jnp.einsum("ij,iab->iajb", jnp.eye(bodies, dtype=m.dtype), each)
    return blocks.reshape(bodies * d, bodies * d)


def poisson_defect(
    system: AbstractLieSystem, integrator: AbstractIntegrator, g, m: Float[Array, "*momentum"], h
) -> Scalar:
    """`max |D B(m) Dᵀ − B(m')|` for the momentum map `m ↦ m'` of one step (docs/theory/checks.md#poisson).

    `D` is computed by `jax.jacfwd` (implicit differentiation through the Newton solve).
    One state: `g` and `m` of the system's `element_shape()` and `momentum_shape()`; for
    a system of several bodies `D` is the Jacobian of the whole momentum `m.ravel()` and
    `B` the block-diagonal structure of the product (`lie_poisson_tensor`).
    """
    system.check_element("g", g)
    system.check_momentum("m", m)
    dtype = jnp.result_type(m, float)
    return _poisson_defect(system, integrator, g, jnp.asarray(m, dtype), jnp.asarray(h, dtype))


@eqx.filter_jit  # as `_del_residual`: one compiled program instead of op-by-op dispatch
def _poisson_defect(system, integrator, g, m, h):

    def momentum_map(flat):
        return integrator.step(system, g, flat.reshape(m.shape), h)[1].ravel()

    D = jax.jacfwd(momentum_map)(m.ravel())
    m_next = momentum_map(m.ravel()).reshape(m.shape)
    pushed = D @ lie_poisson_tensor(system, m) @ D.T
    return jnp.max(jnp.abs(pushed - lie_poisson_tensor(system, m_next)))
