"""The default initial guess of `fit_inertia`: a linear least-squares estimate of a free
rigid body's inertia from the observations.

The equations of a free rigid body are linear in the inertia `I` given the motion:

- from orientations, the spatial angular momentum `g I ω` is conserved. With the body
  velocities `ω_{k+½} = log(R_kᵀ R_{k+1})/Δt` and the midpoint attitudes
  `R_{k+½} = R_k exp(½ log(R_kᵀ R_{k+1}))`, every `k` gives `R_{k+½} I ω_{k+½} = L` — three
  homogeneous linear equations in `(I, L)` (or, with `Π₀` known, `L = R₀ Π₀`: linear
  least squares in `I` alone);
- from angular velocities, Euler's equations `I ω̇ = (I ω) × ω` with `ω̇` by central
  differences.

`I` (principal moments, or the six entries of a tensor) is the right singular vector of the
stacked system for its smallest singular value, scaled to the trace `3` (the scale is not
observable without `Π₀`). The estimate is used when it is well posed: the smallest
singular value clearly separated from the next (else the data leave a family of inertias,
e.g. a spin about a principal axis or a body at rest), and a positive definite (and, with
`realisable`, realisable) inertia after moving moments that are too small to a floor.
Otherwise the start is the equal moments `(1, 1, 1)`.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._groups._so3 import SO3

GAP = 1.5  # the smallest singular value must be below 1/GAP of the next
FLOOR = 0.02  # moments (second moments, if realisable) at least this fraction of their sum


def default_inertia(orientations, angular_velocities, dt, m0, tensor, realisable):
    """Per-body initial guesses `(*batch, 3)` or `(*batch, 3, 3)` (numpy; concrete input)."""
    obs = orientations if orientations is not None else angular_velocities
    core = 3 if orientations is not None else 2
    batch_shape = tuple(np.shape(obs)[: np.ndim(obs) - core])
    basis = _basis(tensor)
    flat = lambda x: (
        None if x is None else np.asarray(x, float).reshape((-1,) + np.shape(x)[len(batch_shape) :])
    )
    R, W = flat(orientations), flat(angular_velocities)
    M = None if m0 is None else flat(np.broadcast_to(m0, batch_shape + (3,)))
    if R is not None:
        rows, rhs = _momentum_rows(R, dt, basis, M)
    else:
        rows, rhs = _euler_rows(W, dt, basis), None
    n = rows.shape[0]
    guesses = np.stack(
        [_solve(rows[b], None if rhs is None else rhs[b], tensor, realisable) for b in range(n)]
    )
    return guesses.reshape(batch_shape + guesses.shape[1:])


def _basis(tensor):
    if not tensor:
        return np.stack([np.diag(e) for e in np.eye(3)])
    basis = [np.diag(e) for e in np.eye(3)]
    for i, j in ((0, 1), (0, 2), (1, 2)):
        E = np.zeros((3, 3))
        E[i, j] = E[j, i] = 1
        basis.append(E)
    return np.stack(basis)


def _momentum_rows(R, dt, basis, M):
    """Rows of `R_{k+½} I ω_{k+½} − L = 0` per body: `(bodies, 3(S−1), p + 3)`, or with Π₀
    known `(rows in I, right-hand sides L = R₀ Π₀)`."""
    with jax.ensure_compile_time_eval():
        xi = SO3.log(jnp.swapaxes(R[:, :-1], -1, -2) @ R[:, 1:])
        mid = np.asarray(R[:, :-1] @ SO3.exp(xi / 2))
    omega = np.asarray(xi) / dt
    columns = np.einsum("bkij,pjl,bkl->bkip", mid, basis, omega)  # R_{k+½} E_p ω
    columns = columns.reshape(R.shape[0], -1, basis.shape[0])
    if M is not None:
        L = np.einsum("bij,bj->bi", R[:, 0], M)
        return columns, np.tile(L, (1, columns.shape[1] // 3))
    eye = np.tile(np.eye(3), (columns.shape[1] // 3, 1))
    return np.concatenate([columns, -np.broadcast_to(eye, columns.shape[:2] + (3,))], -1), None


def _euler_rows(W, dt, basis):
    """Rows of `E_p ω̇ − (E_p ω) × ω` per body (central differences)."""
    omega = W[:, 1:-1]
    dot = (W[:, 2:] - W[:, :-2]) / (2 * dt)
    E_dot = np.einsum("pij,bkj->bkip", basis, dot)
    E_omega = np.einsum("pij,bkj->bkpi", basis, omega)
    cross = np.cross(E_omega, omega[:, :, None, :])  # (b, k, p, 3)
    rows = E_dot - np.swapaxes(cross, -1, -2)
    return rows.reshape(W.shape[0], -1, basis.shape[0])


def _solve(rows, rhs, tensor, realisable):
    fallback = np.eye(3) if tensor else np.ones(3)
    p = 6 if tensor else 3
    if not np.all(np.isfinite(rows)) or rows.shape[0] < rows.shape[1]:
        return fallback
    if rhs is not None:  # Π₀ known: the scale too
        _, s, _ = np.linalg.svd(rows, full_matrices=False)
        if s[-1] <= 1e-8 * s[0]:
            return fallback
        x = np.linalg.lstsq(rows, rhs, rcond=None)[0]
    else:
        _, s, vt = np.linalg.svd(rows, full_matrices=False)
        if s[-2] <= GAP * s[-1]:
            return fallback
        x = vt[-1, :p]
    inertia = np.einsum("p,pij->ij", x, _basis(tensor))
    trace = np.trace(inertia)
    if not trace != 0:
        return fallback
    if rhs is None:
        inertia = inertia * (3 / trace)  # the sign, and the gauge's scale
    elif trace < 0:
        return fallback
    inertia = _feasible(inertia, realisable)
    if inertia is None:
        return fallback
    return inertia if tensor else np.diagonal(inertia).copy()


def _feasible(inertia, realisable):
    """Moments (or second moments) below `FLOOR` of their sum raised to it; `None` when
    no positive part is left."""
    values, axes = np.linalg.eigh((inertia + inertia.T) / 2)
    moments = np.trace(inertia) / 2 - values if realisable else values
    total = np.sum(np.maximum(moments, 0))
    if not total > 0:
        return None
    moments = np.maximum(moments, FLOOR * total)
    values = np.sum(moments) - moments if realisable else moments
    return axes @ np.diag(values) @ axes.T
