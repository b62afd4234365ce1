"""High-accuracy reference solutions of the continuous Euler–Poincaré equations.

Left-invariant: `ṁ = ad_ξᵀ m + M(g)`, `ġ = g ξ̂`; right-invariant: `ṁ = −ad_ξᵀ m + M(g)`,
`ġ = ξ̂ g`; with `ξ` the velocity of `m` (inverse Legendre map) and `M` the generalised
force of the system's potential (zero for a free system), plus an external force if given
(`lievi.Control`, `lievi.ForceLaw`). For the rigid body the first is
Euler's equation `Π̇ = Π × Ω + M` (for a heavy top `M = m γ Γ × ρ`). Solved by scipy's DOP853 (scipy is a dependency of JAX),
the yardstick of docs/theory/checks.md#reference.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

from ._forcing import as_forcing
from ._integrators._rk4 import euler_poincare_vector_field
from ._systems._base import AbstractLieSystem


def reference_solution(
    system: AbstractLieSystem,
    g0,
    m0,
    ts,
    *,
    rtol: float = 1e-13,
    atol: float = 1e-13,
    forcing=None,
    args=None,
):
    """Solve the Euler–Poincaré equations of `system` to `rtol`/`atol` with DOP853.

    **Arguments:** `g0 (n, n)`, `m0 (d,)` — one state, of the system's `element_shape()`
    and `momentum_shape()` (a row per body for a system of several, e.g. `(N, 4, 4)` and
    `(N, 6)` for `lievi.RigidBodies`; for a batch of states, call it on each) — and `ts`:
    increasing times starting at the initial time. Needs 64-bit JAX (`jax.config.update("jax_enable_x64", True)`).
    `forcing`, `args`: an external force as for `lievi.simulate`, added to `ṁ`. With a
    `lievi.Control(u)` the times `ts` are the step times: `u[k]` is held on
    `[ts[k], ts[k+1]]` (so `len(ts) = len(u) + 1`) and each interval is solved separately,
    so the jumps of the control do not spoil the accuracy.

    **Returns:** `(g, m)` as NumPy arrays of shapes `(len(ts), *element_shape)` and
    `(len(ts), *momentum_shape)`.
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "reference_solution needs float64: call jax.config.update('jax_enable_x64', True) "
            "before creating arrays."
        )
    system.check_unconstrained("lievi.reference_solution")
    system.check_element("g0", g0)
    system.check_momentum("m0", m0)
    # One state's shapes (per body for a system of several bodies), flattened for DOP853.
    element, momentum = system.element_shape(), system.momentum_shape()
    d = int(np.prod(momentum))
    forcing = as_forcing(forcing)
    ts = np.asarray(ts, dtype=float)
    per_step = None if forcing is None else forcing.per_step()
    piecewise = bool(jax.tree.leaves(per_step))
    if forcing is not None:
        forcing.check(system, len(ts) - 1, jnp.float64, args)  # the step grid, for a control

    @jax.jit
    def rhs(t, y, data):
        m, g = y[:d].reshape(momentum), y[d:].reshape(element)
        force = None if forcing is None else forcing.at_step(data, args)
        g_dot, m_dot = euler_poincare_vector_field(system, g, m, force, t)
        return jnp.concatenate([m_dot.reshape(-1), g_dot.reshape(-1)])

    def solve(t_eval, y0, data):
        sol = solve_ivp(
            lambda t, y: np.asarray(rhs(t, jnp.asarray(y), data)),
            (t_eval[0], t_eval[-1]),
            y0,
            method="DOP853",
            t_eval=t_eval,
            rtol=rtol,
            atol=atol,
        )
        if not sol.success:
            raise RuntimeError(f"reference_solution: DOP853 failed: {sol.message}")
        return sol.y.T

    y0 = np.concatenate([np.asarray(m0, float).reshape(-1), np.asarray(g0, float).reshape(-1)])
    if piecewise:
        ys = [y0]
        for k in range(len(ts) - 1):
            data = jax.tree.map(lambda x, k=k: jnp.asarray(x[k], jnp.float64), per_step)
            ys.append(solve(ts[k : k + 2], ys[-1], data)[-1])
        y = np.stack(ys)
    else:
        y = solve(ts, y0, per_step)
    return y[:, d:].reshape(-1, *element), y[:, :d].reshape(-1, *momentum)
