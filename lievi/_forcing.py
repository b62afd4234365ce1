"""External forces and controls: the discrete Lagrange–d'Alembert principle.

A forced system `L(g, ξ) = l(ξ) − V(g)` with an external generalised force `f(t)` in the
dual of the algebra (for the rigid body: the body torque; trivialised on the side of the
symmetry, like the potential's force `M(g)`) satisfies the Lagrange–d'Alembert principle
`δ∫L dt + ∫⟨f, g⁻¹δg⟩ dt = 0`. Its discrete version (Marsden & West, *Discrete mechanics
and variational integrators*, Acta Numerica 2001, §3.2) adds two discrete forces to the
discrete Euler–Lagrange equations: `f_k⁻` acting at `g_k` and `f_k⁺` acting at `g_{k+1}`,
both ≈ `(h/2)·f`. In momentum form they are two more kicks around the free step:

    m_k⁺ = m_k + (h/2) M(g_k) + f_k⁻,
    (g_{k+1}, m_{k+1}⁻) = free step of (g_k, m_k⁺),
    m_{k+1} = m_{k+1}⁻ + (h/2) M(g_{k+1}) + f_k⁺.

This module chooses `f_k⁻ = (h/2) f(t_k, g_k, m_k)` and `f_k⁺ = (h/2) f(t_{k+1}, g_{k+1},
m_{k+1})`: the trapezoidal rule on the force. When `f` depends on the momentum the last
kick is implicit (solved by Newton's method, differentiated implicitly); the step is then
explicit Euler (h/2) ∘ symmetric free step ∘ implicit Euler (h/2) on the force, a symmetric
composition, hence second order. For a control held over the step both forces are
`(h/2) u_k` and everything stays explicit.

Discrete Noether theorem with forces: for a left-invariant system the free step keeps the
spatial momentum `Ad*_{g⁻¹} m` (for the rigid body `g Π`), so over one step it changes by
exactly the spatial impulse `Ad*_{g_k⁻¹} f_k⁻ + Ad*_{g_{k+1}⁻¹} f_k⁺` (plus the potential's).

Inputs are modules, as diffrax's terms are: `Control(u)` (a per-step control sequence,
zero-order hold) and `ForceLaw(fn)` (a function `fn(t, g, m, args)`, e.g. feedback or
damping); several are added by passing a tuple. `simulate(..., forcing=..., args=...)`
takes one of them.
"""

from __future__ import annotations

import abc
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree, Scalar

from ._checks import is_concrete


class AbstractStepForce(eqx.Module):
    """The external force over one step, a callable `(t, g, m) -> (d,)`.

    `depends_on_momentum()` says whether the end-of-step kick `f_k⁺` must be solved
    implicitly (known when the step is traced).
    """

    def depends_on_momentum(self) -> bool:
        return True

    @abc.abstractmethod
    def __call__(
        self, t: Scalar, g: Float[Array, "n n"], m: Float[Array, " d"]
    ) -> Float[Array, " d"]:
        """The generalised force at time `t` and state `(g, m)`."""


class HeldForce(AbstractStepForce):
    """A force held constant over the step (zero-order hold)."""

    value: Float[Array, " d"]

    def depends_on_momentum(self) -> bool:
        return False

    def __call__(self, t, g, m):
        return self.value


class LawForce(AbstractStepForce):
    """A force law `fn(t, g, m, args)` with its `args` bound."""

    fn: Callable
    args: PyTree

    def __call__(self, t, g, m):
        return self.fn(t, g, m, self.args)


class SumForce(AbstractStepForce):
    """The sum of several step forces."""

    forces: tuple[AbstractStepForce, ...]

    def depends_on_momentum(self) -> bool:
        return any(f.depends_on_momentum() for f in self.forces)

    def __call__(self, t, g, m):
        return sum(f(t, g, m) for f in self.forces)


