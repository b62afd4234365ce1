"""Lagrangian systems on a Lie group, reduced to the algebra (paper §2, §4.2, §7).

A system is a reduced Lagrangian `l: g → R` on algebra coordinates together with the
group and the side of the symmetry: `side="left"` for left-invariant systems such as
the rigid body (`ξ = g⁻¹ġ`, body momentum `Π`), `side="right"` for right-invariant ones
(`ξ = ġ g⁻¹`, spatial momentum `μ`). The momentum is `m = ∂l/∂ξ` (the Legendre map),
written in the coordinates dual to the algebra basis.

A system may carry a potential `V(g)` (paper §7: the symmetry is then only the subgroup
that leaves `V` unchanged); the Lagrangian is `L(g, ξ) = l(ξ) − V(g)` and the integrators
see `V` through `potential_energy`, `force` and `kick` below.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._checks import (
    Conditions,
    all_hold,
    check_finite,
    check_shape,
    evaluated_now,
    finite_conditions,
    is_concrete,
    membership_tolerance,
    raise_if_violated,
)
from .._groups._base import MatrixLieGroup
from ._potential import AbstractPotential
from ._side import Side


class AbstractLieSystem(eqx.Module):
    """A reduced Lagrangian system on a matrix Lie group.

    Subclasses set `group`, `side` and `potential` (`None` for a free system) and
    implement `lagrangian`. The Legendre map, its inverse and the energy have generic
    versions (autodiff and Newton) that quadratic systems override with closed forms.
    """

    group: eqx.AbstractVar[MatrixLieGroup]
    side: eqx.AbstractVar[Side]
    potential: eqx.AbstractVar[AbstractPotential | None]

    def __check_init__(self):
        # After the subclass's own checks (shapes, dtypes): the parameter values, eagerly.
        raise_if_violated(self.parameter_conditions)
        if self.potential is None:
            return
        shape = self.element_shape()
        what = "×".join(map(str, shape))
        probe = jax.ShapeDtypeStruct(shape, jnp.result_type(float))
        try:
            out = jax.eval_shape(self.potential, probe)
        except Exception as error:  # the user's function, any failure: say whose it is
            raise ValueError(
                f"`potential` could not be evaluated on a {what} configuration: {error}"
            ) from error
        if getattr(out, "shape", None) != ():
            raise ValueError(
                f"`potential` must return a scalar V(g) for a {what} `g`, got "
                f"{getattr(out, 'shape', type(out).__name__)}."
            )
        if not jnp.issubdtype(out.dtype, jnp.floating):
            # Its torque is a gradient: JAX differentiates real floating-point values only.
            raise ValueError(
                f"`potential` must return a real floating-point V(g), got dtype {out.dtype} "
                "(e.g. `lambda g: 0` returns an integer: write `0.0`, or convert with "
                "`jnp.asarray(value, float)`)."
            )

    def element_shape(self) -> tuple[int, ...]:
        """The shape of a configuration `g`: `(n, n)`, one group element (the default);
        a system of several bodies has one element per body."""
        n = self.group.matrix_dim
        return (n, n)

    def momentum_shape(self) -> tuple[int, ...]:
        """The shape of a momentum `m`: `(d,)` (the default), or one row per body."""
        return (self.group.algebra_dim,)

    def batch_axes(self, axis: int | None):
        """`jax.vmap`'s `in_axes` for this system as a batch of systems along `axis` (`None`:
        one system shared by the batch): `axis` for its array leaves and `None` for the
        others — a potential given as a Python function, for one — which `jax.vmap`
        cannot map (a batch built with `equinox.filter_vmap` keeps them)."""
        if axis is None:
            return None
        return jax.tree.map(lambda x: axis if eqx.is_array(x) else None, self)

    def check_unconstrained(self, method: str) -> None:
        """Nothing: `method` (a method that knows only the Euler–Poincaré equations
        (2.4)/(2.5), or a kick method's free step) applies to this system. A system with
        constraints that such a method would ignore (`lievi.ArticulatedBodies`) raises a
        `ValueError` naming `method` and the one that enforces them."""

    def constrained_rate(self, g, m, m_dot):
        """The momentum rate `m_dot` of the Euler–Poincaré equations (every force applied)
        with the reaction of this system's constraints added: `m_dot` itself (the default,
        no constraints). `lievi.ArticulatedBodies` adds its joints' reaction, so that the
        explicit Lie-group methods (`lievi.RKMK4` …) integrate its equations."""
        return m_dot

    def project_state(self, g, m):
        """`(g, m, held)`: the state after an explicit step moved back onto this system's
        constraints, and whether they then hold: the state itself (the default, none)."""
        return g, m, jnp.asarray(True)

    def free_flow(self, integrator, g, m, h: Scalar):
        """The free step of a kick integrator (`AbstractKickIntegrator.free_step`) on this
        system: the integrator's own (the default). A system of several bodies steps each
        body with it (`lievi.RigidBodies`, `lievi.RigidRotors`)."""
        return integrator.free_step(self, g, m, h)

    def free_discrete_lagrangian(self, integrator, g0, g1, h: Scalar) -> Scalar:
        """The kinetic discrete Lagrangian `L_d(g0, g1)` of a variational integrator on this
        system (`AbstractVariationalIntegrator.kinetic_discrete_lagrangian`): the
        integrator's own (the default). A system of several bodies sums its bodies' — the
        discrete Lagrangian whose discrete Euler–Lagrange equations (paper (2.1)) its
        `free_flow` steps (`lievi.RigidBodies`, `lievi.RigidRotors`)."""
        return integrator.kinetic_discrete_lagrangian(self, g0, g1, h)

    @abc.abstractmethod
    def lagrangian(self, xi: Float[Array, " d"]) -> Scalar:
        """The reduced Lagrangian `l(ξ)`."""

    def legendre(self, xi: Float[Array, " d"]) -> Float[Array, " d"]:
        """Momentum `m = ∇l(ξ)`."""
        return jax.grad(self.lagrangian)(xi)

    def velocity(self, m: Float[Array, " d"], iterations: int = 30) -> Float[Array, " d"]:
        """Inverse Legendre map: `ξ` with `∇l(ξ) = m` (Newton from `ξ = 0`)."""

        def body(_, xi):
            hessian = jax.hessian(self.lagrangian)(xi)
            return xi - jnp.linalg.solve(hessian, self.legendre(xi) - m)

        return jax.lax.fori_loop(0, iterations, body, jnp.zeros_like(m))

    def velocity_size(self, m: Float[Array, " d"]) -> Float[Array, "*batch"]:
        """`group.exp_norm(velocity(m))`: the size of the velocity that a step's bound
        limits (`AbstractIntegrator.step_too_large`). A system may give it from less than
        the whole velocity (on SE(3) only the rotation rate counts)."""
        return self.group.exp_norm(self.velocity(m))

    def energy(self, m: Float[Array, " d"]) -> Scalar:
        """Hamiltonian `H(m) = ⟨m, ξ⟩ − l(ξ)` with `ξ` the velocity of `m`."""
        xi = self.velocity(m)
        return jnp.dot(m, xi) - self.lagrangian(xi)

    def potential_energy(self, g: Float[Array, "n n"]) -> Scalar:
        """`V(g)`; zero for a free system."""
        if self.potential is None:
            return jnp.zeros((), jnp.result_type(g))
        return self.potential(g)

    def force(self, g: Float[Array, "n n"]) -> Float[Array, " d"]:
        """The generalised force `M(g) = −dV` trivialised on the side of the symmetry.

        Left-invariant: `M_i = −d/dε V(g exp(ε e_i))` (the body torque of a rigid body);
        right-invariant: `M_i = −d/dε V(exp(ε e_i) g)`. By autodiff along the first-order
        curve `g (I + ε ê_i)` (resp. `(I + ε ê_i) g`), which has the same derivative and
        costs no exponential. Zero for a free system.

        NaN where `V(g)` itself is not finite (its value comes with the derivative at no
        extra cost): a potential past a singularity, e.g. a log barrier `−k log g₃₃` once
        `g₃₃ < 0`, can have a finite derivative, and the step that reached it must be
        reported (`RESULTS.nonfinite`), not integrated on.
        """
        shape = self.momentum_shape()
        if self.potential is None:
            return jnp.zeros(shape, jnp.result_type(g))

        def along(eta):
            E = self.group.hat(eta)
            return self.potential(g + self.side.translate(g, E))

        value, gradient = jax.value_and_grad(along)(jnp.zeros(shape, jnp.result_type(g, float)))
        return jnp.where(jnp.isfinite(value), -gradient, jnp.nan)

    def kick(self, g: Float[Array, "n n"], m: Float[Array, " d"], dt: Scalar) -> Float[Array, " d"]:
        """`m + dt·M(g)`: the exact flow of the potential for a time `dt` (`g` is fixed)."""
        if self.potential is None:
            return m
        return m + dt * self.force(g)

    def lambda_matrix(self):
        """The symmetric `n × n` matrix `Λ` of a free rigid body on SO(n) whose inertia
        operator is `J(ξ̂) = Λξ̂ + ξ̂Λ` (paper §5), or `None` (the default): the methods of
        the rigid body alone (`lievi.MoserVeselov`, `lievi.LiePoissonSplitting`) run the
        systems that have one and reject the others."""
        return None

    def principal_planes(self):
        """`(moments, Q)` of a system with a `lambda_matrix`: the moment `Λᵢ + Λⱼ` of each
        coordinate plane of `so(n)` in the principal frame of `Λ` (in the group's coordinate
        order) and the rotation `Q` into that frame (`None`: the coordinates are principal
        already). `None` where `lambda_matrix` is."""
        return None

    def principal_body(self):
        """Where `principal_planes` has a rotation `Q`: the free system in that frame (the
        state `(g Q, Qᵀ m)`), whose inertia operator is the principal moments — what a
        method written for principal moments steps in place of this one. `None` by
        default."""
        return None

    def principal_frames(self):
        """`(moments, Q, principal_body())` of each body the system's `free_flow` steps
        (`principal_planes`; `principal_body` only where `Q` is not `None`), or `None`
        where `principal_planes` is: of the system itself by default; a system of several
        bodies gives them with a leading body axis. What a method that steps in the
        principal frame computes once per run (`AbstractIntegrator.init`), not at every
        step."""
        planes = self.principal_planes()
        if planes is None:
            return None
        moments, Q = planes
        return moments, Q, None if Q is None else self.principal_body()

    def kinetic_tensor(self):
        """The tensor `M` of a quadratic reduced Lagrangian `l(ξ) = ½ ξᵀMξ` in the algebra
        basis — a vector where `M` is diagonal (a rigid body's principal moments) — or
        `None` where `l` is not known to be quadratic (the default). Physics only: an
        integrator's fast kernels read it to decide whether they apply."""
        return None

    def check_element(self, name: str, g) -> None:
        """Raise `ValueError` unless `g` is a finite configuration of `element_shape()` (an
        `(n, n)` element of the group, to `membership_tolerance` of its dtype, the bound of
        `element_valid`; for several bodies, every one)."""
        shape = self.element_shape()
        n = self.group.matrix_dim
        what = f"a {n}×{n} group element" + (
            f" for each of {shape[0]} bodies" if len(shape) > 2 else ""
        )
        check_shape(name, g, shape, what)
        check_finite(name, g)
        if is_concrete(g):
            # Evaluated now even when `simulate` is being traced by an outer `jit` with a
            # concrete `g` captured from outside.
            g = jnp.asarray(g)
            bound = membership_tolerance(g.dtype)
            with evaluated_now():
                defect = float(_largest_defect(self.group, g))
            if defect > bound:
                raise _off_group(self.group, name, defect, bound)

    def parameter_conditions(self) -> Conditions:
        """The admissible parameters, as conditions (`lievi._checks.Conditions`): here
        finite, and the potential's own (`AbstractPotential.parameter_conditions`).
        Subclasses add theirs. One definition for both forms: the constructor raises on a
        concrete violation, and `parameters_valid` is their traced conjunction."""
        fields = {k: v for k, v in vars(self).items() if k != "potential"}
        conditions = finite_conditions(fields)
        if self.potential is not None and hasattr(self.potential, "parameter_conditions"):
            conditions = conditions + self.potential.parameter_conditions()
        return conditions

    def parameters_valid(self):
        """A boolean array: the parameters are admissible (`parameter_conditions`).
        Traceable, so `simulate` checks it under `jit`/`vmap` too and reports
        `RESULTS.invalid_input`."""
        return all_hold(self.parameter_conditions())

    def element_valid(self, g):
        """A boolean array: `g` is a finite group element (membership defect within
        `membership_tolerance`, the bound of `check_element`). Traceable."""
        dtype = jnp.result_type(g, float)
        g = jnp.asarray(g, dtype)
        finite = jnp.all(jnp.isfinite(g))
        safe = jnp.where(finite, g, jnp.eye(g.shape[-1], dtype=dtype))
        defect = self.group.membership_defect(safe)
        return finite & jnp.all(defect <= membership_tolerance(dtype))

    def check_momentum(self, name: str, m) -> None:
        """Raise `ValueError` unless `m` is a finite momentum of `momentum_shape()`."""
        d = self.group.algebra_dim
        check_shape(name, m, self.momentum_shape(), f"momentum coordinates of dimension {d}")
        check_finite(name, m)


@eqx.filter_jit
def _largest_defect(group: MatrixLieGroup, g):
    """`check_element`'s eager membership defect as one compiled program, not one small
    program per operation compiled at its first call."""
    return jnp.max(group.membership_defect(jnp.asarray(g, float)))


def _off_group(group: MatrixLieGroup, name: str, defect, bound) -> ValueError:
    """The error of `check_element` for the state `name`."""
    return ValueError(
        f"`{name}` is not in the group: membership defect {defect:.3g} > {bound:.2g} "
        f"({group.membership_hint()})."
    )
