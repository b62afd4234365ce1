"""Point dipoles carried by rigid rotors: a coupling potential of the rotations `(N, 3, 3)`.

Body `i` turns about a pivot fixed at the world position `x_i` and carries a point dipole
(magnetic or electric) at its pivot, of fixed body-frame moment `μ_i`; its world moment is
`R_i μ_i`. The dipole–dipole energy of every pair (`r = x_j − x_i`, `r̂ = r/|r|`) is

    V(R) = k Σ_{i<j} (R_iμ_i · R_jμ_j − 3 (R_iμ_i · r̂)(R_jμ_j · r̂)) / |r|³,

`k` the prefactor of the units (`μ₀/4π` for magnetic moments in SI, `1/(4πε₀)` for electric
ones; 1 in Gaussian units). A potential on the group in the sense of the paper's §7: the
torques on each body follow from it by autodiff (`AbstractLieSystem.force`).

Symmetry (§7: the symmetry is what leaves `V` unchanged). A common rotation `Q` of all
bodies, `R_i ↦ Q R_i`, keeps every `R_iμ_i · R_jμ_j` but turns the moments against the
fixed pivot directions: `V` is invariant only if `Q r̂_ij = ±r̂_ij` for every pair. So

- pivots on one line (direction `a`): `V` is invariant under the rotations about `a`, and
  the component `a · Σ_i R_i Π_i` of the total spatial angular momentum is conserved
  (exactly by the discrete flow, discrete Noether theorem, paper §2);
- pivots not on one line: no continuous symmetry is left, so no component of
  `Σ_i R_i Π_i` is conserved — only the energy (bounded, by a symplectic method).

The whole of `Σ_i R_i Π_i` is conserved by a coupling of the relative rotations only, e.g.
the alignment energy `−Σ k_ij (R_i a_i) · (R_j b_j)`, which has no `r̂` term.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._checks import is_concrete
from ._potential import AbstractPotential


def _pair_vectors(positions):
    """`(r, i, j)`: `r = x_j − x_i` for every pair `i < j` (static indices)."""
    i, j = np.triu_indices(jnp.shape(positions)[0], k=1)
    return positions[j] - positions[i], i, j


class DipoleCoupling(AbstractPotential):
    """The dipole–dipole energy of rigid rotors (`lievi.RigidRotors`), each carrying a
    point dipole at its fixed pivot:
    `V = k Σ_{i<j} (w_i·w_j − 3 (w_i·r̂)(w_j·r̂)) / r³` with `w_i = R_i μ_i`.

    **Arguments:**

    - `positions`: the pivots' world positions `(N, 3)`, all distinct.
    - `dipoles`: the moments `μ_i` in each body's frame, `(N, 3)`.
    - `strength`: the prefactor `k` of the units (default 1).

    Conserved: with the pivots on one line, the component of the total spatial angular
    momentum `Σ R_i Π_i` along it; otherwise none of it (the module docstring says why).
    """

    positions: Float[Array, "N 3"]
    dipoles: Float[Array, "N 3"]
    strength: Float[Array, ""]

    def __init__(self, positions, dipoles, strength=1.0):
        self.positions = jnp.asarray(positions, float)
        self.dipoles = jnp.asarray(dipoles, float)
        self.strength = jnp.asarray(strength, float)

    def __check_init__(self):
        shape = jnp.shape(self.positions)
        if len(shape) != 2 or shape[-1] != 3 or shape[0] < 2:
            raise ValueError(
                f"`positions` must be the pivots' world positions, shape (N, 3) with N ≥ 2 "
                f"bodies, got shape {shape}."
            )
        if jnp.shape(self.dipoles) != shape:
            raise ValueError(
                f"`dipoles` must be one body-frame moment per body, shape {shape} (that of "
                f"`positions`), got shape {jnp.shape(self.dipoles)}."
            )
        if jnp.ndim(self.strength) != 0:
            raise ValueError(f"`strength` must be a scalar, got shape {jnp.shape(self.strength)}.")
        if is_concrete(self.positions):
            r, i, j = _pair_vectors(np.asarray(self.positions))
            close = np.linalg.norm(r, axis=-1) == 0
            if np.any(close):
                k = int(np.argmax(close))
                raise ValueError(
                    f"`positions`: bodies {i[k]} and {j[k]} share a pivot; a point dipole "
                    "pair needs distinct positions (their energy is infinite)."
                )

    def parameter_conditions(self):
        r, _, _ = _pair_vectors(jnp.asarray(self.positions))
        distinct = jnp.all(jnp.sum(r * r, axis=-1) > 0)
        return super().parameter_conditions() + [
            (distinct, "`positions` must be distinct (no two bodies share a pivot).")
        ]

    def __call__(self, g: Float[Array, "N 3 3"]) -> Scalar:
        dtype = jnp.result_type(g, float)
        r, i, j = _pair_vectors(jnp.asarray(self.positions, dtype))
        w = jnp.einsum("nab,nb->na", g, jnp.asarray(self.dipoles, dtype))  # world moments
        d2 = jnp.sum(r * r, axis=-1)
        d = jnp.sqrt(d2)
        along_i, along_j = jnp.sum(w[i] * r, axis=-1), jnp.sum(w[j] * r, axis=-1)
        pair = (jnp.sum(w[i] * w[j], axis=-1) - 3 * along_i * along_j / d2) / (d2 * d)
        return jnp.asarray(self.strength, dtype) * jnp.sum(pair)