class AbstractForcing(eqx.Module):
    """An external generalised force (in the dual of the algebra) acting on a system.

    Subclasses give the per-step data (`per_step`, arrays with a leading axis of length
    `n_steps`, scanned over by `simulate`) and `at_step`, the force over one step.
    """

    def per_step(self) -> PyTree:
        """Data indexed by step (leading axis `n_steps`), or `None`."""
        return None

    @abc.abstractmethod
    def at_step(self, data: PyTree, args: PyTree) -> AbstractStepForce:
        """The force over a step, given that step's slice of `per_step()` and `args`."""

    def check(self, system, n_steps: int, dtype, args) -> None:
        """Raise `ValueError` for input that cannot be right (shapes, NaN), before tracing."""

    def batch_axes(self, system) -> PyTree:
        """`jax.vmap` in-axes of this forcing in a batch of `system`s: shared by default."""
        return None

    def per_step_axes(self, system) -> PyTree:
        """The batch axis of each leaf of `per_step()` in a batch of `system`s (`0`:
        per-member data `(batch, n_steps, …)`), or `None` where it is shared."""
        if self.batch_axes(system) is None:
            return None
        return jax.tree.map(lambda _: 0, self.per_step())

    def check_batch(self, system, batch: int) -> None:
        """Raise `ValueError` if per-member data does not have `batch` rows."""

    def steps(self, start: int, n: int) -> AbstractForcing:
        """The forcing over steps `start, …, start + n − 1` of a run, for a run cut into
        segments (each a `simulate` call from its own `t0`): unchanged by default, since
        a force law reads the time; data indexed by step is sliced."""
        return self


class Control(AbstractForcing):
    """A control sequence held constant over each step (zero-order hold).

    **Arguments:**

    - `u`: shape `(n_steps, d)`: `u[k]` is the generalised force (for the rigid body, the
      body-frame torque) over step `k`, from `t_k` to `t_{k+1}`; for a system of several
      bodies, one row per body, `(n_steps, *momentum_shape)` (for `lievi.RigidBodies` of
      N bodies `(n_steps, N, 6)`: each body's body-frame torque and force). A pytree
      leaf: gradients with respect to the whole sequence come from `jax.grad` (implicit
      differentiation through the Newton solves, no unrolled iterations).

    The discrete forces are `f_k⁻ = f_k⁺ = (h/2) u[k]`.

    `u` may be any array-like (a JAX or NumPy array, nested lists or tuples of numbers);
    it is converted with `jnp.asarray`, integers to the default float dtype. For
    `lievi.simulate_batch` it may also have a leading batch axis, `(batch, n_steps, d)`,
    one sequence per member of the batch.
    """

    u: Float[Array, "n_steps d"]

    def __init__(self, u):
        self.u = _as_control(u)

    def per_step(self):
        return self.u

    def at_step(self, data, args):
        return HeldForce(data)

    def _per_member(self, system) -> bool:
        """Whether `u` has a batch axis in front of one run's `(n_steps, *momentum_shape)`:
        decided by the system's momentum shape, since a system of N bodies has per-body
        rows of its own (`(n_steps, N, 6)` is one run's control, not a batch)."""
        return jnp.ndim(self.u) == 2 + len(system.momentum_shape())

    def batch_axes(self, system):
        # The in-axes pytree is built by `tree.map`, which bypasses `__init__`.
        return jax.tree.map(lambda _: 0, self) if self._per_member(system) else None

    def check_batch(self, system, batch):
        if self._per_member(system) and jnp.shape(self.u)[0] != batch:
            shape = ", ".join(("batch", "n_steps", *map(str, system.momentum_shape())))
            raise ValueError(
                f"`forcing`: a control per member of the batch must have shape ({shape}) "
                f"with batch = {batch}, got {jnp.shape(self.u)}."
            )

    def steps(self, start, n):
        # One run's rows (a batch of sequences is not cut into segments); `start` may be
        # traced (the segments of a run looped over in one program).
        return Control(jax.lax.dynamic_slice_in_dim(self.u, start, n))

    def check(self, system, n_steps, dtype, args):
        momentum = system.momentum_shape()
        expected = (n_steps, *momentum)
        shape = tuple(jnp.shape(self.u))
        if shape != expected:
            what = (
                f"one generalised force of dimension {momentum[0]} per step"
                if len(momentum) == 1
                else f"one generalised force of shape {momentum} per step, a row per body"
            )
            raise ValueError(
                f"`forcing`: the control `u` must have shape {expected} ({what}, held over "
                f"the step), got {shape}."
            )
        if is_concrete(self.u) and not np.all(np.isfinite(np.asarray(self.u))):
            bad = int(np.argmax(~np.all(np.isfinite(np.asarray(self.u)), axis=-1)))
            raise ValueError(
                f"`forcing`: the control `u` contains NaN or inf (first at step {bad}); pass "
                "finite controls."
            )


