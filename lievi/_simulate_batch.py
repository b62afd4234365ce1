"""`simulate_batch`: many bodies at once, with fast paths for rigid bodies.

Semantics are those of `jax.vmap(simulate)` over the bodies (the generic path is exactly
that); for `RigidBody` with principal moments and the integrators that have one (`DEP`,
`MoserVeselov`: `_kernels/_so3.py`; `LiePoissonSplitting`, `RK4`: `_kernels/_explicit.py`), a
structure-of-arrays fast path computes the same iterates to round-off, 10–50× faster on
CPU (`benchmarks/throughput.py`); for the free `RigidBodySE3` with `DEP` (both charts),
`_kernels/_se3.py` (`benchmarks/se3_step_cost.py`). The system picks the kernel
(`AbstractLieSystem.batch_kernel`) and the kernel owns its state layout
(`AbstractBatchKernel`); nothing here depends on the group. Everything runs inside one jit-compiled `lax.scan`: no host
synchronisation per step. For a potential with an advected parameter (`UniformGravity`:
`Γ = gᵀe₃`) and a run that does not save `g`, the fast path carries the reduced state
`(Π, Γ)` of the paper's §7 instead of `(Π, g)` (`AbstractBatchKernel.reduced`).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._checks import (
    abstract_key,
    abstract_tree,
    check_finite,
    check_real_dtype,
    is_concrete,
    state_dtype,
)
from ._integrators._base import AbstractIntegrator
from ._loop import Run, execute, raise_if_failed
from ._options import OPTIONS, Tuning, options
from ._progress import AbstractProgressMeter
from ._save import Save
from ._solution import Solution
from ._steppers import plan_for
from ._systems._base import AbstractLieSystem


def has_fast_path(
    system: AbstractLieSystem, integrator: AbstractIntegrator, system_axis=None
) -> bool:
    """Whether `simulate_batch` has a structure-of-arrays fast path for this pair
    (`system_axis` as in `simulate_batch`, inferred for a batch built with `jax.vmap`)."""
    system_axis = infer_system_axis(system, system_axis)
    return integrator.batch_kernel(system, system_axis is not None) is not None


def _is_one_system(system) -> bool:
    """Whether `system` describes one system: its energy of one momentum `(d,)` and its
    potential at one element `(n, n)` are scalars, and its velocity of that momentum has
    the momentum's shape (by shapes alone, nothing computed).

    Cached by the system's structure, its non-array fields and its arrays' shapes and
    dtypes: tracing the energy and the potential again cost about 7 ms of every eager
    `simulate_batch` call, more than half of a 100-step run of 64 SE(3) bodies (12.1 →
    4.7 ms, `benchmarks/compile_time.py --throughput`)."""
    dtype = state_dtype(system)
    g = jax.ShapeDtypeStruct(system.element_shape(), dtype)
    m = jax.ShapeDtypeStruct(system.momentum_shape(), dtype)
    key = abstract_key(system)
    try:
        return _scalar_energy_and_potential(key, g, m)
    except TypeError:  # an unhashable field (e.g. a list): not cached
        return _scalar_energy_and_potential.__wrapped__(key, g, m)


@functools.lru_cache(maxsize=64)
def _scalar_energy_and_potential(key, g, m) -> bool:
    def both(system, g, m):
        return system.energy(m), system.potential_energy(g), system.velocity(m)

    try:
        energy, potential, velocity = eqx.filter_eval_shape(both, abstract_tree(key), g, m)
    except Exception:  # e.g. a (B, 3) inertia against a (3,) momentum
        return False
    # The velocity too: an energy summed over bodies is a scalar even for a batch of
    # systems whose leaves broadcast against one state (`(B, N, 3)` moments of rotors).
    return jnp.shape(energy) == jnp.shape(potential) == () and velocity.shape == m.shape


def infer_system_axis(system, system_axis, batch: int | None = None):
    """`system_axis`, or for `None` the axis a batch of systems carries: `None` for one
    system, `0` for a batch built with `jax.vmap` (every array leaf with the same leading
    size — `batch`, where known — and one system per index along it). Anything else
    raises a `ValueError` that says what to pass."""
    if system_axis is not None or _is_one_system(system):
        return system_axis
    leaves = jax.tree.leaves(eqx.filter(system, eqx.is_array))
    sizes = sorted({jnp.shape(x)[0] if jnp.ndim(x) else 0 for x in leaves})
    first = jax.tree.map(lambda x: x[0] if eqx.is_array(x) and jnp.ndim(x) else x, system)
    if len(sizes) == 1 and sizes[0] > 0 and _is_one_system(first):
        if batch is None or sizes == [batch]:
            return 0
        raise ValueError(
            f"`system` is a batch of {sizes[0]} systems (e.g. built with `jax.vmap`) but `g0` "
            f"has {batch} bodies; pass one system per body and `system_axis=0`."
        )
    raise ValueError(
        "`system` is not one system (its energy or potential is not a scalar) nor a batch "
        f"along the leading axis of its array leaves (leading sizes {sizes}). For a batch "
        "built with `jax.vmap(lievi.RigidBody)(inertias)` pass `system_axis=0`; for one "
        "system shared by all bodies, build it from unbatched parameters."
    )


def _check_batch(name, x, shape_tail, what):
    shape = tuple(jnp.shape(x))
    if len(shape) != 1 + len(shape_tail) or shape[1:] != tuple(shape_tail):
        raise ValueError(
            f"`{name}` must have shape (batch, {', '.join(map(str, shape_tail))}) ({what}), "
            f"got {shape}. For one body use `lievi.simulate`."
        )
    check_finite(name, x)


def simulate_batch(
    system: AbstractLieSystem,
    integrator: AbstractIntegrator,
    g0,
    m0,
    *,
    h,
    n_steps: int,
    save: Save = OPTIONS["save"],
    t0=OPTIONS["t0"],
    throw: bool = OPTIONS["throw"],
    checkpoint: bool | int = OPTIONS["checkpoint"],
    progress_meter: AbstractProgressMeter | bool | str = OPTIONS["progress_meter"],
    forcing=OPTIONS["forcing"],
    args=OPTIONS["args"],
    monitor=OPTIONS["monitor"],
    tuning: Tuning = OPTIONS["tuning"],
    system_axis: int | None = None,
    **deprecated,
) -> Solution:
    """Integrate a batch of `B` bodies: `jax.vmap(simulate)` with a fast path.

    **Arguments:**

    - `system`: one system shared by all bodies (`system_axis=None`), or a batch of
      systems whose array leaves carry the batch as their leading axis (`system_axis=0`),
      e.g. `jax.vmap(lievi.RigidBody)(inertias)` for `inertias` of shape `(B, 3)`.
    - `integrator`: e.g. `lievi.DEP(chart="exp")`.
    - `g0`: initial group elements, `(B, n, n)`, or one `(n, n)` for every body; `m0`:
      initial momenta, `(B, d)`.
    - `h`: one step size, or one per body, shape `(B,)`.
    - `n_steps`: number of steps.
    - `system_axis`: `None` or `0`, as `in_axes` of `jax.vmap` for `system`. Left at
      `None` for a batch of systems built with `jax.vmap` (every array leaf one dimension
      larger than one system's, with leading size `B`), it is inferred as `0`; a system
      that is neither one system nor such a batch raises a `ValueError`. (A batch of
      three principal-moment vectors, `(3, 3)`, is also one valid inertia tensor: pass
      `system_axis=0` for it.)
    - `save`, `t0`, `throw`, `checkpoint`, `progress_meter`, `forcing`, `args`,
      `monitor`, `tuning`: the options of every run function, as `lievi.simulate` (the
      same defaults). For a batch: `throw=True` raises if any body failed, while with
      `throw=False` each body's `result` says whether it succeeded and a failed body does
      not stop the others; a `lievi.Control(u)` with `u` of shape `(B, n_steps, d)` gives
      each body its own control sequence, of shape `(n_steps, d)` one shared by all (for
      systems of N bodies, `(B, n_steps, N, 6)` and `(n_steps, N, 6)`); a force law and
      `args` are shared; one progress line or bar for the whole batch. For a potential
      with an advected parameter (e.g. `UniformGravity`) `Γ_k = g_kᵀa` is
      `Solution.advected`, `(B, T, 3)`, whenever `save.g` or `save.advected`, and
      **`save` also picks the algorithm of its fast path:** without `g` it carries the
      reduced state `(Π, Γ)` instead of `(Π, g)` — the reduced discrete Lie–Poisson
      equations of the paper's §7, `Γ_{k+1} = F_kᵀΓ_k`, half the state — which gives the
      same `Π_k`, `Γ_k` to round-off (docs/potentials.md).

    The fast path (`lievi.advanced.has_fast_path`): the integrator's structure-of-arrays
    kernel, for a system with `principal_moments` — the rigid body with `DEP` (both
    charts), `MoserVeselov`, `LiePoissonSplitting` or `RK4`; in `UniformGravity` (the
    heavy top) the first three; `RigidBodySE3` without a potential, any kinetic tensor,
    and `DEP`, both charts. Forced runs take the generic path. Its iterates equal the
    generic path's to round-off, and so do its derivatives: reverse mode goes through
    the fast path, implicit steps by the implicit function theorem at each step's
    converged root with the closed-form 3×3 Jacobian (the Newton iterations are not
    differentiated). `tuning=lievi.advanced.Tuning(fast=False)` runs `jax.vmap(simulate)`.

    Both paths apply the same checks as `simulate`, per body: a bad value of a body's
    system, `g0`, `m0` or `h` gives `RESULTS.invalid_input` (also when they are traced,
    e.g. a vmapped system), a non-finite `g` or `m` gives `RESULTS.nonfinite`, and a step
    past `integrator.step_bound()` gives `RESULTS.step_too_large` (docs/guarantees.md).

    **Returns:** a `Solution` whose fields have a leading batch axis: `ts` `(B, T)`, `g`
    `(B, T, n, n)`, `m` `(B, T, d)`, `result` `(B,)`, `stats[...]` `(B, …)` — as
    `jax.vmap(simulate)` would give. On the fast path `stats["newton_iterations"]`
    counts the fixed iterations too (the generic path stops at convergence).

    To spread the batch over several devices, place the inputs with
    `lievi.shard_batch`; the jit-compiled loop then runs sharded (see the README).
    """
    opts = options("lievi.simulate_batch", n_steps, locals(), deprecated)
    n_steps, save, forcing = opts.n_steps, opts.save, opts.forcing
    if save.advected and (
        system.potential is None or system.potential.advected_direction() is None
    ):
        raise ValueError(
            "`save.advected` but the system's potential has no advected parameter "
            "(`AbstractPotential.advected_direction` is None; e.g. `lievi.UniformGravity` has "
            "one); save `g` instead."
        )
    if system_axis not in (None, 0):
        raise ValueError(f"`system_axis` must be None (shared system) or 0, got {system_axis!r}.")
    # One state's shapes, `(n, n)` and `(d,)` (per body for a system of several bodies).
    element, momentum = system.element_shape(), system.momentum_shape()
    for name, x in (("g0", g0), ("m0", m0), ("h", h)):
        if isinstance(x, (bool, np.bool_)):
            raise ValueError(f"`{name}` must hold real numbers, got {x!r}.")
        check_real_dtype(name, x)
    # JAX arrays (or tracers) kept, anything else read on the host: no program compiled.
    g0, m0 = (x if isinstance(x, jax.Array) else np.asarray(x) for x in (g0, m0))
    if jnp.shape(g0) == element and jnp.ndim(m0) == 1 + len(momentum):
        # One initial element for every body (e.g. all starting at the identity): on the
        # host where concrete (no program compiled for it).
        shape = (jnp.shape(m0)[0], *element)
        g0 = (
            np.broadcast_to(np.asarray(g0), shape)
            if is_concrete(g0)
            else (jnp.broadcast_to(g0, shape))
        )
    _check_batch("g0", g0, element, "one group element per body")
    _check_batch("m0", m0, momentum, "one momentum per body")
    batch = jnp.shape(g0)[0]
    if batch == 0:
        raise ValueError("the batch is empty (`g0` has 0 bodies); pass at least one body.")
    if jnp.shape(m0)[0] != batch:
        raise ValueError(
            f"`g0` and `m0` must have the same batch size, got {batch} and {jnp.shape(m0)[0]}."
        )
    check_batch_h(h, batch)
    system_axis = infer_system_axis(system, system_axis, batch)
    if system_axis == 0:
        sizes = {
            jnp.shape(x)[0] for x in jax.tree_util.tree_leaves(eqx.filter(system, eqx.is_array))
        }
        if sizes != {batch}:
            raise ValueError(
                f"with `system_axis=0` every array leaf of `system` must have leading axis "
                f"{batch}, got leading sizes {sorted(sizes)}; build it with "
                "`jax.vmap(lievi.RigidBody)(inertias)`."
            )
    dtype = state_dtype(system, g0, m0, h)
    if forcing is not None:
        forcing.check_batch(system, batch)
        for x in jax.tree.leaves(forcing.per_step()):
            check_finite("forcing", x)
        # One member's run takes what `simulate` takes (shapes, values).
        member = _member(forcing, forcing.batch_axes(system))
        member.check(_member(system, system.batch_axes(system_axis)), n_steps, dtype, args)
    plan = plan_for(
        system,
        integrator,
        system_axis,
        forcing,
        args,
        tuning=opts.tuning,
        # A monitor reads `g` at every save: not the reduced state.
        carry_g=save.g or opts.monitor is not None,
    )
    run = Run.of(plan, opts, dtype)

    def explain():
        # An eager run with a bad input: the group's own test (`check_element`'s) names
        # the body (on SE(3) a pose is not an orthogonal matrix).
        system.check_elements("g0", g0)

    solution = execute(run, g0, m0, h, t0, n_steps, opts.save.every, explain=explain)
    if throw:
        solution = raise_if_failed(solution, "lievi.simulate_batch", "a body")
    return solution


def check_batch_h(h, batch: int) -> None:
    """`h`: a scalar or one per body `(batch,)`; concrete values finite, positive, normal."""
    if jnp.ndim(h) not in (0, 1) or (jnp.ndim(h) == 1 and jnp.shape(h)[0] != batch):
        raise ValueError(
            f"`h` must be a scalar or have shape ({batch},) (one per body), got {jnp.shape(h)}."
        )
    if is_concrete(h):
        check_finite("h", h)
        if not np.all(np.asarray(h) > 0):
            raise ValueError("`h` must be > 0 for every body; pass positive step sizes.")
        tiny = float(jnp.finfo(jnp.result_type(h, float)).tiny)
        if np.any(np.asarray(h) < tiny):
            raise ValueError(
                f"`h` has subnormal values (below {tiny:.3g}); pass normal step sizes."
            )


def _member(tree, axes):
    """The first member of a batch `tree` whose batched leaves are those with axis `0` in
    `axes` (a `jax.vmap` in-axes prefix), on the host (no program compiled)."""
    if axes is None:
        return tree
    return jax.tree.map(
        lambda x, axis: x if axis is None or not eqx.is_array(x) else np.asarray(x)[0],
        tree,
        axes,
        is_leaf=lambda x: x is None,
    )
