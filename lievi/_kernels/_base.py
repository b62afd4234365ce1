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
so that `simulate_batch` and `simulate` can keep it across a `jax.checkpoint`: the
backward pass then re-evaluates the explicit part of a step from the stored root instead of solving again.
"""

from __future__ import annotations

import abc
import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp

from .._groups._so3 import SO3
from .._newton import ROOT_NAME as ROOT_NAME
from .._results import RESULTS

# Whether integrators may run their kernels (`AbstractIntegrator.free_kernel`).
_ENABLED = [True]


def kernels_enabled() -> bool:
    """Whether the fast kernels are on (they are, except inside `reference_path`)."""
    return _ENABLED[0]


@contextlib.contextmanager
def reference_path():
    """Turn every kernel off: inside, `simulate` and `simulate_batch` take the generic path
    (the residual from the group and the Lagrangian, its Jacobian by `jax.jacfwd`, the
    Newton system by `linalg.solve`), the independent reference the kernels are tested
    against (`tests/test_kernel_parity.py`). Internal: for tests and benchmarks.

    The switch is read when a program is traced, so JAX's compiled programs are dropped
    on entry and exit (a program compiled with kernels must not be reused without them).
    """
    jax.clear_caches()
    _ENABLED[0] = False
    try:
        yield
    finally:
        _ENABLED[0] = True
        jax.clear_caches()


def ones(x):
    """An array of ones computed at run time, `x·0 + 1` (the `one` of `materialise`)."""
    return x * 0 + 1


# The most bodies whose values `materialise` stores three to an array.
STACKED_MAX = 2


def _stacked(v) -> bool:
    """Whether `materialise` stores `v` in a stack: a scalar, or the values of 2 to
    `STACKED_MAX` bodies. A batch of one, `(1,)` (an eager one-body `simulate` runs the
    batch kernel), keeps one array per value: stacked, its SO(3) DEP run of 10⁴ steps,
    every step saved, was 1.15× slower, the SE(3) one 1.15× faster (2-core CPU); its
    layout stays."""
    return jnp.ndim(v) == 0 or (jnp.ndim(v) == 1 and 1 < jnp.size(v) <= STACKED_MAX)


def per_run(values):
    """Per-run constants (scalars, or `(B,)` arrays of a batch) as one array `(k, …)`,
    read as components (`x[i]`) as a tuple of them is. Computed in the run's set-up
    program and passed to its loop: there each output array is a kernel XLA compiles on
    its own, so three rates are one kernel instead of three."""
    return jnp.stack(jnp.broadcast_arrays(*values))


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
    against 1.10 µs a step, Cayley chart). So are the values of up to `STACKED_MAX`
    bodies (`(N,)` arrays): the bodies of a binary (`lievi.RigidBodies`) stepped together
    by `bodies_step` keep the layout they had as scalars under `jax.vmap` of the
    one-body step. Not more: a batch of 8 SE(3) bodies ran at 0.8× the body-steps/s
    stacked (2-core CPU).
    `stack=False` stores them one by one (see its use in `_se3`).
    """
    if stack and all(_stacked(v) for v in values):
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
    batch). The bodies that need it are gathered, `B // fraction` at a time, into arrays
    of that size, run there and scattered back, in rounds until none is left: for a few
    stragglers (the usual case) one round, a fraction of a step, where on the whole
    batch, masked, one iteration would cost about a Newton iteration of every body.
    `run` is traced once, for the gathered size: a second copy for the whole batch (a
    branch for "more than `B // fraction` need it") doubled the compile time of the
    tail, the largest part of the SE(3) step's. Each body's values are computed
    elementwise, so they do not depend on which bodies share its round.
    `run` must leave alone the bodies whose `args` mark them inactive: the gathered
    padding is passed with `args[-1]` (the `alive` mask) false.

    A batch of fewer than `fraction` bodies (the few bodies of one system,
    `bodies_step`) runs `run` on all of them: `run` must then also leave alone the bodies
    that do not need it (its loop runs no iteration when none does). For them a
    `lax.cond` on "any body needs it" cost more than that: a binary of
    `lievi.RigidBodies` ran 1000 DEP steps in 7.3 ms with it, 6.5 ms before
    (the forward run of `benchmarks/rigid_bodies_throughput.py --gradient-only`). One body
    (scalars) keeps the `cond`.
    """
    batch = jnp.shape(need)[0] if jnp.ndim(need) else 0
    size = batch // fraction
    if batch and size < 1:
        return run(state, args)
    if size < 1:
        return jax.lax.cond(jnp.any(need), run, lambda s, _: s, state, args)

    def one_round(carry):
        state, left = carry
        index = jnp.nonzero(left, size=size, fill_value=batch)[0]

        def take(y):
            return jnp.take(y, index, mode="clip") if jnp.ndim(y) else y

        sub_state, sub_args = jax.tree.map(take, (state, args))
        sub_args = (*sub_args[:-1], sub_args[-1] & (index < batch))
        out = run(sub_state, sub_args)
        state = jax.tree.map(lambda y, s: y.at[index].set(s, mode="drop"), state, out)
        return state, left.at[index].set(False, mode="drop")

    state, _ = jax.lax.while_loop(lambda carry: jnp.any(carry[1]), one_round, (state, need))
    return state


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

    def prepare_run(self, constants, m0, h):
        """Per-run constants of a run that starts at the momenta `m0` `(B, d)`: by default
        `prepare`'s, which do not depend on them. A kernel whose step depends on each
        trajectory (the preprocessed Moser–Veselov method's modified moments, functions of
        its energy and Casimir) computes that here, once per run, outside the loop."""
        return self.prepare(constants, h)

    @abc.abstractmethod
    def step(self, params, g, m, alive):
        """Advance `(g, m)` by one step.

        `params`: what `prepare` returned; `g`: the carried entries (`carried`); `m`: the
        momentum's components (3 on SO(3)); `alive`: a boolean `(B,)` mask of the bodies
        that have not failed (a failed body's step is computed but must not cost extra
        work, e.g. Newton iterations past the fixed ones).

        **Returns:** `(g_next, m_next, result, iterations, residual)`, the last three per body.
        """

    def physics(self, system, batched: bool = False):
        """The constants of `system` this kernel runs on, or `None` where it does not
        apply to `system` (the integrator then takes its generic step).

        The kernel reads the system's physics (its group, side and kinetic tensor,
        `AbstractLieSystem.kinetic_tensor`); systems know nothing of kernels. By default:
        a left-invariant system on `SO3` with principal moments of inertia, shape `(3,)`
        (`(B, 3)` for a batch of systems built with `jax.vmap`, `batched=True`)."""
        tensor = system.kinetic_tensor()
        if system.group != SO3 or system.side != "left" or tensor is None:
            return None
        return tensor if jnp.ndim(tensor) == 1 + batched else None

    def constants(self, moments):
        """`physics`'s constants as structure of arrays: by default the principal moments,
        `(B, 3)` as 3 arrays `(B,)`, or `(3,)` (one body, or a system shared by the batch)
        as 3 scalars. Shared moments stay scalars, broadcast inside the step's loops:
        as `(B,)` arrays they are read from memory in every stage (measured: `RKMK8`'s
        heavy top at batch 4096 ran at 0.65× the body-steps/s)."""
        return tuple(moments[..., i] for i in range(3))

    def turn_rates(self, constants, h):
        """Per-run constants of `turn_squared` (computed once, outside the loop): by
        default `|h|/I_p`."""
        return per_run([jnp.abs(h) / constants[i] for i in range(3)])

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
        """This kernel as `simulate` runs it on one body (`one_body_step`, every component a
        scalar): by default the same."""
        return self

    def one_body_step(self, system, g, m, h):
        """One step of this kernel on one system, `(g_next, m_next, result, iterations,
        residual)`: `simulate`'s step where the kernel applies (`physics`). Every component
        is a scalar, so under `jax.vmap` (a `(B,)` array each) this is the batched kernel.
        """
        kernel = self.one_body()
        params = kernel.prepare(kernel.constants(self.physics(system)), h)
        # The kernel's own state layout, on a batch of one, as scalars.
        carried, momentum = jax.tree.map(
            lambda e: e[..., 0], (kernel.carried(g[None]), kernel.carried_momentum(m[None]))
        )
        g_next, m_next, *info = kernel.step(params, carried, momentum, True)
        g_next = kernel.elements(jnp.stack(g_next)[None, :, None])[0, 0]
        return (g_next, jnp.stack(m_next), *info)

    def bodies_step(self, physics, g, m, h):
        """One step of this kernel on the N bodies of one system at once (`lievi.RigidBodies`),
        the bodies its batch: `physics` as `physics` returns it for N systems (a leading
        body axis), `g` `(N, n, n)`, `m` `(N, d)`. Returns `(g_next, m_next, result,
        iterations, residual)`, each with the body axis: `one_body_step` of each body, in
        one structure-of-arrays step rather than under `jax.vmap`, whose batching of the
        step's few hundred scalar operations took most of the tracing and made a larger
        program (an SE(3) binary's first `DEP` call: `benchmarks/compile_time.py`)."""
        params = self.prepare(self.constants(physics), h)
        momentum = self.carried_momentum(m)
        g_next, m_next, *info = self.step(params, self.carried(g), momentum, True)
        # The saved layout `(T, k, B)` with one save.
        g_next = self.elements(jnp.stack(g_next)[None])[:, 0]
        return (g_next, jnp.stack(m_next, axis=-1), *info)

    def prepare_stages(self, constants, h, coefficients: tuple[float, ...]):
        """Per-run constants of `step_stages`, the composition `Φ_{γ_s h} ∘ … ∘ Φ_{γ_1 h}`
        of this kernel's step (`lievi.Composition`, `coefficients` the `γ_i`): by default
        each stage's `prepare` at `γ_i h`, stacked along a leading axis of stages."""
        stages = [self.prepare(constants, gamma * h) for gamma in coefficients]
        return jax.tree.map(lambda *xs: jnp.stack(xs), *stages)

    def step_stages(self, params, g, m, alive):
        """One step of the composition (`prepare_stages`), `step`'s returns: by default
        `step` at each stage, in one `lax.scan` over the stages — one stage's code is
        compiled (written out, the 9- and 17-stage compositions compiled 4–17× the inner
        step's code, and on a GPU ran at a half to a quarter of the rate their stage count
        predicts). The codes are the first failing stage's, the iterations summed, the
        residual the largest."""

        def stage(carry, stage_params):
            g, m, result, iterations, residual = carry
            g, m, code, its, res = self.step(stage_params, g, m, alive)
            result = RESULTS.first_failure(result, code)
            return (g, m, result, iterations + its, jnp.maximum(residual, res)), None

        zeros = jnp.zeros(jnp.shape(m[0]), jnp.int32)
        init = (g, m, zeros + RESULTS.successful, zeros, jnp.zeros_like(m[0]))
        return jax.lax.scan(stage, init, params)[0]

    def with_fixed_iterations(self, fixed_iterations: int):
        """The kernel with this many Newton iterations before its convergence check
        (`simulate_batch(fixed_iterations=...)`); explicit kernels ignore it."""
        return self

    def carried(self, g0):
        """The configuration state this kernel carries, from the initial elements `g0`
        `(B, 3, 3)`: by default all of `g`, 9 arrays (row-major)."""
        return tuple(g0[:, i, j] for i in range(3) for j in range(3))

    def carried_momentum(self, m0):
        """The momentum state this kernel carries, from the initial momenta `m0` `(B, d)`:
        by default one array `(B,)` per component. A kernel whose step works on whole
        arrays carries one array `(d, B)` instead (as `carried` may `(k, B)`): either
        layout is read as components (`m[i]`, `(B,)`), and `jnp.stack` of it is `(d, B)`."""
        return tuple(m0[:, i] for i in range(m0.shape[1]))

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
