"""High-accuracy reference solutions of the continuous Euler–Poincaré equations.

Left-invariant: `ṁ = ad_ξᵀ m + M(g)`, `ġ = g ξ̂`; right-invariant: `ṁ = −ad_ξᵀ m + M(g)`,
`ġ = ξ̂ g`; with `ξ` the velocity of `m` (inverse Legendre map) and `M` the generalised
force of the system's potential (zero for a free system). For the rigid body the first is
Euler's equation `Π̇ = Π × Ω + M` (for a heavy top `M = m γ Γ × ρ`). Solved by scipy's DOP853 (scipy is a dependency of JAX),
the yardstick of NOTES §3.2.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from scipy.integrate import solve_ivp

from ._integrators._rk4 import euler_poincare_vector_field
from ._systems._base import AbstractLieSystem


def reference_solution(
    system: AbstractLieSystem, g0, m0, ts, *, rtol: float = 1e-13, atol: float = 1e-13
):
    """Solve the Euler–Poincaré equations of `system` to `rtol`/`atol` with DOP853.

    **Arguments:** `g0 (n, n)`, `m0 (d,)`, `ts`: increasing times starting at the
    initial time. Needs 64-bit JAX (`jax.config.update("jax_enable_x64", True)`).

    **Returns:** `(g, m)` as NumPy arrays of shapes `(len(ts), n, n)` and `(len(ts), d)`.
    """
    if not jax.config.jax_enable_x64:
        raise ValueError(
            "reference_solution needs float64: call jax.config.update('jax_enable_x64', True) "
            "before creating arrays."
        )
    group = system.group
    n, d = group.matrix_dim, group.algebra_dim

    @jax.jit
    def rhs(y):
        m, g = y[:d], y[d:].reshape(n, n)
        g_dot, m_dot = euler_poincare_vector_field(system, g, m)
        return jnp.concatenate([m_dot, g_dot.reshape(-1)])

    ts = np.asarray(ts, dtype=float)
    y0 = np.concatenate([np.asarray(m0, float), np.asarray(g0, float).reshape(-1)])
    sol = solve_ivp(
        lambda t, y: np.asarray(rhs(jnp.asarray(y))),
        (ts[0], ts[-1]),
        y0,
        method="DOP853",
        t_eval=ts,
        rtol=rtol,
        atol=atol,
    )
    if not sol.success:
        raise RuntimeError(f"reference_solution: DOP853 failed: {sol.message}")
    y = sol.y.T
    return y[:, d:].reshape(-1, n, n), y[:, :d]
