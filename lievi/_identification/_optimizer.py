"""The optimiser of `fit_system`: one loss evaluation per body per tick.

A batched fit evaluates the loss and its gradient for every body at once (one
`simulate_batch` call: the structure-of-arrays fast path and its reverse mode). Running
`optax.lbfgs` under `jax.vmap` would instead put a line search — a `while_loop` — inside
every iteration, and a vmapped loop runs until its slowest member is done: every body would
pay for the longest line search in the batch, every iteration (with a thousand bodies that
is close to the line search's maximum length each time).

So the optimiser is written as a state machine that asks for exactly one evaluation per
tick: each body proposes a trial point, the batch is evaluated once, and each body digests
its own value and gradient — accepting the point and choosing the next direction, or
shortening its step. Bodies in a line search and bodies starting an iteration share every
evaluation, and none waits for another.

Two machines, over one body's parameters flattened into a vector `x`:

- `LBFGS`: limited-memory BFGS (Nocedal & Wright, *Numerical Optimization*, 2nd ed., 2006,
  Algorithm 7.4, two-loop recursion, `H₀ = γI` with `γ = sᵀy / yᵀy`) with a backtracking
  line search: the first trial step is 1 (on the first iteration `min(1, 1/‖g‖₂)`), and a
  trial is accepted on the Armijo condition `f(x + td) ≤ f(x) + c₁ t gᵀd`, or, where the
  change of `f` is lost in round-off near the minimum, on Hager and Zhang's approximate
  Wolfe conditions (`f(x + td) ≤ f(x) + ε|f(x)|` and `σ gᵀd ≤ g(x + td)ᵀd ≤ (2c₁ − 1) gᵀd`,
  SIAM J. Optim. 16 (2005) 170–192). A rejected trial shortens the step to the minimiser of
  the quadratic through `f(x)`, `gᵀd` and `f(x + td)`, kept within `[t/10, t/2]`. A pair
  `(s, y)` enters the memory only with `sᵀy > 0` (curvature; else the update is skipped).
  After `max_backtracks` rejections the memory is dropped and the step restarts along
  `−g`; if that fails too the body has `stalled`.
- `OptaxMachine`: any `optax.GradientTransformation` used as `update(g, state, x)`; each
  evaluation is one iteration.

Both expose `init(x)`, `trial(state)` (where to evaluate next), `tell(state, f, g)` (digest
the evaluation at the trial point; returns the state and whether `x` is now a newly
evaluated accepted point, with `f` and `g` its value and gradient), `advance(state)` (from
an accepted point, prepare the next trial) and `restart(state)` (the loss has changed:
re-evaluate at `x` and forget curvature information). Everything is per body: the caller
`jax.vmap`s it.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int


class LBFGSState(eqx.Module):
    x: Float[Array, " n"]  # the accepted point
    f: Float[Array, ""]  # its value ...
    g: Float[Array, " n"]  # ... and gradient
    S: Float[Array, "m n"]  # memory of steps s, newest first
    Y: Float[Array, "m n"]  # memory of gradient changes y, newest first
    count: Int[Array, ""]  # valid entries of the memory
    d: Float[Array, " n"]  # search direction
    t: Float[Array, ""]  # trial step along d
    slope: Float[Array, ""]  # gᵀd < 0
    backtracks: Int[Array, ""]
    fresh: Bool[Array, ""]  # the next evaluation is at x itself
    stalled: Bool[Array, ""]


class LBFGS(eqx.Module):
    memory: int = eqx.field(default=10, static=True)
    c1: float = eqx.field(default=1e-4, static=True)
    sigma: float = eqx.field(default=0.9, static=True)
    approx_rtol: float = eqx.field(default=1e-6, static=True)
    max_backtracks: int = eqx.field(default=30, static=True)

    def init(self, x) -> LBFGSState:
        n, dtype = x.shape[0], x.dtype
        zero = jnp.zeros((), dtype)
        return LBFGSState(
            x=x,
            f=jnp.full((), jnp.inf, dtype),
            g=jnp.zeros_like(x),
            S=jnp.zeros((self.memory, n), dtype),
            Y=jnp.zeros((self.memory, n), dtype),
            count=jnp.zeros((), jnp.int32),
            d=jnp.zeros_like(x),
            t=zero,
            slope=zero,
            backtracks=jnp.zeros((), jnp.int32),
            fresh=jnp.asarray(True),
            stalled=jnp.asarray(False),
        )

    def trial(self, s: LBFGSState):
        return jnp.where(s.fresh, s.x, s.x + s.t * s.d)

    def restart(self, s: LBFGSState) -> LBFGSState:
        return eqx.tree_at(
            lambda s: (s.count, s.fresh), s, (jnp.zeros_like(s.count), jnp.asarray(True))
        )

    def _direction(self, g, S, Y, count):
        """`−H g` by the two-loop recursion over the valid memory (newest first)."""
        dtype = g.dtype
        tiny = jnp.finfo(dtype).tiny
        valid = jnp.arange(self.memory) < count
        sy = jnp.sum(S * Y, axis=1)
        rho = jnp.where(valid, 1 / jnp.where(valid, sy, 1), 0)
        q = g
        alphas = []
        for i in range(self.memory):  # newest to oldest
            a = rho[i] * jnp.dot(S[i], q)
            q = q - a * Y[i]
            alphas.append(a)
        yy = jnp.dot(Y[0], Y[0])
        gamma = jnp.where(count > 0, sy[0] / jnp.maximum(yy, tiny), _first_scale(g))
        r = gamma * q
        for i in reversed(range(self.memory)):  # oldest to newest
            b = rho[i] * jnp.dot(Y[i], r)
            r = r + S[i] * (alphas[i] - b)
        return -r

    def advance(self, s: LBFGSState) -> LBFGSState:
        d = self._direction(s.g, s.S, s.Y, s.count)
        slope = jnp.dot(s.g, d)
        # Round-off can make an old memory's direction ascend: forget it, go down −g.
        descent = (slope < 0) & jnp.all(jnp.isfinite(d))
        count = jnp.where(descent, s.count, 0)
        d = jnp.where(descent, d, -_first_scale(s.g) * s.g)
        return eqx.tree_at(
            lambda s: (s.d, s.t, s.slope, s.count, s.backtracks, s.fresh),
            s,
            (
                d,
                jnp.ones_like(s.t),
                jnp.dot(s.g, d),
                count,
                jnp.zeros_like(s.backtracks),
                jnp.asarray(False),
            ),
        )

    def tell(self, s: LBFGSState, f, g):
        finite = jnp.isfinite(f) & jnp.all(jnp.isfinite(g))
        z = self.trial(s)
        slope_z = jnp.dot(g, s.d)
        armijo = f <= s.f + self.c1 * s.t * s.slope
        approx = (
            (f <= s.f + self.approx_rtol * jnp.abs(s.f))
            & (slope_z >= self.sigma * s.slope)
            & (slope_z <= (2 * self.c1 - 1) * s.slope)
        )
        accepted = jnp.where(s.fresh, True, finite & (armijo | approx))

        # Accepted: the memory gains (s, y) if it has positive curvature.
        step, change = z - s.x, g - s.g
        sy = jnp.dot(step, change)
        curvature = ~s.fresh & (sy > jnp.finfo(f.dtype).eps * _norm(step) * _norm(change))
        S = jnp.where(curvature, jnp.roll(s.S, 1, axis=0).at[0].set(step), s.S)
        Y = jnp.where(curvature, jnp.roll(s.Y, 1, axis=0).at[0].set(change), s.Y)
        count = jnp.where(curvature, jnp.minimum(s.count + 1, self.memory), s.count)
        # A fresh point whose value or gradient is not finite cannot be left.
        stalled_here = s.fresh & ~finite
        taken = eqx.tree_at(
            lambda s: (s.x, s.f, s.g, s.S, s.Y, s.count, s.stalled),
            s,
            (z, f, g, S, Y, count, s.stalled | stalled_here),
        )

        # Rejected: the minimiser of the interpolating quadratic, within [t/10, t/2].
        excess = f - s.f - s.slope * s.t
        quadratic = -s.slope * s.t**2 / (2 * jnp.where(excess > 0, excess, 1))
        t_new = jnp.where(
            jnp.isfinite(f) & (excess > 0),
            jnp.clip(quadratic, s.t / 10, s.t / 2),
            s.t / 4,
        )
        backtracks = s.backtracks + 1
        give_up = backtracks >= self.max_backtracks
        rejected = eqx.tree_at(lambda s: (s.t, s.backtracks), s, (t_new, backtracks))
        # Out of backtracks: with a memory, start again along −g; without one, stalled.
        retry = self.advance(eqx.tree_at(lambda s: s.count, rejected, jnp.zeros_like(s.count)))
        rejected = jax.tree.map(
            lambda a, b: jnp.where(give_up & (s.count > 0), a, b), retry, rejected
        )
        rejected = eqx.tree_at(
            lambda s: s.stalled, rejected, s.stalled | (give_up & (s.count == 0))
        )
        new = jax.tree.map(lambda a, b: jnp.where(accepted, a, b), taken, rejected)
        return new, accepted


class OptaxState(eqx.Module):
    x: Float[Array, " n"]
    f: Float[Array, ""]
    g: Float[Array, " n"]
    opt_state: object
    fresh: Bool[Array, ""]
    stalled: Bool[Array, ""]


class OptaxMachine(eqx.Module):
    optimizer: object = eqx.field(static=True)

    def init(self, x) -> OptaxState:
        return OptaxState(
            x=x,
            f=jnp.full((), jnp.inf, x.dtype),
            g=jnp.zeros_like(x),
            opt_state=self.optimizer.init(x),
            fresh=jnp.asarray(True),
            stalled=jnp.asarray(False),
        )

    def trial(self, s: OptaxState):
        return s.x

    def restart(self, s: OptaxState) -> OptaxState:
        return eqx.tree_at(
            lambda s: (s.opt_state, s.fresh), s, (self.optimizer.init(s.x), jnp.asarray(True))
        )

    def advance(self, s: OptaxState) -> OptaxState:
        updates, opt_state = self.optimizer.update(s.g, s.opt_state, s.x)
        return eqx.tree_at(
            lambda s: (s.x, s.opt_state, s.fresh),
            s,
            (s.x + updates, opt_state, jnp.asarray(False)),
        )

    def tell(self, s: OptaxState, f, g):
        finite = jnp.isfinite(f) & jnp.all(jnp.isfinite(g))
        new = eqx.tree_at(lambda s: (s.f, s.g, s.stalled), s, (f, g, s.stalled | ~finite))
        return new, jnp.asarray(True)


def _norm(x):
    return jnp.sqrt(jnp.sum(x * x))


def _first_scale(g):
    """`H₀ = γI` before any curvature is known: a first step of length at most 1 along −g."""
    return jnp.minimum(1.0, 1 / jnp.maximum(_norm(g), jnp.finfo(g.dtype).tiny))
