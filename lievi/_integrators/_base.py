"""The integrator interface: a one-step map on `(g, m)` that reports a result code.

An integrator is an `eqx.Module` (its settings are fields). `step` advances the group
element and the momentum by one step `h` and returns a `StepInfo`. Variational
integrators also expose their discrete Lagrangian `L_d(g_k, g_{k+1})`, from which the
diagnostics check the discrete Euler–Lagrange equations (2.1) by autodiff.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._forcing import AbstractStepForce
from .._kernels._base import AbstractBatchKernel, kernels_enabled
from .._kernels._kick import KickKernel
from .._newton import newton_solve, newton_tolerance
from .._results import RESULTS, StepInfo
from .._systems._base import AbstractLieSystem


class AbstractIntegrator(eqx.Module):
    """A one-step method for a `AbstractLieSystem`."""

    @abc.abstractmethod
    def order(self) -> int:
        """Classical order of accuracy."""

    def is_symmetric(self) -> bool:
        """Whether `Φ_{−h} = Φ_h⁻¹` (time-reversible); `Composition` needs it."""
        return False

    def init(self, system: AbstractLieSystem, m0: Float[Array, " d"], h: Scalar):
        """This integrator as it runs one trajectory from `m0` with step `h`: what depends
        on the run rather than on the step, computed once, outside the step loop
        (`simulate` calls it at the start of every run, so it is computed for that run's
        own `h` and `m0`; diffrax's `solver.init` in spirit). Default: itself."""
        return self

    @abc.abstractmethod
    def step(
        self,
        system: AbstractLieSystem,
        g: Float[Array, "n n"],
        m: Float[Array, " d"],
        h: Scalar,
        force: AbstractStepForce | None = None,
        t: Scalar = 0.0,
    ) -> tuple[Float[Array, "n n"], Float[Array, " d"], StepInfo]:
        """Advance `(g_k, m_k)` at time `t = t_k` to `(g_{k+1}, m_{k+1})`.

        `force`, if given, is the external generalised force over the step, a callable
        `force(t, g, m) -> (d,)` (see `lievi.Control`, `lievi.ForceLaw`).
        """

    def own_step(self) -> bool:
        """Whether this object's `step` is the one its class's kernels (`kernels`) and step
        cache (`step_cache`) compute. Each integrator with a kernel or a cache says so for
        its own class alone (`type(self) is DEP`), so a subclass that changes the step (a
        test's broken method, a user's modified step) runs its own `step` everywhere —
        `simulate`, `simulate_batch`, under `jax.vmap` — rather than its parent's kernel.
        Default `False`: no kernel, no cache."""
        return False

    def step_cache(self, system: AbstractLieSystem, g):
        """What a step may take over from the step before it, a function of the state
        `g` alone (e.g. a kick method's potential force, `AbstractKickIntegrator`), or
        `None` (nothing: the default, and wherever `step` runs as written, `own_step`).
        The loops compute it once at the start of a run and carry what `cached_step`
        returns from step to step."""
        return self._start_cache(system, g) if self.own_step() else None

    def cached_step(
        self, system: AbstractLieSystem, g, m, h: Scalar, cache, force=None, t: Scalar = 0.0
    ):
        """`step` given `cache = step_cache(system, g)`, also returning
        `step_cache(system, g_{k+1})`: `(g_{k+1}, m_{k+1}, info, cache_{k+1})`; what the
        loops run. The default is `step`, with nothing to take over."""
        if self.own_step():
            return self._step_from_cache(system, g, m, h, cache, force, t)
        # Unforced, `step` is called without `force` and `t`: a user's step written for
        # unforced runs (`step(system, g, m, h)`) keeps working.
        if force is None:
            g, m, info = self.step(system, g, m, h)
        else:
            g, m, info = self.step(system, g, m, h, force, t)
        return g, m, info, cache

    def _start_cache(self, system: AbstractLieSystem, g):
        """`step_cache` of a method that takes something over (`_step_from_cache`)."""
        return None

    def _step_from_cache(self, system, g, m, h, cache, force, t):
        """`cached_step` of a method that takes something over from step to step (with
        `own_step`); by default `step`, the cache passed on unchanged."""
        g, m, info = self.step(system, g, m, h, force, t)
        return g, m, info, cache

    def step_bound(self) -> float:
        """The largest angle `h·|ξ|` a step may turn (`ξ` the velocity of the current
        momentum, `|ξ|` its algebra norm, an upper bound of the largest rotation angle
        per unit time on SO(n)). Default π: a rotation sampled at π or more per step is
        aliased (its increment is indistinguishable from a shorter turn the other way),
        so no one-step method can resolve it. `simulate` and `simulate_batch` report
        `RESULTS.step_too_large` for a step beyond it (docs/guarantees.md)."""
        return math.pi

    def step_too_large(self, system: AbstractLieSystem, m: Float[Array, " d"], h: Scalar):
        """Whether a step of size `h` from momentum `m` exceeds `step_bound()` (traceable).

        A NaN momentum is not "too large" (it is reported as `nonfinite`)."""
        # The angle the group's exponential turns (`exp_norm`: on SE(3) the rotation part
        # only; a translation per step has no such bound).
        # `any`: a system of several bodies steps too far if one of them does.
        return jnp.any(jnp.abs(h) * system.velocity_size(m) > self.step_bound())

    def kernels(self) -> tuple[AbstractBatchKernel, ...]:
        """This method's structure-of-arrays steps of the free system, one per kind of
        system they serve (each says which in `AbstractBatchKernel.physics`); none by
        default. A kernel computes the iterates of the generic step, faster."""
        return ()

    def free_kernel(self, system: AbstractLieSystem, batched: bool = False):
        """The kernel of `kernels()` that applies to `system` (free of its potential), or
        `None`: then the generic step runs. `batched`: `system` is a batch built with
        `jax.vmap`. The one place that decides (`kernels_enabled` turns every kernel off,
        for the reference path the kernels are tested against; a subclass that changes the
        step has none, `own_step`)."""
        if not kernels_enabled() or not self.own_step():
            return None
        for kernel in self.kernels():
            if kernel.physics(system, batched) is not None:
                return kernel
        return None

    def batch_kernel(self, system: AbstractLieSystem, batched: bool = False):
        """The kernel `simulate_batch` runs for `system` (its potential included), or
        `None`: by default the free kernel, for a free system."""
        return self.free_kernel(system, batched) if system.potential is None else None

    def kernel_step(self, system: AbstractLieSystem, g, m, h: Scalar):
        """One free step by this method's kernel for `system`, or `None` where none
        applies: `simulate`'s step runs the same kernel code as `simulate_batch`."""
        kernel = self.free_kernel(system)
        if kernel is None:
            return None
        g_next, m_next, result, iterations, residual = kernel.one_body_step(system, g, m, h)
        return g_next, m_next, StepInfo(result, iterations, residual)


class AbstractKickIntegrator(AbstractIntegrator):
    """An integrator whose step, for a system with a potential, is kick – free step – kick.

    The step is `m⁺ = m_k + (h/2) M(g_k)`, `(g_{k+1}, m⁻) = free_step(g_k, m⁺)`,
    `m_{k+1} = m⁻ + (h/2) M(g_{k+1})` with `M` the system's generalised force
    (`AbstractLieSystem.force`). For a variational method with discrete Lagrangian
    `L_d − (h/2)(V(g_k) + V(g_{k+1}))` this *is* its discrete Euler–Lagrange equation in
    momentum form (the discrete Legendre transforms `∓D_{1,2}L_d` pick up `∓(h/2)dV`); for
    a splitting it is the symmetric Strang composition with the exact flow of `V`. Either
    way symmetric and second order when the free step is, and nothing changes for a free
    system (the kicks are skipped at trace time).

    An external force (`force`; `lievi.Control`, `lievi.ForceLaw`) adds the discrete
    Lagrange–d'Alembert forces to these kicks: `f_k⁻ = (h/2) f(t_k, g_k, m_k)` to the
    first, `f_k⁺ = (h/2) f(t_{k+1}, g_{k+1}, m_{k+1})` to the last (implicit if `f`
    depends on `m`; see `lievi/_forcing.py`). The step stays symmetric and second order.

    A run evaluates `M` once per step: `M(g_{k+1})` of one step's last kick is carried to
    the next step's first (`step_cache`, `cached_step`).
    """

    @abc.abstractmethod
    def free_step(
        self, system: AbstractLieSystem, g: Float[Array, "n n"], m: Float[Array, " d"], h: Scalar
    ) -> tuple[Float[Array, "n n"], Float[Array, " d"], StepInfo]:
        """The step of the system without its potential."""

    def body(self, index):
        """This integrator as it steps body `index` of a system of several bodies (their
        `free_flow`): itself, unless its `init` computed data per body (then that body's).
        """
        return self

    def free_body_step(self, inertia, mass, g, m, h: Scalar):
        """The free step of a rigid body in vacuum (mass `mass`, `inertia` about its centre
        of mass, the body origin there) where this method has its own, or `None` (the
        default): `lievi.RigidBodies` then takes this method's `free_step` of the body
        (`RigidBodies.free_flow`). A method of the rotation alone steps the rotation and
        translates exactly (`_drift.rotation_and_drift`)."""
        return None

    def batch_kernel(self, system: AbstractLieSystem, batched: bool = False):
        free = self.free_kernel(system, batched)
        if free is None or system.potential is None:
            return free
        # Kick – free step – kick, as `step`, where the potential has a closed-form torque.
        kernel = KickKernel(free, system.potential)
        return kernel if kernel.physics(system, batched) is not None else None

    def step(self, system: AbstractLieSystem, g, m, h: Scalar, force=None, t: Scalar = 0.0):
        return self._kick_step(system, g, m, h, None, force, t)[:3]

    def _start_cache(self, system: AbstractLieSystem, g):
        """The potential's force `M(g_k)`: the force of one step's end kick is that of
        the next step's first kick (the same `g`), so a run evaluates the potential's
        force once per step, not twice — for coupled bodies, where the coupling is most
        of the step, nearly half the cost. `None` for a free system."""
        return None if system.potential is None else system.force(g)

    def _step_from_cache(self, system, g, m, h, cache, force, t):
        return self._kick_step(system, g, m, h, cache, force, t)

    def _kick_step(self, system, g, m, h, start_force, force, t):
        """The step, from the potential's force at `g_k` if known (`start_force`, else
        computed), returning the force at `g_{k+1}` (`None` for a free system)."""
        # `system.free_flow`: the system decides how this method's free step applies to it
        # (one body: `free_step` itself; several bodies: each of them).
        if system.potential is None and force is None:
            return (*system.free_flow(self, g, m, h), None)
        end_force = None
        m_plus = m
        if system.potential is not None:
            start_force = system.force(g) if start_force is None else start_force
            m_plus = m + h / 2 * start_force
        if force is not None:
            # The discrete Lagrange–d'Alembert force at g_k: f_k⁻ = (h/2) f(t_k, g_k, m_k).
            m_plus = m_plus + h / 2 * checked_force(force, t, g, m)
        g_next, m_next, info = system.free_flow(self, g, m_plus, h)
        if system.potential is not None:
            end_force = system.force(g_next)
            m_next = m_next + h / 2 * end_force
        iterations, residual, result = info.iterations, info.residual, info.result
        if force is not None:
            # The integrator's stopping test (`newton_tolerance`), relative by default.
            tolerances = getattr(self, "rtol", None), getattr(self, "atol", None)
            m_next, kick = forced_end_kick(
                force, t + h, g_next, m_next, h, info.result, *tolerances
            )
            iterations, residual = (
                iterations + kick.iterations,
                jnp.maximum(residual, kick.residual),
            )
            result = RESULTS.first_failure(result, kick.result)
        # A non-finite potential or force shows up only after the free step's own checks.
        nonfinite = (result == RESULTS.successful) & ~jnp.all(jnp.isfinite(m_next))
        result = jnp.where(nonfinite, RESULTS.nonfinite, result)
        return g_next, m_next, StepInfo(result, iterations, residual), end_force


def checked_force(force, t, g, m):
    """`force(t, g, m)`, of the momentum's shape, in the momentum's dtype.

    The run's dtype is that of the state (a float64 constant inside a force law must not
    turn a float32 run into a float64 one halfway through a step)."""
    value = force(t, g, m)
    if jnp.shape(value) != jnp.shape(m):
        raise ValueError(
            f"`forcing`: the force must have the shape of the momentum {jnp.shape(m)}, got "
            f"{jnp.shape(value)}."
        )
    return jnp.asarray(value, m.dtype)


def forced_end_kick(
    force: AbstractStepForce,
    t,
    g,
    m_minus,
    h,
    result_before=RESULTS.successful,
    rtol: float | None = None,
    atol: float | None = None,
):
    """`m` with `m = m⁻ + (h/2) f(t, g, m)`: the end-of-step discrete force `f_k⁺`.

    Explicit when the force does not depend on the momentum (a held control); otherwise
    an implicit Euler half step solved by Newton's method from the explicit guess,
    differentiated implicitly, to the tolerance of every implicit step
    (`lievi._newton.newton_tolerance` with the integrator's `rtol`, `atol`: relative to
    the size of the momentum, so the step does not depend on the units). Returns
    `(m, StepInfo)`; a solve that does not converge within `END_KICK_MAX_STEPS` is
    reported as `RESULTS.newton_not_converged`.
    """
    zero = jnp.zeros((), m_minus.dtype)
    if not force.depends_on_momentum():
        m = m_minus + h / 2 * checked_force(force, t, g, m_minus)
        return m, StepInfo(
            jnp.asarray(RESULTS.successful, jnp.int32), jnp.zeros((), jnp.int32), zero
        )

    # Newton on the momentum as one vector (a system of several bodies has one row each).
    shape = jnp.shape(m_minus)

    def residual(flat):
        m = flat.reshape(shape)
        return (m - m_minus - h / 2 * checked_force(force, t, g, m)).reshape(-1)

    guess = m_minus + h / 2 * checked_force(force, t, g, m_minus)
    # The terms of the equation are of the size of `m⁻` and of the root (≈ the guess).
    scale = jnp.maximum(jnp.max(jnp.abs(m_minus)), jnp.max(jnp.abs(guess)))
    tolerance = newton_tolerance(scale, m_minus.dtype, rtol, atol)
    m, info = newton_solve(residual, guess.reshape(-1), tolerance, END_KICK_MAX_STEPS)
    m = m.reshape(shape)
    ok = info.converged | (result_before != RESULTS.successful)
    result = jnp.where(ok, RESULTS.successful, RESULTS.newton_not_converged)
    return m, StepInfo(result.astype(jnp.int32), info.iterations, info.residual)


# The end-of-step kick's Newton solve reports failure after 20 iterations.
END_KICK_MAX_STEPS = 20


class AbstractVariationalIntegrator(AbstractKickIntegrator):
    """An integrator defined by a discrete Lagrangian `L_d(g_k, g_{k+1})` (paper §2)."""

    @abc.abstractmethod
    def kinetic_discrete_lagrangian(
        self, system: AbstractLieSystem, g0: Float[Array, "n n"], g1: Float[Array, "n n"], h: Scalar
    ) -> Scalar:
        """`L_d` of the reduced Lagrangian `l(ξ)` alone (the free system)."""

    def body_discrete_lagrangian(self, inertia, mass, g0, g1, h: Scalar) -> Scalar | None:
        """The discrete Lagrangian of `free_body_step` where this method has its own free
        body step, or `None` (the default): `lievi.RigidBodies` then takes this method's
        `kinetic_discrete_lagrangian` of the body (`RigidBodies.free_discrete_lagrangian`).
        A method of the rotation alone adds the exact translation's
        (`_drift.rotation_and_drift_lagrangian`)."""
        return None

    def discrete_lagrangian(
        self, system: AbstractLieSystem, g0: Float[Array, "n n"], g1: Float[Array, "n n"], h: Scalar
    ) -> Scalar:
        """`L_d(g_k, g_{k+1})`: the kinetic part minus `(h/2)(V(g_k) + V(g_{k+1}))`.

        The trapezoidal potential term makes the step kick – free step – kick (see
        `AbstractKickIntegrator`); it is the Lie group variational integrator of Lee, Leok
        and McClamroch for the exponential/Cayley charts.
        """
        # The system's: a system of several bodies sums its bodies' (`free_discrete_lagrangian`).
        kinetic = system.free_discrete_lagrangian(self, g0, g1, h)
        if system.potential is None:
            return kinetic
        return kinetic - h / 2 * (system.potential_energy(g0) + system.potential_energy(g1))

    def momentum_from_configurations(
        self, system: AbstractLieSystem, g0: Float[Array, "n n"], g1: Float[Array, "n n"], h: Scalar
    ) -> Float[Array, " d"]:
        """The momentum at `g0` of the discrete trajectory through `(g0, g1)`.

        The discrete Legendre transform `m_0 = −D₁L_d(g_0, g_1)`, trivialised on the
        side of the symmetry (paper §2); computed by autodiff of `discrete_lagrangian`.
        """
        group = system.group

        def perturbed(eta):
            e = group.exp(eta)
            g = system.side.translate(g0, e)
            return self.discrete_lagrangian(system, g, g1, h)

        return -jax.grad(perturbed)(jnp.zeros(group.algebra_dim, g0.dtype))
