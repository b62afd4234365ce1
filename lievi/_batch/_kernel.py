"""The interface of a structure-of-arrays step: what an integrator hands `simulate_batch`.

An integrator that has a fast batched step for a system returns one of these from
`AbstractIntegrator.batch_kernel(system)` (`None` where it has none); `simulate_batch`
runs it inside one `lax.scan` and never asks which integrator it came from. A kernel sees
the state as structure of arrays: `g` as 9 arrays (row-major), `Π` as 3, each of shape
`(B,)` with the batch minor, so that XLA emits long elementwise loops it vectorises.

Kernels are differentiable in both modes: explicit ones by hand-written tangents
(`_explicit_adjoints.py`), implicit ones by the implicit function theorem at each step's
converged root (no differentiation through the Newton iterations or their
`while_loop`). The root is tagged `ROOT_NAME` (see `jax.ad_checkpoint.checkpoint_name`)
so that `simulate_batch` can keep it across a `jax.checkpoint`: the backward pass then
re-evaluates the explicit part of a step from the stored root instead of solving again.
"""

from __future__ import annotations

import abc
import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp

from .._results import RESULTS

ROOT_NAME = "lievi_step_root"


def materialise(values, one, stack: bool = True):
    """`values / one` with `one` an array of ones computed at run time: forces XLA to store
    `values` instead of recomputing them in every consumer.

    XLA's CPU fusion duplicates a cheap producer into each of its consumers; a step with
    12 outputs that all depend on one chain of cheap elementwise work then evaluates that
    chain up to 12 times (measured 5–10× the operation count of the step, 2–3× the run
    time). A floating division counts as expensive (`InstructionFusion::IsExpensive`), so
    its result is computed once and kept. `one` must not be a constant, or the division
    is simplified away: it is built from the state (`x·0 + 1`).

    Scalars (one body: `simulate`'s step) are stored together, three to an array: each
    stored array is a kernel launch, and for one body the launches, not the arithmetic,
    set the time (measured: the SE(3) step 1.4–1.6× faster than with each scalar stored
    alone). Three, because XLA fuses the computation of a short stack into one loop but
    computes each entry of a longer one (9, 12) in a loop of its own (measured: 0.98
    against 1.10 µs a step, Cayley chart).
    `stack=False` stores them one by one (see its use in `_fast_se3`).
    """
    if stack and all(jnp.ndim(v) == 0 for v in values):
        out = []
        for k in range(0, len(values), 3):
            stacked = jnp.stack(jnp.broadcast_arrays(*values[k : k + 3])) / one
            out.extend(stacked[i] for i in range(stacked.shape[0]))
        return tuple(out)
    return tuple(v / one for v in values)


def compacted_tail(need, run, state, args, fraction: int = 8):
    """`run(state, args)` (a `while_loop` of Newton steps) for the bodies where `need`,
    the others unchanged; nothing when no body needs it.

    `state` and `args` are pytrees of per-body arrays `(B,)` (or scalars shared by the
    batch). When at most `B // fraction` bodies need it (a few stragglers, the usual case),
    they are gathered into arrays of that size, run there and scattered back: the loop
    then costs a fraction of a step, where on the whole batch, masked, one iteration costs
    about as much as a Newton iteration of every body. Otherwise the whole batch runs.
    `run` must leave alone the bodies whose `args` mark them inactive: the gathered
    padding is passed with `args[-1]` (the `alive` mask) false.
    """
    batch = jnp.shape(need)[0] if jnp.ndim(need) else 0
    size = batch // fraction
    if size < 1:
        return jax.lax.cond(jnp.any(need), run, lambda s, _: s, state, args)
    count = jnp.sum(need.astype(jnp.int32))

    def gathered(state, args):
        index = jnp.nonzero(need, size=size, fill_value=batch)[0]

        def take(y):
            return jnp.take(y, index, mode="clip") if jnp.ndim(y) else y

        sub_state, sub_args = jax.tree.map(take, (state, args))
        sub_args = (*sub_args[:-1], sub_args[-1] & (index < batch))
        out = run(sub_state, sub_args)
        return jax.tree.map(lambda y, s: y.at[index].set(s, mode="drop"), state, out)

    branch = jnp.where(count == 0, 0, jnp.where(count <= size, 1, 2))
    return jax.lax.switch(branch, (lambda s, _: s, gathered, run), state, args)