def _as_control(u) -> Array:
    """`u` as a real array of shape `(n_steps, d)` (or with more axes: per body, per member
    of a batch; `Control.check` compares them with the system's), else a
    `ValueError` naming the argument and the fix."""
    fix = (
        "pass a real array of shape (n_steps, d), one generalised force of dimension d per "
        "step (for the rigid body, d = 3: e.g. jnp.zeros((n_steps, 3)); for N bodies, "
        "(n_steps, N, 6)), with a leading batch axis for lievi.simulate_batch"
    )
    if u is None or isinstance(u, (str, bytes)):
        raise ValueError(f"`u` of lievi.Control: {fix}; got {u!r}.")
    try:
        array = jnp.asarray(u)
    except (TypeError, ValueError) as error:  # ragged nested lists, non-numeric objects
        raise ValueError(
            f"`u` of lievi.Control could not be converted to an array ({error}); {fix}."
        ) from error
    dtype = array.dtype
    if jnp.issubdtype(dtype, jnp.integer):
        array = jnp.asarray(array, dtype=float)
    elif not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"`u` of lievi.Control must hold real numbers, got dtype {dtype}; {fix}.")
    if array.ndim < 2 or 0 in array.shape[-1:]:
        raise ValueError(f"`u` of lievi.Control has shape {array.shape}; {fix}.")
    return array


class ForceLaw(AbstractForcing):
    """A force given as a function of time and state: feedback, damping, disturbances.

    **Arguments:**

    - `fn`: `fn(t, g, m, args) -> (d,)`, the generalised force (for the rigid body, the
      body torque) at time `t`, attitude `g` and momentum `m`. May be a plain function or
      an `eqx.Module` (e.g. an `eqx.nn.MLP` wrapped in a function of `(t, g, m, args)`),
      whose parameters are then pytree leaves. Damping `−cΩ` of a rigid body is
      `lambda t, g, m, c: -c * m / inertia`.

    `args` of `simulate` is passed through unchanged (as in diffrax), so parameters you
    differentiate with respect to may live in either place. The discrete forces are
    `f_k⁻ = (h/2) fn(t_k, g_k, m_k)` and `f_k⁺ = (h/2) fn(t_{k+1}, g_{k+1}, m_{k+1})`,
    the latter solved implicitly (a force that does not depend on `m` converges in one
    Newton iteration).
    """

    fn: Callable

    def at_step(self, data, args):
        return LawForce(self.fn, args)

    def check(self, system, n_steps, dtype, args):
        # One state's shapes: `(n, n)` and `(d,)`, per body for a system of several.
        element, momentum = system.element_shape(), system.momentum_shape()
        probe = (
            jax.ShapeDtypeStruct((), dtype),
            jax.ShapeDtypeStruct(element, dtype),
            jax.ShapeDtypeStruct(momentum, dtype),
        )
        try:
            out = jax.eval_shape(lambda t, g, m: self.fn(t, g, m, args), *probe)
        except Exception as error:  # the user's function, any failure: say whose it is
            raise ValueError(
                f"`forcing`: the force law could not be evaluated as fn(t, g, m, args) with "
                f"t a scalar, g {element}, m {momentum}: {error}"
            ) from error
        if getattr(out, "shape", None) != momentum:
            raise ValueError(
                f"`forcing`: the force law must return a generalised force of shape "
                f"{momentum}, got {getattr(out, 'shape', type(out).__name__)}."
            )


class ForcingSum(AbstractForcing):
    """Several forcings acting together (their forces add): e.g. a control plus damping."""

    terms: tuple[AbstractForcing, ...]

    def per_step(self):
        return tuple(term.per_step() for term in self.terms)

    def at_step(self, data, args):
        return SumForce(tuple(term.at_step(x, args) for term, x in zip(self.terms, data)))

    def check(self, system, n_steps, dtype, args):
        for term in self.terms:
            term.check(system, n_steps, dtype, args)

    def batch_axes(self, system):
        return ForcingSum(tuple(term.batch_axes(system) for term in self.terms))

    def per_step_axes(self, system):
        return tuple(term.per_step_axes(system) for term in self.terms)

    def check_batch(self, system, batch):
        for term in self.terms:
            term.check_batch(system, batch)

    def steps(self, start, n):
        return ForcingSum(tuple(term.steps(start, n) for term in self.terms))


def as_forcing(forcing) -> AbstractForcing | None:
    """`None`, an `AbstractForcing`, or a tuple/list of them (added); else an error."""
    if forcing is None or isinstance(forcing, AbstractForcing):
        return forcing
    if isinstance(forcing, (tuple, list)) and all(isinstance(f, AbstractForcing) for f in forcing):
        return ForcingSum(tuple(forcing))
    raise ValueError(
        "`forcing` must be None, a lievi.Control(u) (a control sequence of shape (n_steps, d)), "
        "a lievi.ForceLaw(fn) with fn(t, g, m, args), or a tuple of them; got "
        f"{type(forcing).__name__}. A bare array of controls: wrap it as lievi.Control(u); a "
        "function: lievi.ForceLaw(fn)."
    )
