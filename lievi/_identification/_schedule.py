"""The batch driver: one loss evaluation per tick for every body, horizon stages, rounds
after which finished bodies leave the batch, and the final report.

Every loss evaluation is one `simulate_batch` call for all bodies, and the optimiser is a
per-body state machine that needs exactly one evaluation per tick (`_optimizer.py`): a
body in its line search and a body starting a new iteration share each evaluation, and
none waits for the longest line search of the batch. Large batches run in rounds of
`check_every` ticks: after each round the bodies that have finished leave the batch and the
others continue in a smaller one.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree
from jaxtyping import Array

from ._identifiability import identifiability
from ._problem import initial_momentum, initial_params, misfit
from ._result import FIT_REASONS, SystemFit


class Carry(eqx.Module):
    params: dict  # the accepted point
    opt: object  # the optimiser's state (`_optimizer.py`)
    failed: Array  # failed samples at the accepted point
    stage: Array
    it: Array
    history: Array
    failed_history: Array
    done: Array  # the current stage's stopping test holds at the accepted point
    finished: Array


@eqx.filter_jit
def initial_momenta(problem, theta0, dynamic, data, h):
    """Every body's initial guess of Π₀ (unknown Π₀)."""
    return jax.vmap(lambda t, dyn, dat: initial_momentum(problem, t, dyn, dat, h))(
        theta0, dynamic, data
    )


@eqx.filter_jit
def start(problem, theta0, m0_guess, dynamic, data, h):
    params = jax.vmap(initial_params)(theta0, m0_guess, data)
    n_bodies = jax.tree.leaves(params)[0].shape[0]
    dtype = h.dtype
    # The first stage: the longest horizon the initial guess already predicts.
    predicted = jnp.cumprod(problem.predicted(params, dynamic, data, h), axis=1)
    n_predicted = jnp.sum(predicted, axis=1)
    horizons = jnp.asarray(problem.horizons)
    stage = jnp.maximum(jnp.sum(horizons[None, :] <= n_predicted[:, None], axis=1) - 1, 0)
    return Carry(
        params=params,
        opt=jax.vmap(problem.machine().init)(jax.vmap(_flat)(params)),
        failed=jnp.zeros(n_bodies, jnp.int32),
        stage=stage.astype(jnp.int32),
        it=jnp.zeros(n_bodies, jnp.int32),
        history=jnp.full((n_bodies, problem.max_iters + 1), jnp.nan, dtype),
        failed_history=jnp.full((n_bodies, problem.max_iters + 1), -1, jnp.int32),
        done=jnp.zeros(n_bodies, bool),
        finished=jnp.zeros(n_bodies, bool),
    )


def _flat(params):
    return ravel_pytree(params)[0]


def _digest(problem, machine, unravel, c: Carry, value, loss, grad, failed) -> Carry:
    """One body takes in the (normalised) loss `value` and its gradient at its trial point;
    `loss` (not normalised) goes into the history."""
    last = len(problem.horizons) - 1
    opt, accepted = machine.tell(c.opt, value, grad)
    it = c.it + (accepted & ~c.opt.fresh).astype(c.it.dtype)
    # The loss at the accepted point (a new stage re-evaluates it over its longer horizon).
    history = jnp.where(accepted, c.history.at[it].set(loss), c.history)
    failed_history = jnp.where(accepted, c.failed_history.at[it].set(failed), c.failed_history)
    failed = jnp.where(accepted, failed, c.failed)
    gnorm = jnp.max(jnp.abs(grad))
    done = jnp.where(accepted, problem.stage_done(value, failed, gnorm, c.stage), c.done)
    # A finished stage hands its solution to the next, longer horizon (the loss has
    # changed: the point is evaluated again and the curvature memory dropped).
    next_stage = done & (c.stage < last)
    finished = (done & (c.stage == last)) | (it >= problem.max_iters) | opt.stalled
    point = unravel(opt.x)  # (an optax machine's `advance` moves `x` on)
    advanced = machine.advance(opt)
    restarted = machine.restart(opt)
    opt = jax.tree.map(
        lambda r, a, o: jnp.where(next_stage, r, jnp.where(accepted & ~finished, a, o)),
        restarted,
        advanced,
        opt,
    )
    new = Carry(
        params=jax.tree.map(lambda old, x: jnp.where(accepted, x, old), c.params, point),
        opt=opt,
        failed=failed,
        stage=jnp.where(next_stage, c.stage + 1, c.stage),
        it=it,
        history=history,
        failed_history=failed_history,
        done=done & ~next_stage,
        finished=finished,
    )
    return jax.tree.map(lambda n, o: jnp.where(c.finished, o, n), new, c)


