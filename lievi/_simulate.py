"""`simulate`: one body, as a batch of one in the one step loop (`lievi._loop`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import (
    check_real_dtype,
    check_scalar,
    check_shape,
    is_concrete,
    state_dtype,
)
from ._integrators._base import AbstractIntegrator, AbstractVariationalIntegrator
from ._loop import Run, execute, raise_if_failed
from ._monitor import AbstractInvariantMonitor
from ._options import OPTIONS, Tuning, options
from ._progress import AbstractProgressMeter
from ._save import Save
from ._solution import Solution
from ._steppers import plan_for
from ._systems._base import AbstractLieSystem


def simulate(
    system: AbstractLieSystem,
    integrator: AbstractIntegrator,
    g0: Float[Array, "n n"],
    m0: Float[Array, " d"] | None = None,
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
    monitor: AbstractInvariantMonitor | None = OPTIONS["monitor"],
    tuning: Tuning = OPTIONS["tuning"],
    g1: Float[Array, "n n"] | None = None,
    **deprecated,
) -> Solution:
    """Integrate `system` with `integrator` from `(g0, m0)` for `n_steps` steps of size `h`.

    **Arguments:**

    - `system`: e.g. `lievi.RigidBody(inertia)`.
    - `integrator`: e.g. `lievi.DEP(chart="exp")`.
    - `g0`: initial group element, `(n, n)`; for SO(n) orthogonal to 1e-6.
    - `m0`: initial momentum in algebra coordinates, `(d,)` (body momentum for
      left-invariant systems). Give either `m0` or `g1`.
    - `h`: step size `> 0` (may be traced, e.g. differentiated or vmapped).
    - `n_steps`: number of steps, a Python `int ≥ 1`.
    - `g1`: instead of `m0`, the second configuration of the discrete trajectory (paper
      §2: a variational integrator is started from `(g0, g1)`); `m0` is then the discrete
      Legendre transform `−D₁L_d(g0, g1)`.

    **Options** — every run function (`simulate_batch`, `stream_batch`,
    `simulate_with_neighbor_list`) takes these, with these defaults:

    - `save`: what is stored and how often, a `lievi.Save` (default `Save()`: `g`, `m`
      and the Newton statistics at every step; `Save(every=k)` every `k`-th step, `k`
      dividing `n_steps`).
    - `t0`: initial time; save `j` is at `t0 + j·every·h`.
    - `throw`: if a step fails (see `RESULTS`), raise an error saying what to do; with
      `throw=False` the failure is returned in `Solution.result` instead. Inside your own
      `jax.jit` the error is raised by Equinox's runtime check and reaches you wrapped in
      `JaxRuntimeError` (lievi's message is in its text); wrap with `eqx.filter_jit` for
      a readable error, or pass `throw=False` and read `result`.
    - `checkpoint`: memory of reverse-mode differentiation (`jax.grad`). `False` (default)
      stores each step's state and the roots of its implicit solves, O(`n_steps`)
      memory, and recomputes the rest of the step in the backward pass. `True` splits the
      run into segments of about √`n_steps` steps, each wrapped in `jax.checkpoint`: the
      backward pass stores only the state at segment boundaries and recomputes one
      segment at a time, O(√`n_steps`) memory for one extra forward pass. An `int` sets
      the segment length in steps; it must divide `save.every` or be a multiple of it
      that divides `n_steps`. No effect on values or on forward-mode derivatives.
    - `progress_meter`: report progress of a long run while it computes (diffrax's
      `progress_meter` convention): `lievi.NoProgressMeter()` (the default, also `False`),
      `lievi.TextProgressMeter()` (also `"text"`: the percentage done on one line updated
      in place, printed once the run has taken a second), `lievi.TqdmProgressMeter()`
      (also `"tqdm"`: a tqdm bar, needs `pip install tqdm`); `True` picks tqdm where it is
      installed and text otherwise. Updated about every 1% of the steps from inside the
      compiled loop (`jax.debug.callback`), so it also works under an outer `jit`; no
      effect on values.
    - `forcing`: an external generalised force (for the rigid body, the body torque):
      `lievi.Control(u)` with `u` of shape `(n_steps, d)` held over each step,
      `lievi.ForceLaw(fn)` with `fn(t, g, m, args)` (feedback, damping), or a tuple of
      them (added). Enters the step through the discrete Lagrange–d'Alembert principle
      (see `lievi.AbstractKickIntegrator`). Step `k` runs from `t_k = t0 + k·h`.
    - `args`: passed unchanged to a force law (as diffrax's `args`).
    - `monitor`: an invariant checked at every save, `lievi.EnergyMonitor(rtol)` or
      `lievi.MomentumMonitor(rtol)`: a run whose invariant drifts past the tolerance ends
      with `RESULTS.invariant_drift` (off by default; docs/concepts/failure.md).
    - `tuning`: how the run is computed, never what it computes
      (`lievi.advanced.Tuning`: the kernel, its fixed Newton iterations, loop unrolling).

    The keywords of earlier releases — `save_every=k` (now `save=Save(every=k)`),
    `save=("g", "m")` (now `Save(g=True, m=True, stats=False)`), `fast`,
    `fixed_iterations`, `unroll` (now `tuning=lievi.advanced.Tuning(...)`) — still work
    for one release, with a `DeprecationWarning`.

    **Returns:** a `Solution`.

    The run computes in the promoted dtype of `g0`, `m0`, `h` and the system's parameters
    (NumPy rules: float32 throughout needs a float32 system too).

    Shapes, dtypes, `h`, `t0`, `n_steps`, the options and concrete values of `g0`,
    `m0` and the system's parameters are checked eagerly and raise `ValueError`. The same
    value checks run inside the computation, so under `jit`/`vmap` a bad value (an
    inertia that is not positive definite, `g0` not a rotation, NaN, `h ≤ 0`) gives
    `RESULTS.invalid_input` for that body, never `successful`. Every step is also checked
    for a non-finite `g` or `m` (`RESULTS.nonfinite`) and against the integrator's step
    bound (`RESULTS.step_too_large`, see `AbstractIntegrator.step_bound`). Under
    `jax.vmap` (many bodies) use `throw=False` to let a batch carry on and read the
    per-body `result`.
    """
    opts = options("lievi.simulate", n_steps, locals(), deprecated)
    n_steps, forcing = opts.n_steps, opts.forcing
    check_scalar("h", h, positive=True)
    if (m0 is None) == (g1 is None):
        raise ValueError(
            "Give exactly one of `m0` (initial momentum) and `g1` (second configuration)."
        )
    g0 = _as_array("g0", g0)
    _check_configuration(system, "g0", g0)
    if g1 is not None and forcing is not None:
        raise ValueError(
            "`g1` with `forcing`: the forced discrete Legendre transform needs the force at "
            "the first step; pass the initial momentum `m0` instead."
        )
    if g1 is not None:
        m0 = _momentum_from_g1(system, integrator, g0, g1, h)
    m0 = _as_array("m0", m0)
    system.check_momentum("m0", m0)
    dtype = state_dtype(system, g0, m0, h)
    if forcing is not None:
        forcing.check(system, n_steps, dtype, args)
    plan = plan_for(system, integrator, None, forcing, args, one_body=True, tuning=opts.tuning)
    run = Run.of(plan, opts, dtype)

    def explain():
        # An eager run with a bad input: the eager checks name it (`ValueError`).
        system.check_element("g0", g0)

    solution = execute(
        run, _lead(g0), _lead(m0), h, t0, n_steps, opts.save.every, explain=explain, one=True
    )
    if throw:
        solution = raise_if_failed(solution, "lievi.simulate", "a step")
    return solution


def _lead(x):
    """`x` with a leading batch axis of one: on the host for a concrete array (no program
    compiled for it), traced otherwise."""
    return np.asarray(x)[None] if is_concrete(x) else jnp.asarray(x)[None]


def _check_configuration(system, name, g) -> None:
    """Shape and finiteness now (no program compiled); membership in the group is checked
    inside the run (a body off the group starts as `RESULTS.invalid_input`, and an eager
    run then raises `check_element`'s `ValueError`)."""
    shape = system.element_shape()
    n = system.group.matrix_dim
    what = f"a {n}×{n} group element" + (
        f" for each of {shape[0]} bodies" if len(shape) > 2 else ""
    )
    check_shape(name, g, shape, what)
    if is_concrete(g) and not np.all(np.isfinite(np.asarray(g))):
        raise ValueError(f"`{name}` contains NaN or inf; pass finite values.")


def _momentum_from_g1(system, integrator, g0, g1, h):
    """`m0` of the discrete trajectory through `(g0, g1)`: the discrete Legendre transform
    `−D₁L_d(g0, g1)` (paper §2: a variational integrator is started from `(g0, g1)`)."""
    if not isinstance(integrator, AbstractVariationalIntegrator):
        raise ValueError("`g1` needs a variational integrator (one with a discrete Lagrangian).")
    system.check_element("g0", g0)
    g1 = _as_array("g1", g1)
    system.check_element("g1", g1)
    dtype = state_dtype(system, g0, g1, h)
    g0, g1 = jnp.asarray(g0, dtype), jnp.asarray(g1, dtype)
    m0 = integrator.momentum_from_configurations(system, g0, g1, jnp.asarray(h, dtype))
    if is_concrete(m0) and not np.all(np.isfinite(np.asarray(m0))):
        raise ValueError(
            "the momentum of the discrete trajectory through (`g0`, `g1`) is not finite: "
            "the increment g0⁻¹g1 is outside the domain of the integrator's chart (e.g. a "
            "half-turn for chart='cayley' or the Moser–Veselov Lagrangian). Pass `g1` "
            "closer to `g0` (a smaller step) or pass `m0` instead."
        )
    return m0


def _as_array(name: str, x):
    """Lists and tuples are accepted like arrays; complex, bool and strings are not. A
    JAX array (or tracer) is kept; anything else is read on the host (no program
    compiled)."""
    check_real_dtype(name, x)
    return x if isinstance(x, jax.Array) else np.asarray(x)
