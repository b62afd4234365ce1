"""`simulate_batch`'s generic path: `jax.vmap(simulate)` over the bodies.

For a method without a structure-of-arrays kernel for the system, and for forced runs.
Eagerly (unforced) the run takes the horizon as traced loop bounds, in blocks
(`lievi._horizon`), as `simulate` itself; otherwise one vmapped static scan.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from ._checks import input_valid
from ._horizon import horizon_traced
from ._progress import NoProgressMeter
from ._simulate import run_kernel, simulate
from ._simulate_generic import simulate_blocks
from ._solution import Solution


def _keep(solution: Solution, save) -> Solution:
    stats = dict(solution.stats)
    if not save.stats:
        del stats["newton_iterations"], stats["residual"]
    keep_advected = save.with_advected()
    return Solution(
        ts=solution.ts,
        g=solution.g if save.g else None,
        m=solution.m if save.m else None,
        result=solution.result,
        stats=stats,
        advected=solution.advected if keep_advected else None,
    )


def simulate_vmap(
    system,
    integrator,
    g0,
    m0,
    h,
    n_steps,
    save_every,
    save,
    system_axis,
    segment,
    forcing=None,
    args=None,
    progress=NoProgressMeter(),
):
    """`jax.vmap(simulate)`; eagerly, in blocks whose program does not depend on the horizon
    (`lievi._horizon`), as `simulate` itself. Where the method has a kernel for the system,
    `simulate` runs it on each body (`lievi._simulate._simulate_on_kernel`), and so does the
    vmapped scan here; the blocks run the generic step, so only a method without one takes
    them (with a kernel, `simulate_batch`'s fast path is the one that compiles once)."""
    on_kernel = run_kernel(system, integrator, forcing, system_axis == 0) is not None
    if forcing is None and not on_kernel and horizon_traced(system, integrator, g0, m0, h):
        axes = (system.batch_axes(system_axis), None if h.ndim == 0 else 0)
        valid = jax.vmap(input_valid, in_axes=(axes[0], 0, 0, axes[1]))(system, g0, m0, h)
        g0, t0 = jnp.asarray(g0, m0.dtype), jnp.zeros((), m0.dtype)
        run = (system, integrator, g0, m0, h, t0, n_steps, save_every, valid, progress, axes)
        return _batched(simulate_blocks(*run), g0.shape[0], n_steps, save, axes[1])
    run = (system, integrator, g0, m0, h, n_steps, save_every, save, system_axis, segment)
    return _simulate_vmap_scan(*run, forcing, args, progress)


@eqx.filter_jit
def _simulate_vmap_scan(
    system,
    integrator,
    g0,
    m0,
    h,
    n_steps,
    save_every,
    save,
    system_axis,
    segment,
    forcing=None,
    args=None,
    progress=NoProgressMeter(),
):
    def one(system, g0, m0, h, forcing):
        return simulate(
            system,
            integrator,
            g0,
            m0,
            h=h,
            n_steps=n_steps,
            save_every=save_every,
            throw=False,
            checkpoint=False if segment is None else segment,
            forcing=forcing,
            args=args,
            progress_meter=progress,
        )

    h_axis = None if h.ndim == 0 else 0
    forcing_axes = None if forcing is None else forcing.batch_axes(system)
    in_axes = (system.batch_axes(system_axis), 0, 0, h_axis, forcing_axes)
    solution = jax.vmap(one, in_axes=in_axes)(system, g0, m0, h, forcing)
    return _batched(solution, g0.shape[0], n_steps, save, h_axis)


def _batched(solution, batch, n_steps, save, h_axis):
    """A vmapped run's `Solution` as `simulate_batch` returns it (`ts` and `num_steps` one per
    body, the fields `save` omits dropped)."""
    if h_axis is None:
        solution = eqx.tree_at(
            lambda s: s.ts,
            solution,
            jnp.broadcast_to(solution.ts, (batch,) + solution.ts.shape[1:]),
        )
    stats = dict(solution.stats)
    stats["num_steps"] = jnp.broadcast_to(jnp.asarray(n_steps), (batch,))
    # `simulate` gives Γ_k = g_kᵀa from the saved elements (NaN after a failure, as `g`).
    return _keep(eqx.tree_at(lambda s: s.stats, solution, stats), save)