@eqx.filter_jit
def run(problem, n_evals, carry, dynamic, data, h):
    """Up to `n_evals` ticks (until every body is finished if `None`): each evaluates the
    loss and gradient of every body at its trial point in one batched call, then lets each
    body digest its own."""
    machine = problem.machine()
    _, unravel = ravel_pytree(jax.tree.map(lambda x: x[0], carry.params))
    horizons = jnp.asarray(problem.horizons)
    gradient = jax.value_and_grad(problem.batch_loss, has_aux=True)

    def cond(state):
        k, c = state
        more = ~jnp.all(c.finished)
        return more if n_evals is None else more & (k < n_evals)

    def body(state):
        k, c = state
        trial = jax.vmap(unravel)(jax.vmap(machine.trial)(c.opt))
        (_, aux), grad = gradient(trial, dynamic, data, h, horizons[c.stage])
        value, loss, failed = aux[:3]
        digest = lambda *a: _digest(problem, machine, unravel, *a)
        return k + 1, jax.vmap(digest)(c, value, loss, jax.vmap(_flat)(grad), failed)

    return jax.lax.while_loop(cond, body, (jnp.zeros((), jnp.int32), carry))[1]


def _finish_one(problem, carry, dynamic, data, h, loss, failed, result, residuals):
    last = jnp.asarray(len(problem.horizons) - 1, jnp.int32)
    values, m0, g0 = problem.unpack(carry.params, dynamic, data)
    flags, s, condition, full_rank = identifiability(problem, carry.params, dynamic, data, h)
    optimised = carry.done & (carry.stage == last)
    systematic = misfit(residuals, loss, data)
    on_boundary = jnp.any(jnp.stack([f.on_boundary(v) for f, v in zip(problem.fitted, values)]))
    reason = jnp.select(
        [
            ~jnp.isfinite(loss),
            failed > 0,
            ~full_rank,
            optimised & systematic & on_boundary,
            optimised & systematic,
            optimised,
            carry.opt.stalled & systematic & on_boundary,
            carry.opt.stalled,
        ],
        [
            FIT_REASONS.nonfinite,
            FIT_REASONS.failed_samples,
            FIT_REASONS.unidentifiable,
            FIT_REASONS.boundary,
            FIT_REASONS.misfit,
            FIT_REASONS.converged,
            FIT_REASONS.boundary,
            FIT_REASONS.stalled,
        ],
        FIT_REASONS.max_iters,
    ).astype(jnp.int32)
    # `system`, `params`, `identifiable` are assembled outside the compiled function (the
    # user's `where` is not part of the compilation key): here the fitted leaves' values
    # and flags.
    return SystemFit(
        system=dynamic,
        params=values,
        m0=m0,
        g0=g0,
        loss=loss,
        loss_history=carry.history,
        failed_history=carry.failed_history,
        failed_samples=failed,
        iterations=carry.it,
        converged=reason == FIT_REASONS.converged,
        reason=reason,
        identifiable=flags["values"],
        identifiable_m0=flags.get("m0"),
        identifiable_g0=flags.get("g0_chart"),
        singular_values=s,
        condition=condition,
        result=result,
    )


@eqx.filter_jit
def finish(problem, carry, dynamic, data, h):
    last = jnp.full(carry.it.shape, problem.horizons[-1])
    _, (_, loss, failed, result, residuals) = problem.batch_loss(
        carry.params, dynamic, data, h, last
    )
    return jax.vmap(lambda c, dyn, dat, *rest: _finish_one(problem, c, dyn, dat, h, *rest))(
        carry, dynamic, data, loss, failed, result, residuals
    )


def _bucket(n_active: int, n_total: int) -> int:
    """Compiled batch sizes: the full batch, then powers of 4 (few compilations)."""
    size = 1
    while size < n_active:
        size *= 4
    return min(size, n_total)


def iterate(problem, check_every, carry, dynamic, data, h):
    """Run the optimiser in rounds of `check_every` ticks (`None`: one round to the end);
    after each, the finished bodies leave the batch."""
    if check_every is None:
        return run(problem, None, carry, dynamic, data, h)
    n_total = int(carry.it.shape[0])
    take = lambda tree, idx: jax.tree.map(lambda x: x[idx], tree)
    while True:
        active = np.flatnonzero(~np.asarray(carry.finished))
        if active.size == 0:
            return carry
        size = _bucket(active.size, n_total)
        if size == n_total:
            carry = run(problem, check_every, carry, dynamic, data, h)
            continue
        idx = np.concatenate([active, np.full(size - active.size, active[0])])
        sub = run(problem, check_every, take(carry, idx), take(dynamic, idx), take(data, idx), h)
        sub = take(sub, np.arange(active.size))
        carry = jax.tree.map(lambda full, part, rows=active: full.at[rows].set(part), carry, sub)
