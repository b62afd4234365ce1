"""How each fitted leaf is optimised: unconstrained coordinates θ ↔ the physical value.

One class per kind of leaf, each owning its transform both ways and what else differs
between kinds (the gauge, the admissible perturbations of the identifiability report, the
boundary test):

- `Free`: any array leaf, fitted as is.
- `PositiveMoments`: principal moments `I = exp(θ)` (positive definite; the boundary
  `I_i = 0` is no physical body, so it may lie at infinity).
- `RealisableMoments`: `I = ΣΛ − Λ` with `Λ = θ²` (the second moments of a mass
  distribution, `Σ = diag Λ ⪰ 0`, §5 of the paper). The realisability boundary — a planar
  body, `Λ_i = 0`, `I_j = I_i + I_k` — is a real body and lies at a finite distance in
  θ: with `Λ = exp(θ)` it would lie at infinity, where the gradient in θ vanishes
  (`∂/∂θ_i = Λ_i ∂/∂Λ_i → 0`) and a fit drifting towards it stops there, satisfying any
  gradient test.
- `PositiveTensor`: `I = L Lᵀ`, `L` lower triangular with diagonal `exp(θ_diag)`.
- `RealisableTensor`: `I = tr(Σ)·1 − Σ`, `Σ = L Lᵀ` with `L`'s diagonal free (`Σ ⪰ 0`;
  singular `Σ`, a planar body, at a finite distance, as for the moments).
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
import numpy as np

# A fit ends "on the boundary" when the smallest second moment is below this fraction of
# their sum (`RealisableMoments`, `RealisableTensor`).
BOUNDARY_RTOL = 1e-3


class Parametrisation(eqx.Module):
    """One fitted leaf: its flat index in the system's leaves and its per-body shape."""

    index: int = eqx.field(static=True)
    shape: tuple = eqx.field(static=True)

    is_inertia: ClassVar[bool] = False

    def to_value(self, theta):
        """The physical value from unconstrained `theta` (traceable)."""
        return theta

    def from_value(self, value: np.ndarray) -> np.ndarray:
        """`theta` with `to_value(theta) = value` (concrete; raises if not representable)."""
        return np.asarray(value, float)

    def gauge(self, value, trace):
        """The value with the gauge applied (inertia: its trace held at `trace`)."""
        return value

    def trace(self, value):
        """The trace of an inertia value (zero for other leaves)."""
        return jnp.zeros((), value.dtype)

    def symmetrise(self, value):
        """A perturbed physical value made admissible (tensors: the lower triangle mirrors
        the upper one)."""
        return value

    def redundant(self) -> np.ndarray:
        """1 on the entries that are not independent coordinates (a tensor's lower
        triangle), 0 elsewhere."""
        return np.zeros(self.shape)

    def trace_direction(self) -> np.ndarray:
        """The coefficients of the trace in the entries (zero for other leaves)."""
        return np.zeros(self.shape)

    def entry_flags(self, moved):
        """Per entry, whether some near-null direction moves it (tensors: either mirror)."""
        return moved > 0

    def on_boundary(self, value):
        """Whether the value lies on the constraint's boundary (never, unconstrained)."""
        return jnp.asarray(False)


class Free(Parametrisation):
    """Any array leaf, fitted as is."""


class _Moments(Parametrisation):
    is_inertia: ClassVar[bool] = True

    def gauge(self, value, trace):
        return value * (trace / jnp.sum(value))

    def trace(self, value):
        return jnp.sum(value)

    def trace_direction(self):
        return np.ones(self.shape)


class PositiveMoments(_Moments):
    def to_value(self, theta):
        return jnp.exp(theta)

    def from_value(self, value):
        value = np.asarray(value, float)
        if np.any(value <= 0):
            raise ValueError(f"`inertia` (initial guess) must be positive; got {value}.")
        return np.log(value)


class RealisableMoments(_Moments):
    def to_value(self, theta):
        second_moments = theta**2  # Λ
        return jnp.sum(second_moments) - second_moments

    def from_value(self, value):
        value = np.asarray(value, float)
        second_moments = np.sum(value) / 2 - value
        if np.any(second_moments <= 0):
            raise ValueError(
                "`inertia` (initial guess) must be positive and satisfy the strict triangle "
                f"inequalities I₁ < I₂ + I₃, …; got {value}."
            )
        return np.sqrt(second_moments)

    def on_boundary(self, value):
        second_moments = jnp.sum(value) / 2 - value
        return jnp.min(second_moments) <= BOUNDARY_RTOL * jnp.sum(second_moments)


class _Tensor(Parametrisation):
    is_inertia: ClassVar[bool] = True

    def factor(self, theta):
        """The lower-triangular factor `L` with the diagonal `diagonal(θ)`."""
        L = jnp.zeros((3, 3), theta.dtype).at[jnp.tril_indices(3)].set(theta)
        return L.at[jnp.diag_indices(3)].set(self.diagonal(jnp.diagonal(L)))

    def diagonal(self, theta_diagonal):
        return theta_diagonal

    def from_spd(self, matrix, what):
        try:
            L = np.linalg.cholesky(matrix)
        except np.linalg.LinAlgError:
            raise ValueError(f"`inertia` (initial guess) must be {what}.") from None
        return L

    def gauge(self, value, trace):
        return value * (trace / jnp.trace(value))

    def trace(self, value):
        return jnp.trace(value)

    def symmetrise(self, value):
        return jnp.triu(value) + jnp.triu(value, 1).T

    def redundant(self):
        return np.tril(np.ones((3, 3)), -1)

    def trace_direction(self):
        return np.eye(3)

    def entry_flags(self, moved):
        return (moved + moved.T) > 0


class PositiveTensor(_Tensor):
    def diagonal(self, theta_diagonal):
        return jnp.exp(theta_diagonal)

    def to_value(self, theta):
        L = self.factor(theta)
        return L @ L.T

    def from_value(self, value):
        L = self.from_spd(np.asarray(value, float), "symmetric positive definite")
        L[np.diag_indices(3)] = np.log(np.diagonal(L))
        return L[np.tril_indices(3)]


class RealisableTensor(_Tensor):
    def to_value(self, theta):
        L = self.factor(theta)
        second_moments = L @ L.T  # Σ
        return jnp.trace(second_moments) * jnp.eye(3, dtype=theta.dtype) - second_moments

    def from_value(self, value):
        value = np.asarray(value, float)
        L = self.from_spd(
            np.trace(value) / 2 * np.eye(3) - value,
            "symmetric positive definite and physically realisable (tr(I)/2 − I ≻ 0)",
        )
        return L[np.tril_indices(3)]

    def on_boundary(self, value):
        second_moments = jnp.linalg.eigvalsh(jnp.trace(value) / 2 * jnp.eye(3) - value)
        return second_moments[0] <= BOUNDARY_RTOL * jnp.sum(second_moments)


def inertia_parametrisation(index: int, shape: tuple, realisable: bool) -> Parametrisation:
    """The parametrisation of a rigid body's inertia of per-body `shape` `(3,)` or `(3, 3)`."""
    if shape == (3,):
        kind = RealisableMoments if realisable else PositiveMoments
    elif shape == (3, 3):
        kind = RealisableTensor if realisable else PositiveTensor
    else:
        raise ValueError(f"`inertia` must have shape (3,) or (3, 3), got {shape}.")
    return kind(index, tuple(shape))
