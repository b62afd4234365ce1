"""Runge–Kutta–Nyström splittings of the symmetric (Lagrange) top, with its exact free flow.

**The free flow.** A body with principal moments `(I₁, I₁, I₃)` has the kinetic energy

    T(Π) = |Π|²/(2I₁) + (c/2)Π₃²,     c = 1/I₃ − 1/I₁,

a sum of two pieces that Poisson-commute (`|Π|²` is a Casimir of so(3)*), so its flow is
the product of theirs. The flow of `|Π|²/(2I₁)` keeps `Π` and turns `g` at the constant
body velocity `Π/I₁`; that of `(c/2)Π₃²` turns `g` at `cΠ₃e₃` (`Π₃` constant). For a time `t`

    F = exp(t Π₀/I₁) exp(t c Π₀₃ e₃),     g(t) = g₀ F,     Π(t) = Fᵀ Π₀

(the first factor fixes `Π₀`, the second is the rotation of `Π` about `e₃` by
`−t c Π₀₃`): two rotations, exact, against the axis splitting's five sub-rotations
(`LiePoissonSplitting`, second order in the free flow).

**The splitting.** The heavy top's `H = T(Π) + V(Γ)` with `V` a function of the attitude
alone (`Γ = gᵀa`; `UniformGravity`) has `{V, {V, {V, T}}} = 0` (`{V, T}` is linear in `Π`,
`{V, {V, T}}` a function of `Γ`, and functions of `Γ` Poisson-commute), the structure of
`T(p) + V(q)` with `T` quadratic. The symmetric Runge–Kutta–Nyström splittings of
Blanes & Moan (J. Comput. Appl. Math. 142 (2002) 313–330) satisfy fewer order conditions
there than compositions of a symmetric second-order step, and have small error
constants: `SRKN₆ᵇ` (order 4, 6 drifts) and `SRKN₁₁ᵇ` (order 6, 11 drifts), in the
kick-first form `e^{b_s hV} e^{a_s hT} ⋯ e^{a_1 hT} e^{b_0 hV}` (`_kernels/_scheme.py`).
Their coefficients are the paper's, as tabulated to 15–17 digits; the middle weights
are set from `Σa_i = Σb_i = 1`. The tests check the observed orders.

Each factor is the exact flow of a Hamiltonian on T*SO(3), so the step is a Poisson map
on se(3)* that keeps `|Γ|`, the vertical momentum `Π·Γ` and (the body being symmetric
about `e₃` and the potential about the vertical) `Π₃` to round-off, with bounded energy
error; symmetric (`Φ_{−h} = Φ_h⁻¹`), explicit.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Scalar

from .._checks import check_shape, is_concrete
from .._groups._so3 import SO3
from .._kernels._axisymmetric import (
    AxisymmetricKernel,
    axisymmetric_result,
    is_axisymmetric,
    mean_first_moments,
)
from .._kernels._composition import SchemeKernel
from .._kernels._kick import KickKernel
from .._kernels._scheme import SplittingScheme
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from ._base import AbstractKickIntegrator, StepInfo


def _palindrome(half: tuple[float, ...]) -> tuple[float, ...]:
    """`(w_1, …, w_m)` ↦ `(w_1, …, w_m, 1 − 2Σw_i, w_m, …, w_1)`: symmetric, summing to 1."""
    return (*half, 1.0 - 2.0 * sum(half), *reversed(half))


def _even_palindrome(half: tuple[float, ...]) -> tuple[float, ...]:
    """`(w_1, …, w_m)` ↦ `(w_1, …, w_m, w_m, …, w_1)` with `w_m` set so the sum is 1."""
    last = 0.5 - sum(half[:-1])
    return (*half[:-1], last, last, *reversed(half[:-1]))


# Blanes & Moan (2002), Table 3: SRKN₆ᵇ (order 4) and SRKN₁₁ᵇ (order 6); drifts `a_i`,
# kicks `b_i`, kick first. The last listed entry of each half is set from the sums.
SCHEMES = {
    4: SplittingScheme(
        drifts=_even_palindrome((0.245298957184271, 0.604872665711080, -0.350171622895351)),
        kicks=_palindrome((0.0829844064174052, 0.396309801498368, -0.0390563049223486)),
    ),
    6: SplittingScheme(
        drifts=_palindrome(
            (
                0.123229775946271,
                0.290553797799558,
                -0.127049212625417,
                -0.246331761062075,
                0.357208872795928,
            )
        ),
        kicks=_even_palindrome(
            (
                0.0414649985182624,
                0.198128671918067,
                -0.0400061921041533,
                0.0752539843015807,
                -0.0115113874206879,
                0.2366699247869311,
            )
        ),
    ),
}


def check_axisymmetric(method: str, inertia, tensor: bool = False) -> None:
    """Raise `ValueError` unless concrete principal moments `(..., 3)` (with `tensor`:
    inertia tensors `(..., 3, 3)`, which must be diagonal) have equal first two entries,
    to a few ulps. Traced moments pass: the other integrators, too, leave traced
    parameters to the run (`check_pair_sums`)."""
    if not is_concrete(inertia):
        return
    values = np.asarray(inertia, float)
    if tensor:
        diagonal = np.diagonal(values, axis1=-2, axis2=-1)
        symmetric = np.all(values * (1 - np.eye(3)) == 0)
    else:
        diagonal, symmetric = values, True
    if not symmetric or not np.all(is_axisymmetric(*np.moveaxis(diagonal, -1, 0))):
        raise ValueError(
            f"{method}: `inertia` must be axisymmetric about the body's third axis, principal "
            f"moments (I₁, I₁, I₃) (or a diagonal tensor with equal first two entries); got "
            f"{values.tolist()}. For any other body use `Composition(LiePoissonSplitting(), "
            "…)`."
        )


def check_symmetric_body(method: str, system: AbstractLieSystem, batched: bool = False):
    """Raise `ValueError` unless `system` is a rigid body on SO(3) whose concrete inertia is
    axisymmetric (`check_axisymmetric`; `batched`: a batch of systems, a leading axis);
    returns its inertia."""
    inertia = system.kinetic_tensor()  # a rigid body's principal moments, or its tensor
    if system.group != SO3 or system.lambda_matrix() is None or inertia is None:
        raise ValueError(
            f"{method} integrates a rigid body on SO(3) symmetric about its third axis: pass "
            f"a `lievi.RigidBody` (with or without a potential), got {type(system).__name__}."
        )
    inertia = jnp.asarray(inertia)
    check_axisymmetric(method, inertia, tensor=inertia.ndim == 2 + batched)
    return inertia


def symmetric_moments(method: str, system: AbstractLieSystem):
    """`(I₁, I₃, diagonal)` of one rigid body on SO(3) with principal moments
    `(I₁, I₁, I₃)` (`check_symmetric_body`); `I₁` the mean of the first two
    (`mean_first_moments`), `diagonal` the moments (for the traced check)."""
    inertia = check_symmetric_body(method, system)
    diagonal = jnp.diagonal(inertia) if inertia.ndim == 2 else inertia
    return mean_first_moments(diagonal), diagonal[2], diagonal


def axisymmetric_free_flow(I1, I3, g, m, t):
    """The exact free flow for a time `t` (module docstring): `(g F, Fᵀ Π)`."""
    spin = t * (1 / I3 - 1 / I1) * m[2]
    F = SO3.exp(t * m / I1) @ SO3.exp(jnp.stack([0 * spin, 0 * spin, spin]))
    return g @ F, F.T @ m


class SymmetricTopSplitting(AbstractKickIntegrator):
    """Runge–Kutta–Nyström splitting of a symmetric top: kicks of the potential and the
    exact free flow of an axisymmetric body (see the module docstring for the equations).

    **Arguments:**

    - `order`: 4 (Blanes–Moan `SRKN₆ᵇ`: 6 free flows and 6 torques a step) or 6
      (`SRKN₁₁ᵇ`: 11 and 11).

    For a `lievi.RigidBody` with principal moments `(I₁, I₁, I₃)` — symmetric about its
    third axis — and a potential of its attitude (`UniformGravity`: the Lagrange top);
    any other inertia is refused (`ValueError` naming `inertia`; a traced one, under `jit`,
    ends the run as `RESULTS.invalid_input`). A free symmetric body
    takes one exact flow a step. Why its own class and not a `Composition` scheme: its
    kick weights are not those of a composition of a symmetric second-order step (they
    are chosen independently of the drift weights), and its free flow exists only for
    a symmetric body; `Composition(LiePoissonSplitting(), …)` remains the method for
    any body. External forcing is not supported (`ValueError`).
    """

    target_order: int = eqx.field(static=True)
    scheme: SplittingScheme = eqx.field(static=True)

    def __init__(self, order: int = 6):
        if isinstance(order, bool) or order not in SCHEMES:
            raise ValueError(f"`order` must be one of {sorted(SCHEMES)}, got {order!r}.")
        self.target_order = order
        self.scheme = SCHEMES[order]

    def order(self) -> int:
        return self.target_order

    def is_symmetric(self) -> bool:
        # Palindromic weights of exact flows: Φ_{−h} = Φ_h⁻¹.
        return True

    def step_bound(self) -> float:
        # The longest free flow is max|a_i|·h.
        return super().step_bound() / max(abs(a) for a in self.scheme.drifts)

    def own_step(self) -> bool:
        return type(self) is SymmetricTopSplitting

    def kernels(self):
        return (AxisymmetricKernel(),)

    def batch_kernel(self, system: AbstractLieSystem, batched: bool = False):
        # Where a run is planned, on the concrete system (its step may see it traced).
        check_symmetric_body("SymmetricTopSplitting", system, batched)
        free = self.free_kernel(system, batched)
        if free is None or system.potential is None:
            return free
        # The kicks of the potential at the scheme's weights, between exact free flows.
        kernel = KickKernel(free, system.potential)
        if kernel.physics(system, batched) is None:
            return None
        return SchemeKernel(kernel, self.scheme.drifts, scheme=self.scheme)

    def free_step(self, system: AbstractLieSystem, g, m, h: Scalar):
        I1, I3, moments = symmetric_moments("SymmetricTopSplitting", system)
        check_shape("g", g, (3, 3), "an element of SO(3)")
        check_shape("m", m, (3,), "momentum coordinates of so(3)*")
        fast = self.kernel_step(system, g, m, h)
        if fast is not None:  # the closed form on components (principal moments)
            return fast
        g_next, m_next = axisymmetric_free_flow(I1, I3, g, m, h)
        finite = jnp.all(jnp.isfinite(m_next)) & jnp.all(jnp.isfinite(g_next))
        finite_code = jnp.where(finite, RESULTS.successful, RESULTS.nonfinite)
        result = axisymmetric_result(finite_code, is_axisymmetric(*moments))
        zero = jnp.zeros((), m_next.dtype)
        return g_next, m_next, StepInfo(result, jnp.zeros((), jnp.int32), zero)

    def step(self, system: AbstractLieSystem, g, m, h: Scalar, force=None, t: Scalar = 0.0):
        return self._stages(system, g, m, h, None, force)[:3]

    def _step_from_cache(self, system, g, m, h, cache, force, t):
        return self._stages(system, g, m, h, cache, force)

    def _stages(self, system, g, m, h, start_force, force):
        if force is not None:
            raise ValueError(
                "SymmetricTopSplitting does not take external forcing (`forcing`): its "
                "weights are for a potential of the attitude alone. Use a `Composition` of "
                "a kick integrator."
            )
        if system.potential is None:
            # The free flow of the whole step, exactly.
            return (*system.free_flow(self, g, m, h), None)
        scheme = self.scheme
        start_force = system.force(g) if start_force is None else start_force
        m = m + scheme.kicks[0] * h * start_force
        weights = jnp.asarray([scheme.drifts, scheme.kicks[1:]], dtype=m.dtype).T

        def stage(carry, weight):
            g, m, _, result = carry
            drift, kick = weight[0], weight[1]
            g, m, info = system.free_flow(self, g, m, drift * h)
            end_force = system.force(g)
            m = m + kick * h * end_force
            return (g, m, end_force, RESULTS.first_failure(result, info.result)), None

        init = (g, m, start_force, jnp.asarray(RESULTS.successful, jnp.int32))
        (g, m, end_force, result), _ = jax.lax.scan(stage, init, weights)
        nonfinite = (result == RESULTS.successful) & ~jnp.all(jnp.isfinite(m))
        result = jnp.where(nonfinite, RESULTS.nonfinite, result)
        zero = jnp.zeros((), m.dtype)
        return g, m, StepInfo(result, jnp.zeros((), jnp.int32), zero), end_force
