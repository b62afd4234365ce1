"""`simulate`: one body, as a batch of one in the one step loop (`lievi._loop`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._checks import (
    check_finite,
    check_real_dtype,
    check_scalar,
    check_shape,
    is_concrete,
    state_dtype,
)
from ._integrators._base import AbstractIntegrator, AbstractVariationalIntegrator
from ._loop import Run, execute
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

    **Options** — every run function takes them, with the same defaults (each described
    under *Run options*, docs/api/simulate.md): `save=lievi.Save()`, `t0=0.0` (save `j`
    at `t0 + j·every·h`), `throw=True`, `checkpoint=False`, `progress_meter=False`,
    `forcing=None`, `args=None`, `monitor=None`, `tuning=lievi.advanced.Tuning()`. The
    keywords of earlier releases still work for one release, with a `DeprecationWarning`.

    **Returns:** a `Solution`.

    The run computes in the promoted dtype of `g0`, `m0`, `h` and the system's parameters
    (NumPy rules: float32 throughout needs a float32 system too).

    Shapes, dtypes, `h`, `t0`, `n_steps`, the options and concrete values are checked
    eagerly (`ValueError`); the same value checks run inside the computation, so under
    `jit`/`vmap` a bad value gives `RESULTS.invalid_input`, never `successful`. Every step
    is checked for a non-finite state (`RESULTS.nonfinite`) and against the integrator's
    step bound (`RESULTS.step_too_large`).
    """
    opts = options("lievi.simulate", n_steps, locals(), deprecated)
    n_steps, forcing = opts.n_steps, opts.forcing
    check_scalar("h", h, positive=True)
    if (m0 is None) == (g1 is None):
        raise ValueError(
            "Give exactly one of `m0` (initial momentum) and `g1` (second configuration)."
        )
    g0 = as_array("g0", g0)
    # Shape and finiteness now (no program compiled); membership in the group inside the
    # run (a body off the group starts as `RESULTS.invalid_input`, then `explain` says so).
    shape, n = system.element_shape(), system.group.matrix_dim
    what = f"a {n}×{n} group element" + (
        f" for each of {shape[0]} bodies" if len(shape) > 2 else ""
    )
    check_shape("g0", g0, shape, what)
    check_finite("g0", g0)
    if g1 is not None and forcing is not None:
        raise ValueError(
            "`g1` with `forcing`: the forced discrete Legendre transform needs the force at "
            "the first step; pass the initial momentum `m0` instead."
        )
    if g1 is not None:
        m0 = _momentum_from_g1(system, integrator, g0, g1, h)
    m0 = as_array("m0", m0)
    system.check_momentum("m0", m0)
    dtype = state_dtype(system, g0, m0, h)
    if forcing is not None:
        forcing.check(system, n_steps, dtype, args)
    plan = plan_for(system, integrator, None, forcing, args, one_body=True, tuning=opts.tuning)
    run = Run.of(plan, opts, dtype)

    # With a bad input, an eager run raises the eager check's `ValueError` naming it.
    def explain(_):
        system.check_element("g0", g0)

    # A batch of one.
    g, m = (np.asarray(x)[None] if is_concrete(x) else jnp.asarray(x)[None] for x in (g0, m0))
    check = ("lievi.simulate", "a step") if throw else None
    return execute(
        run, g, m, h, t0, n_steps, opts.save.every, explain=explain, one=True, throw=check
    )


def _momentum_from_g1(system, integrator, g0, g1, h):
    """`m0` of the discrete trajectory through `(g0, g1)`: `−D₁L_d(g0, g1)` (paper §2)."""
    if not isinstance(integrator, AbstractVariationalIntegrator):
        raise ValueError("`g1` needs a variational integrator (one with a discrete Lagrangian).")
    system.check_element("g0", g0)
    g1 = as_array("g1", g1)
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


def as_array(name: str, x):
    """`x` real (lists and tuples too): a JAX array kept, else read on the host."""
    check_real_dtype(name, x)
    return x if isinstance(x, jax.Array) else np.asarray(x)
