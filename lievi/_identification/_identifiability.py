"""Which fitted parameters the data determine.

At the solution the Jacobian `J` of the residuals with respect to the fitted physical
parameters (restricted to the gauge) is computed by forward-mode autodiff. Its columns are
scaled to unit norm (so units do not matter); a singular value of the scaled `J` below
`identifiability_rtol` times the largest is a direction in which the data do not determine
the parameters (a flat valley of the loss: a body spinning about a principal axis does not
reveal its other two moments; a body at rest reveals none). A parameter is reported
unidentifiable when such a direction moves it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax.flatten_util import ravel_pytree

from .._groups._so3 import SO3


def identifiability(problem, params, dynamic, data, h):
    """One body: `(flags, singular values, condition, full_rank)`; `flags` has the
    structure `{"values": [per leaf], "m0"?, "g0_chart"?}` of boolean arrays."""
    dtype = h.dtype
    values, m0, g0 = problem.unpack(params, dynamic, data)
    physical = {"values": values}
    if data["m0"] is None:
        physical["m0"] = m0
    if data["g0"] is None:
        physical["g0_chart"] = params["g0_chart"].astype(dtype)
    flat, unravel = ravel_pytree(physical)
    horizon = problem.horizons[-1]

    def residual(p):
        phys = unravel(p)
        vals = [f.symmetrise(v) for f, v in zip(problem.fitted, phys["values"])]
        m = phys.get("m0", m0)
        g = g0 if "g0_chart" not in phys else data["orientations"][0] @ SO3.exp(phys["g0_chart"])
        system = problem.system_of(vals, dynamic)
        return problem.residuals(system, m, g, data, h, horizon)[0].ravel()

    def marks(per_leaf):
        """A vector over the physical coordinates from one array per fitted leaf."""
        tree = {"values": [per_leaf(f) for f in problem.fitted]}
        for key in ("m0", "g0_chart"):
            if key in physical:
                tree[key] = np.zeros(jnp.shape(physical[key]))
        return np.concatenate(
            [np.ravel(np.asarray(x, float)) for x in jax.tree.leaves(tree)]
        )  # ravel_pytree's order

    # Admissible perturbations: the independent entries; with the gauge, the trace held.
    keep = np.flatnonzero(marks(lambda f: f.redundant()) == 0)
    basis = np.eye(flat.shape[0])[:, keep]
    if data["trace"] is not None:
        c = marks(lambda f: f.trace_direction())[keep]
        _, _, vt = np.linalg.svd(c[None, :])
        basis = basis @ vt[1:].T  # an orthonormal basis of the trace-preserving directions
    basis = jnp.asarray(basis, dtype)
    jacobian = jax.jacfwd(residual)(flat)
    sensitivity = jnp.linalg.norm(jacobian, axis=0)  # per physical coordinate
    J = jacobian @ basis
    scale = jnp.linalg.norm(J, axis=0)
    dead = scale == 0
    scale = jnp.where(dead, 1.0, scale)
    _, s, vt = jnp.linalg.svd(J / scale, full_matrices=False)
    full_rank = jnp.all(s > problem.rtol * s[0]) & ~jnp.any(dead)
    null = jnp.where((s <= problem.rtol * s[0])[:, None], vt, 0.0)  # near-null directions
    null = (null / scale) @ basis.T  # in the physical coordinates
    # Each physical coordinate in units of its own sensitivity; each direction normalised.
    weighted = null * jnp.where(sensitivity > 0, sensitivity, 1.0)
    weighted = weighted / jnp.maximum(
        jnp.linalg.norm(weighted, axis=1, keepdims=True), jnp.finfo(dtype).tiny
    )
    moved = (jnp.max(jnp.abs(weighted), axis=0) > 0.05) | (sensitivity == 0)
    moved = unravel(moved.astype(dtype))
    moved["values"] = [f.entry_flags(v) for f, v in zip(problem.fitted, moved["values"])]
    flags = jax.tree.map(lambda x: ~(x > 0), moved)
    condition = jnp.where(full_rank, s[0] / s[-1], jnp.inf)
    return flags, s, condition, full_rank
