"""`simulate_batch`: many bodies at once — `jax.vmap(simulate)`'s semantics, on the
integrator's structure-of-arrays kernel where it has one for the system
(`AbstractIntegrator.batch_kernel`), else the method's own step under `jax.vmap`."""

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
from ._loop import Run, execute
from ._options import OPTIONS, Tuning, options
from ._progress import AbstractProgressMeter
from ._save import Save
from ._simulate import as_array
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
    """Whether `system` is one system: its energy of one momentum and its potential at one
    element are scalars, its velocity has the momentum's shape (by shapes alone). Cached
    by the system's abstract structure: tracing again cost ~7 ms an eager call."""
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
    size, `batch` where known); anything else is a `ValueError` saying what to pass. An
    explicit `system_axis=0` is checked against `batch` here, before any work (a stream
    would otherwise have created its files)."""
    if system_axis == 0 and batch is not None:
        sizes = {jnp.shape(x)[0] for x in jax.tree.leaves(eqx.filter(system, eqx.is_array))}
        if sizes != {batch}:
            raise ValueError(
                f"with `system_axis=0` every array leaf of `system` must have leading axis "
                f"{batch}, got leading sizes {sorted(sizes)}; build it with "
                "`jax.vmap(lievi.RigidBody)(inertias)`."
            )
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


def batch_size(system, g0, m0, h) -> int:
    """The batch size `B` of `g0` `(B, n, n)` (or one `(n, n)` for every body), `m0`
    `(B, d)` and `h` (a scalar or `(B,)`), from their shapes alone (`g0`, `m0` may be
    memory maps): a `ValueError` naming the argument otherwise."""
    element, momentum = system.element_shape(), system.momentum_shape()
    _check_shape("m0", m0, momentum, "one momentum per body")
    batch = jnp.shape(m0)[0]
    if batch == 0:
        raise ValueError("the batch is empty (`m0` has 0 bodies); pass at least one body.")
    if jnp.shape(g0) != element:
        _check_shape("g0", g0, element, "one group element per body")
        if jnp.shape(g0)[0] != batch:
            raise ValueError(
                f"`g0` and `m0` must have the same batch size, got {jnp.shape(g0)[0]} and {batch}."
            )
    if jnp.ndim(h) not in (0, 1) or (jnp.ndim(h) == 1 and jnp.shape(h)[0] != batch):
        raise ValueError(
            f"`h` must be a scalar or have shape ({batch},) (one per body), got {jnp.shape(h)}."
        )
    return batch


def _check_shape(name, x, shape_tail, what):
    shape = tuple(jnp.shape(x))
    if len(shape) != 1 + len(shape_tail) or shape[1:] != tuple(shape_tail):
        raise ValueError(
            f"`{name}` must have shape (batch, {', '.join(map(str, shape_tail))}) ({what}), "
            f"got {shape}. For one body use `lievi.simulate`."
        )


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
    - `system_axis`: `None` or `0`, as `in_axes` of `jax.vmap` for `system`; `None` is
      inferred as `0` for a batch of systems built with `jax.vmap`, and a system that is
      neither one system nor such a batch is a `ValueError`. (A `(3, 3)` batch of three
      principal-moment vectors is also one inertia tensor: pass `system_axis=0`.)
    - `save`, `t0`, `throw`, `checkpoint`, `progress_meter`, `forcing`, `args`,
      `monitor`, `tuning`: the run options, as `lievi.simulate`. `throw=False`: each
      body's `result` says whether it succeeded, and a failed body does not stop the
      others. A `lievi.Control(u)` with `u` `(B, n_steps, d)` gives each body its own
      controls, `(n_steps, d)` one shared sequence. For a potential with an advected
      parameter (`UniformGravity`) `Solution.advected` is `Γ_k = g_kᵀa`, `(B, T, 3)`,
      whenever `save.g` or `save.advected`; without `save.g` the fast path carries the
      reduced state `(Π, Γ)` of the paper's §7, `Γ_{k+1} = F_kᵀΓ_k`, instead of `(Π, g)`
      (docs/potentials.md).

    The fast path (`lievi.advanced.has_fast_path`; docs/batched.md lists the pairs) gives
    the generic path's iterates and derivatives to round-off; forced runs take the
    generic path. Both check each body as `simulate` does (`RESULTS.invalid_input`,
    `nonfinite`, `step_too_large`; docs/guarantees.md).

    **Returns:** a `Solution` whose fields have a leading batch axis: `ts` `(B, T)`, `g`
    `(B, T, n, n)`, `m` `(B, T, d)`, `result` `(B,)`, `stats[...]` `(B, …)`. On the fast
    path `stats["newton_iterations"]` counts the fixed iterations too.

    To spread the batch over several devices, place the inputs with `lievi.shard_batch`.
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
    element = system.element_shape()  # one body's (of a system of several: `(N, n, n)`)
    check_real_dtype("h", h)
    # JAX arrays (or tracers) kept, anything else read on the host: no program compiled.
    g0, m0 = as_array("g0", g0), as_array("m0", m0)
    batch = batch_size(system, g0, m0, h)
    if jnp.shape(g0) == element:
        # One initial element for every body (e.g. all starting at the identity): on the
        # host where concrete (no program compiled for it).
        g0 = (np if is_concrete(g0) else jnp).broadcast_to(g0, (batch, *element))
    check_finite("g0", g0)
    check_finite("m0", m0)
    _check_h(h)
    system_axis = infer_system_axis(system, system_axis, batch)
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

    def explain(i):
        """Body `i` found invalid by the run: the `ValueError` of its system's own eager
        check of `g0[i]` (the group, and the joints of a system of joints), if that is
        what failed. (A bad parameter of one system of a batch fails that body alone.)"""
        member = _member(system, system.batch_axes(system_axis), i)
        member.check_element(f"g0[{i}]", np.asarray(g0[i]))

    check = ("lievi.simulate_batch", "a body") if throw else None
    return execute(run, g0, m0, h, t0, n_steps, opts.save.every, explain=explain, throw=check)


def _check_h(h) -> None:
    """Concrete step sizes finite, positive and normal (its shape: `batch_size`)."""
    if is_concrete(h):
        check_finite("h", h)
        if not np.all(np.asarray(h) > 0):
            raise ValueError("`h` must be > 0 for every body; pass positive step sizes.")
        tiny = float(jnp.finfo(jnp.result_type(h, float)).tiny)
        if np.any(np.asarray(h) < tiny):
            raise ValueError(
                f"`h` has subnormal values (below {tiny:.3g}); pass normal step sizes."
            )


def _member(tree, axes, i: int = 0):
    """Member `i` of a batch `tree` (`axes`: its `jax.vmap` in-axes), on the host."""
    if axes is None:
        return tree
    return jax.tree.map(
        lambda x, axis: x if axis is None or not eqx.is_array(x) else np.asarray(x)[i],
        tree,
        axes,
        is_leaf=lambda x: x is None,
    )