class AbstractBatchKernel(eqx.Module):
    """One step of a method on a batch of bodies, as structure of arrays.

    The kernel owns its state layout: `constants` splits the system's per-body constants,
    `carried` the initial elements, `elements` joins the saved entries back into group
    elements; the momentum is one array per component. The defaults are those of a rigid
    body on SO(3) with principal moments (3 moments, `g` as 9 entries, `Π` as 3).
    """

    @abc.abstractmethod
    def prepare(self, inertia, h):
        """Per-run constants from the system's constants `inertia` (what `constants`
        returned: by default the 3 principal moments, arrays or scalars) and the step `h`
        (an array `(B,)` or a scalar), computed once outside the loop."""

    @abc.abstractmethod
    def step(self, params, g, Pi, alive):
        """Advance `(g, m)` by one step.

        `params`: what `prepare` returned; `g`: the carried entries (`carried`); `Pi`: the
        momentum's components (3 on SO(3)); `alive`: a boolean `(B,)` mask of the bodies
        that have not failed (a failed body's step is computed but must not cost extra
        work, e.g. Newton iterations past the fixed ones).

        **Returns:** `(g_next, m_next, result, iterations, residual)`, the last three per body.
        """

    def constants(self, moments, batch: int):
        """The system's per-body constants as structure of arrays, from what the system
        handed `simulate_batch` (`AbstractLieSystem.batch_kernel`): by default the
        principal moments `(3,)` or `(B, 3)`, as 3 arrays `(B,)`."""
        return tuple(jnp.broadcast_to(moments[..., i], (batch,)) for i in range(3))

    def turn_rates(self, constants, h):
        """Per-run constants of `turn_squared` (computed once, outside the loop): by
        default `|h|/I_p`."""
        return tuple(jnp.abs(h) / constants[i] for i in range(3))

    def turn_squared(self, rates, m):
        """`(h|ω|)²`, the squared angle turned in one step at momentum `m` (components),
        for the step bound `h|ω| ≤ integrator.step_bound()`: by default `|h I⁻¹Π|²`. A
        square and products only: no division or square root per body-step."""
        return sum((m[i] * rates[i]) ** 2 for i in range(3))

    def elements(self, entries):
        """Saved carried entries `(T, k, B)` back to group elements `(B, T, n, n)`: by
        default the 9 entries of a rotation, row-major."""
        return jnp.moveaxis(entries, -1, 0).reshape(entries.shape[-1], entries.shape[0], 3, 3)

    def one_body(self):
        """This kernel as `simulate` runs it on one body (`AbstractLieSystem.kernel_step`,
        every component a scalar): by default the same."""
        return self

    def on_se3(self):
        """This method's kernel for the free rigid body on SE(3) (`RigidBodySE3` without a
        potential), or `None` where it has none (the default)."""
        return None

    def with_fixed_iterations(self, fixed_iterations: int):
        """The kernel with this many Newton iterations before its convergence check
        (`simulate_batch(fixed_iterations=...)`); explicit kernels ignore it."""
        return self

    def carried(self, g0):
        """The configuration state this kernel carries, from the initial elements `g0`
        `(B, 3, 3)`: by default all of `g`, 9 arrays (row-major)."""
        return tuple(g0[:, i, j] for i in range(3) for j in range(3))

    def reduced(self):
        """This kernel on the reduced state `(Π, Γ)` of a potential with an advected
        parameter (`AbstractPotential.advected_direction`), carrying `Γ` (3 arrays) in
        place of `g` (9), or `None` where it has none (the default: free bodies, and
        potentials that need all of `g`). `simulate_batch` uses it when `g` is not saved."""
        return None

    def advected(self, state):
        """The advected parameter `Γ` (3 arrays) from the carried state, or `None` where
        this kernel's system has none."""
        return None


class KickKernel(AbstractBatchKernel):
    """A free kernel between two half kicks of a potential's torque (paper §7): the step of
    `AbstractKickIntegrator` (`Π⁺ = Π + (h/2)M(g_k)`, free step, `Π_{k+1} = Π⁻ + (h/2)M(g_{k+1})`)
    for a potential with a closed-form `rigid_body_torque` (e.g. `UniformGravity`).

    With `reduced_state` (see `reduced`) the configuration carried is the advected
    parameter `Γ = gᵀa` alone, and the kicks are `M(Γ)`: the free kernel maps `Γᵀ`, one
    row, as it maps each row of `g` (`r ↦ r F_k`), so `Γ_{k+1} = F_kᵀΓ_k` — the
    Bobenko–Suris reduced discrete Lie–Poisson equations on `(Π, Γ)` (paper §7), with
    the same floating-point operations on `Π` and on `Γ` as the run that carries `g`.
    """

    free: AbstractBatchKernel
    potential: eqx.Module
    reduced_state: bool = eqx.field(default=False, static=True)

    @staticmethod
    def applies_to(potential) -> bool:
        """Whether `potential` has a closed-form rigid-body torque."""
        return potential.rigid_body_torque(tuple(jnp.zeros(()) for _ in range(9))) is not None

    def with_fixed_iterations(self, fixed_iterations: int):
        return dataclasses.replace(self, free=self.free.with_fixed_iterations(fixed_iterations))

    def reduced(self):
        if self.reduced_state:
            return self
        zeros = tuple(jnp.zeros(()) for _ in range(3))
        if (
            self.potential.advected_direction() is None
            or self.potential.rigid_body_advected_torque(zeros) is None
        ):
            return None
        return dataclasses.replace(self, reduced_state=True)

    def _advected_of_rows(self, g):
        # Γ_j = Σ_i a_i g_ij (a may carry a batch axis first, like the potential's leaves).
        a = jnp.asarray(self.potential.advected_direction(), g[0].dtype)
        return tuple(sum(a[..., i] * g[3 * i + j] for i in range(3)) for j in range(3))

    def carried(self, g0):
        g = super().carried(g0)
        return self._advected_of_rows(g) if self.reduced_state else g

    def advected(self, state):
        if self.reduced_state:
            return state
        if self.potential.advected_direction() is None:
            return None
        return self._advected_of_rows(state)

    def _torque(self, state):
        if self.reduced_state:
            return self.potential.rigid_body_advected_torque(state)
        return self.potential.rigid_body_torque(state)

    def prepare(self, inertia, h):
        return self.free.prepare(inertia, h), h / 2

    def step(self, params, g, Pi, alive):
        free_params, half = params
        torque = self._torque(g)
        Pi = tuple(p + half * t for p, t in zip(Pi, torque))
        g_next, Pi_next, result, iterations, residual = self.free.step(free_params, g, Pi, alive)
        torque = self._torque(g_next)
        Pi_next = tuple(p + half * t for p, t in zip(Pi_next, torque))
        # A non-finite torque shows up only after the free step's own checks.
        finite = jnp.isfinite(Pi_next[0]) & jnp.isfinite(Pi_next[1]) & jnp.isfinite(Pi_next[2])
        result = jnp.where((result == RESULTS.successful) & ~finite, RESULTS.nonfinite, result)
        return g_next, Pi_next, result, iterations, residual
