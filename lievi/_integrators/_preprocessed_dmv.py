"""The preprocessed discrete Moser–Veselov algorithm (Hairer & Vilmart 2006).

E. Hairer and G. Vilmart, *Preprocessed discrete Moser–Veselov algorithm for the full
dynamics of a rigid body*, J. Phys. A 39 (2006) 13225 (§2–§3).

**The idea.** The DMV step of `lievi.MoserVeselov` on the free rigid body keeps the Casimir
`C = |y|²` and the energy `H = ½ yᵀI⁻¹y` exactly, is symplectic on `T*SO(3)` and commutes
with left rotations. On each invariant torus it is therefore a translation in the angle
variables: the exact flow of a Hamiltonian `S_h(H, C)`. Since `H` moves the body along the
torus and `C` only rotates the attitude about the body momentum, DMV with step `h` is the
exact time-`h` flow of a rigid body whose inverse inertia is `α I⁻¹ + β·Id`, with `α`, `β`
depending on `h`, `H`, `C` and the inertia. Conversely, DMV run with the *modified* inverse
inertia

    Î⁻¹(h) = α(h) I⁻¹ + β(h) Id,      α = 1 + a₂h² + a₄h⁴ + …,   β = b₂h² + b₄h⁴ + …

(coefficients in `H`, `C` and the inertia; odd powers vanish because DMV is symmetric) is
the exact flow of the body `I` over `h`, momentum *and* attitude. Hairer–Vilmart's
preprocessed DMV of order `p` is DMV with `Î⁻¹` cut after `h^(p−2)`: the remainder
perturbs the moments by `O(h^p)`, so the local error is `O(h^(p+1))`.

**What is truncated, and why this choice.** Exactly the series `α(h)`, `β(h)` of the
modified moments, after `h^(p−2)` — nothing else: the DMV step with the truncated `Î` is
solved to round-off, and there is no separate attitude correction (`β` is it). This is
the accurate place to cut. The same step could be written as DMV with a modified *step*
`h'` plus an attitude rotation, `τ(h') = h` with `τ(s)` the exact-flow time reached by one
DMV step of size `s`; but `τ` is a function of the DMV step and inherits its finite radius
of convergence, and its coefficients grow fast with one sign (Hairer–Vilmart body
`I = (0.6, 0.8, 1)`, `y = (1.8, 0.4, −0.9)`: `τ = s + 2.43s³ + 11.9s⁵ + 73.0s⁷ + 503s⁹ +
3715s¹¹ + …`), so cutting it leaves a large remainder (at `h = 0.1`, T = 10: errors 6×
(order 4) to 3×10⁵× (order 10) larger). The modified moments are functions of the exact
flow's time, and their coefficients decay on the same problem (`α = 1 − 2.43h² + 1.94h⁴ −
0.603h⁶ + 0.0995h⁸`, `β = 1.21h² − 1.73h⁴ + 0.624h⁶ − 0.109h⁸`); cutting them gives, step
for step, the errors of Hairer–Vilmart's own code (`docs/preprocessed_dmv.md` has the
table).

**How `α`, `β` are computed.** Numerically, at run time, in JAX (so they differentiate in
the momentum, the inertia and `h`, batch under `vmap`, and work for a full inertia tensor
without an eigendecomposition): for the given `I⁻¹` and `y`, the Taylor coefficients in `h`
of the DMV step `(F(h), y₁(h))` with a series-valued inverse inertia follow from its Cayley
form `x = h Î⁻¹(h)·vee((1 − X/2)Ŷ(1 + X/2))` power by power (`x₀ = 0`, so each power
needs the lower ones only); those of the exact flow from `(k+1) y_{k+1} = Σ_j y_j ×
I⁻¹y_{k−j}`, `(k+1) P_{k+1} = Σ_j P_j (I⁻¹y_{k−j})^` (`Ṗ = PΩ̂`). Then `a_k`, `b_k` are
fixed power by power (`modified_moments_series`). At given `(H, C, I)` these numbers are
Hairer–Vilmart's coefficients (their closed forms are polynomials in `h²H`, `h²C` with
coefficients rational in the moments); `tools/derive_preprocessed_dmv.py` re-derives them
in exact rational arithmetic, checks the structure (the other mismatch components vanish
identically; odd powers vanish) and prints the polynomials. The series depend only on
`(h, H, C)`, which the modified step keeps, so `prepare` computes them once per trajectory;
the step then costs one DMV step on the modified body.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._checks import check_scalar, state_dtype, step_size_valid
from .._groups._so3 import SO3
from .._kernels._preprocessed import PreprocessedKernel
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from .._systems._rigid_body import RigidBody
from ._base import AbstractIntegrator, StepInfo
from ._moser_veselov import MoserVeselov
from ._preprocessed_shared import fitted_principal_moments

ORDERS = (4, 6, 8, 10)


def _cauchy_mask(n: int) -> np.ndarray:
    """`mask[i, j, k] = 1` iff `i + j = k`: the Cauchy product of truncated series."""
    i, j, k = np.ogrid[:n, :n, :n]
    return (i + j == k).astype(float)


def _hat(v):
    return SO3.hat(v)


def _vee(M):
    return jnp.stack([M[..., 2, 1], M[..., 0, 2], M[..., 1, 0]], axis=-1)


def _pairs(mask, k):
    """`pairs[i, j] = 1` iff `i + j = k`: one row of a Cauchy product (`k` traced)."""
    return jax.lax.dynamic_index_in_dim(mask, k, axis=2, keepdims=False)


def _inner_at(k, pairs, X, Y):
    """The coefficient `k` of `(1 − X/2) Ŷ (1 + X/2)`, from `X₁ … X_k` (`X₀ = 0`): `Ŷ` at
    `k = 0`, the linear terms, the quadratic one."""
    X_k = jax.lax.dynamic_index_in_dim(X, k, keepdims=False)
    quadratic = jnp.einsum("ij,iab,bc,jcd->ad", pairs, X, Y, X)
    return Y * (k == 0) + (Y @ X_k - X_k @ Y) / 2 - quadratic / 4


def _cayley_at(k, pairs, half, F):
    """`F_k` of `F = cay(X)`, `k ≥ 1`, from `(1 − X/2) F = 1 + X/2`: `X_k/2 + Σ_{i+j=k}
    (X_i/2) F_j` (`half = X/2`, `X₀ = 0`; `F_k` itself not yet set, zero)."""
    half_k = jax.lax.dynamic_index_in_dim(half, k, keepdims=False)
    return half_k + jnp.einsum("ij,iab,jbc->ac", pairs, half, F)


def dmv_series(inverse_inertia, y: Float[Array, 3], degree: int):
    """Taylor coefficients in the step `s` of the DMV step: `(F(s), y₁(s))`, degree `degree`.

    `F = cay(x)`, `I x = s·vee((1 − X/2) Ŷ (1 + X/2))`, `y₁ = Fᵀy` (as in `MoserVeselov`).
    `inverse_inertia`: a constant `(3, 3)` matrix, or a series `(degree + 1, 3, 3)` in `s`
    (the modified inverse inertia `α(s) I⁻¹ + β(s)`). Power by power, as `exact_series`:
    `x₀ = 0`, so the coefficient `k` of `(1 − X/2) Ŷ (1 + X/2)` needs `x₁ … x_k` only, and
    `x_{k+1}` is its Cauchy product with `Î⁻¹`; then `F_k = X_k/2 + Σ_{i≥1} X_i F_{k−i}/2`.
    Each power costs one row of a Cauchy product (a `fori_loop`: one compiled power), not
    the whole truncated product that a fixed-point sweep over all powers recomputed for
    every power (8× the work at order 8; the start-up of a batched run was mostly this).
    """
    n = degree + 1
    mask = jnp.asarray(_cauchy_mask(n), y.dtype)
    eye = jnp.eye(3, dtype=y.dtype)
    if inverse_inertia.ndim == 2:
        inverse_inertia = jnp.zeros((n, 3, 3), y.dtype).at[0].set(inverse_inertia)
    inverse_inertia = inverse_inertia[:n]
    Y = _hat(y)

    def power_x(k, series):
        x, inner = series
        pairs = _pairs(mask, k)
        inner = inner.at[k].set(_vee(_inner_at(k, pairs, _hat(x), Y)))
        x_next = jnp.einsum("ij,iab,jb->a", pairs, inverse_inertia, inner)
        return x.at[k + 1].set(x_next), inner

    zeros = jnp.zeros((n, 3), y.dtype)
    x, _ = jax.lax.fori_loop(0, degree, power_x, (zeros, zeros))
    half = _hat(x) / 2

    def power_F(k, F):
        return F.at[k].set(_cayley_at(k, _pairs(mask, k), half, F))

    F = jax.lax.fori_loop(1, n, power_F, jnp.zeros((n, 3, 3), y.dtype).at[0].set(eye))
    y1 = jnp.einsum("kba,b->ka", F, y)
    return F, y1


def exact_series(inverse_inertia: Float[Array, "3 3"], y: Float[Array, 3], degree: int):
    """Taylor coefficients in `t` of the exact `y(t)` (Euler) and `P(t)` (`Ṗ = PΩ̂`):
    `(k+1) y_{k+1} = Σ_j y_j × I⁻¹y_{k−j}`, `(k+1) P_{k+1} = Σ_j P_j (I⁻¹y_{k−j})^`."""
    n = degree + 1
    mask = jnp.asarray(_cauchy_mask(n), y.dtype)
    ys = jnp.zeros((n, 3), y.dtype).at[0].set(y)
    Ps = jnp.zeros((n, 3, 3), y.dtype).at[0].set(jnp.eye(3, dtype=y.dtype))

    def recurrence(k, series):
        ys, Ps = series
        pairs = jax.lax.dynamic_index_in_dim(mask, k, axis=2, keepdims=False)  # i + j = k
        omegas = ys @ inverse_inertia.T
        y_next = jnp.einsum("ij,iab,jb->a", pairs, _hat(ys), omegas) / (k + 1)
        P_next = jnp.einsum("ij,iab,jbc->ac", pairs, Ps, _hat(omegas)) / (k + 1)
        return ys.at[k + 1].set(y_next), Ps.at[k + 1].set(P_next)

    return jax.lax.fori_loop(0, degree, recurrence, (ys, Ps))


def modified_moments_series(inverse_inertia: Float[Array, "3 3"], y: Float[Array, 3], degree: int):
    """`(α, β)`: the Taylor coefficients in `h` (up to `h^degree`; odd powers are zero) of
    the modification `I⁻¹ ↦ α(h) I⁻¹ + β(h)·Id` whose DMV step is the exact flow over `h`.

    A change `δα h^k, δβ h^k` of the modified moments moves the Cayley coordinates `x` of
    the step by `h^{k+1}(δα I⁻¹y + δβ y)`, hence `y₁` by `h^{k+1} δα ẏ(0)` and the attitude
    mismatch `R = P(h)ᵀF` by the same vector (hatted), and nothing of lower order. So one
    pass over the powers of the DMV step (`dmv_series`'s recurrence) fixes them as it goes:
    at power `k + 1`, computed with `α_k = β_k = 0`, `δα_k` is read off the momentum
    mismatch (projected on `ẏ(0)`) and `δβ_k` off the component along `y` of the attitude
    mismatch, for even `k` (odd coefficients vanish by symmetry), and `x`, `F` at that power
    are moved by them before the next. (A fixed-point sweep over the whole series per even
    power cost 3× at order 8.) The other components of
    the mismatch vanish by the torus argument of the module docstring
    (`tools/derive_preprocessed_dmv.py` checks it in exact arithmetic).
    """
    n = degree + 2  # the step is matched up to h^(degree + 1)
    dtype = y.dtype
    eye = jnp.eye(3, dtype=dtype)
    mask = jnp.asarray(_cauchy_mask(n), dtype)
    ys, Ps = exact_series(inverse_inertia, y, n - 1)
    velocity = ys[1]
    speed2 = jnp.dot(velocity, velocity)
    norm2 = jnp.dot(y, y)
    spin_axis = inverse_inertia @ y
    # At a relative equilibrium (ẏ = 0) α is not determined by y: keep α = 1 there; β then
    # accounts for the whole attitude error (double `where`: safe gradients). At y = 0
    # nothing moves and (α, β) = (1, 0).
    moving = speed2 > 1e3 * jnp.finfo(dtype).tiny
    safe_speed2 = jnp.where(moving, speed2, 1.0)
    spinning = norm2 > 1e3 * jnp.finfo(dtype).tiny
    safe_norm2 = jnp.where(spinning, norm2, 1.0)

    Y = _hat(y)

    def power(k, state):
        x, inner, F, alpha, beta = state
        pairs, pairs_next = _pairs(mask, k), _pairs(mask, k + 1)
        inner = inner.at[k].set(_vee(_inner_at(k, pairs, _hat(x), Y)))
        modified = alpha[:, None, None] * inverse_inertia + beta[:, None, None] * eye
        x = x.at[k + 1].set(jnp.einsum("ij,iab,jb->a", pairs, modified, inner))
        F = F.at[k + 1].set(_cayley_at(k + 1, pairs_next, _hat(x) / 2, F))
        # The mismatch at h^(k+1), with the coefficients of h^k not yet set.
        F_next = jax.lax.dynamic_index_in_dim(F, k + 1, keepdims=False)
        y_next = jax.lax.dynamic_index_in_dim(ys, k + 1, keepdims=False)
        R = jnp.einsum("ij,iba,jbc->ac", pairs_next, Ps, F)
        a = jnp.where(moving, (y_next - F_next.T @ y) @ velocity / safe_speed2, 0.0)
        rotation = -_vee(R - R.T) / 2 - a * spin_axis
        b = jnp.where(spinning, rotation @ y / safe_norm2, 0.0)
        # Even k ≥ 2 only: odd coefficients are zero, and (α₀, β₀) = (1, 0).
        update = (k % 2 == 0) & (k >= 2)
        a, b = jnp.where(update, a, 0.0), jnp.where(update, b, 0.0)
        shift = a * spin_axis + b * y  # x at h^(k+1), hence F (its coefficient there is X)
        x, F = x.at[k + 1].add(shift), F.at[k + 1].add(_hat(shift))
        return x, inner, F, alpha.at[k].add(a), beta.at[k].add(b)

    zeros = jnp.zeros((n, 3), dtype)
    alpha = jnp.zeros(n, dtype).at[0].set(1.0)
    F = jnp.zeros((n, 3, 3), dtype).at[0].set(eye)
    state = (zeros, zeros, F, alpha, jnp.zeros(n, dtype))
    *_, alpha, beta = jax.lax.fori_loop(0, n - 1, power, state)
    return alpha[: degree + 1], beta[: degree + 1]


def _polyval(coefficients, s):
    return sum(c * s**k for k, c in enumerate(coefficients))


def preprocessing(system: RigidBody, m: Float[Array, 3], h: Scalar, order: int):
    """`(α, β)` at step `h`: the modified moments `α I⁻¹ + β` truncated after `h^(order − 2)`."""
    inverse_inertia = jnp.linalg.inv(system.inertia_tensor.astype(m.dtype))
    return _at_step(inverse_inertia, m, h, order)


def _at_step(inverse_inertia, m, h, order: int):
    alpha, beta = modified_moments_series(inverse_inertia, m, order - 2)
    return _polyval(alpha, h), _polyval(beta, h)


def modified_principal_moments(moments: Float[Array, 3], m: Float[Array, 3], h, order: int):
    """The principal moments `1/(α/I_i + β)` of `modified_body` for a body with principal
    moments `moments`, prepared from `m` for step `h` (the batch kernel's per-run constants,
    `_kernels/_preprocessed.py`)."""
    alpha, beta = _at_step(jnp.diag(1 / moments), m, h, order)
    return 1 / (alpha / moments + beta)


def shared_modified_principal_moments(
    moments: Float[Array, 3], m0s: Float[Array, "B 3"], h, order: int
):
    """`modified_principal_moments` of every body of a batch that shares `moments`, fitted
    from `order/2` sample trajectories (`_preprocessed_shared.py`: why, and how)."""
    return fitted_principal_moments(modified_moments_series, moments, m0s, h, order)


def modified_body(system: RigidBody, alpha, beta) -> RigidBody:
    """The rigid body with inverse inertia `α I⁻¹ + β·Id` (same principal axes)."""
    inertia = jnp.asarray(system.inertia)
    alpha, beta = alpha.astype(inertia.dtype), beta.astype(inertia.dtype)
    if inertia.ndim == 1:
        return RigidBody(1 / (alpha / inertia + beta))
    eye = jnp.eye(3, dtype=inertia.dtype)
    modified = jnp.linalg.inv(alpha * jnp.linalg.inv(inertia) + beta * eye)
    return RigidBody((modified + modified.T) / 2)


class PreprocessedMoserVeselov(AbstractIntegrator):
    """Hairer–Vilmart's preprocessed DMV: orders 4, 6, 8, 10 for the free rigid body.

    For `lievi.RigidBody` on SO(3) (principal moments or a full tensor). Each step is one
    `MoserVeselov` step on the body with the modified inverse inertia
    `α(h) I⁻¹ + β(h)·Id`, whose series in `h²` (coefficients in the energy, the Casimir and
    the inertia) are cut after `h^(order − 2)` (module docstring: what is truncated and why
    it is the accurate choice). Symmetric; Casimir, energy and spatial momentum are kept to
    round-off (the modified body's energy `αH + βC/2` and `C` are DMV invariants, hence so
    is `H`). Differentiable (Newton by the implicit function theorem, the series by
    ordinary autodiff) and batched (`vmap`).

    **Arguments:**

    - `order`: 4, 6, 8 or 10 (the modified moments are cut after `h^(order − 2)`).
    - `method`: the inner `MoserVeselov` (its Newton tolerances).

    `α`, `β` depend on the step size and on the trajectory's invariants (truncated-series
    arithmetic in one pass over the powers of the step: ~9 µs per body at order 8, batched;
    a batch sharing one body fits them from `order/2` such computations, ~0.1–1.5 µs per
    body).
    `lievi.simulate` computes them once per run, for that run's `h` and `m0` (its set-up),
    so every step costs one DMV step, and an
    integrator prepared for another `h` is prepared anew rather than misused. Called
    directly, `step` computes them from the current momentum; `prepare(system, m0, h)`
    returns a copy that stores them, whose `step` then requires that `h` (an error
    otherwise, also under `jit`) and a state on the trajectory of `m0` (the same energy
    and Casimir; another momentum is reported as `RESULTS.invalid_input`).
    `equivalent_moser_veselov(system, m0, h)` returns the modified body itself.
    `lievi.simulate_batch` and `simulate` run it, on principal moments, on `MoserVeselov`'s
    batch kernel with each body's modified moments computed once, from its own `m0`, in the
    run's set-up (`_kernels/_preprocessed.py`).
    """

    order_: int = eqx.field(static=True)
    method: MoserVeselov
    h_prepared: Array | None
    alpha: Array | None
    beta: Array | None
    invariants: Array | None = None

    def __init__(self, order: int = 6, method: MoserVeselov | None = None, *, _prepared=None):
        if isinstance(order, bool) or order not in ORDERS:
            raise ValueError(f"`order` must be one of {ORDERS}, got {order!r}.")
        method = MoserVeselov() if method is None else method
        if not isinstance(method, MoserVeselov):
            raise ValueError(f"`method` must be a lievi.MoserVeselov, got {type(method).__name__}.")
        self.order_ = order
        self.method = method
        prepared = _prepared or (None, None, None, None)
        self.h_prepared, self.alpha, self.beta = prepared[:3]
        # (Casimir |m0|², energy H(m0)): the trajectory the prepared moments belong to.
        self.invariants = prepared[3] if len(prepared) > 3 else None

    def order(self) -> int:
        return self.order_

    def own_step(self) -> bool:
        # The kernel computes this class's step, with the plain Moser–Veselov step inside.
        return type(self) is PreprocessedMoserVeselov and self.method.own_step()

    def kernels(self):
        # Plain DMV's kernel on each body's modified moments, prepared from its `m0`.
        return tuple(
            PreprocessedKernel(
                inner, modified_principal_moments, shared_modified_principal_moments, self.order_
            )
            for inner in self.method.kernels()
        )

    def is_symmetric(self) -> bool:
        # α and β are even in h and depend on the invariants H, C only, which the modified
        # DMV step keeps: the step is DMV (symmetric) for a body that does not depend on
        # the sign of h.
        return True

    def init(self, system: AbstractLieSystem, m0: Float[Array, 3], h):
        # The run's own `h` and `m0` (already checked by `simulate`): see `prepare`.
        _check_system(system)
        return self._prepared(system, m0, h)

    def prepare(
        self, system: AbstractLieSystem, m0: Float[Array, 3], h
    ) -> PreprocessedMoserVeselov:
        """A copy with `α(h)` and `β(h)` computed once for step `h` on the trajectory of `m0`."""
        _check_system(system)
        check_scalar("h", h, positive=True)
        system.check_momentum("m0", m0)
        dtype = state_dtype(system, m0, h)
        return self._prepared(system, jnp.asarray(m0, dtype), jnp.asarray(h, dtype))

    def _prepared(self, system, m0, h) -> PreprocessedMoserVeselov:
        alpha, beta = preprocessing(system, m0, h, self.order_)
        invariants = jnp.stack([jnp.dot(m0, m0), system.energy(m0)])
        return PreprocessedMoserVeselov(
            self.order_, self.method, _prepared=(h, alpha, beta, invariants)
        )

    def equivalent_moser_veselov(
        self, system: AbstractLieSystem, m0: Float[Array, 3], h
    ) -> tuple[RigidBody, MoserVeselov]:
        """`(body, method)`: plain DMV on `body` takes the same steps as this integrator
        prepared for `(system, m0, h)` — `body` has the modified inverse inertia
        `α(h) I⁻¹ + β(h)·Id`. So any fast path for `MoserVeselov` (e.g. the batched one of
        `lievi.simulate_batch`, with `jax.vmap` over `m0` and `system_axis=0`) runs the
        preprocessed method at the cost of plain DMV."""
        prepared = self.prepare(system, m0, h)
        return modified_body(system, prepared.alpha, prepared.beta), self.method

    def step(self, system: AbstractLieSystem, g, m, h: Scalar, force=None, t: Scalar = 0.0):
        _check_system(system)
        if force is not None:
            raise ValueError(
                "`forcing`: PreprocessedMoserVeselov is exact to its order for the free rigid "
                "body only (its preprocessing uses the free body's energy and Casimir). Use "
                "`lievi.Composition(lievi.MoserVeselov(), order)` or `lievi.DEP()` with forcing."
            )
        if self.alpha is None:
            alpha, beta = preprocessing(system, m, h, self.order_)
        else:
            # The prepared moments belong to one step size: a different `h` would silently
            # give a low-order step, so it is an error, also under `jit`.
            h = eqx.error_if(
                jnp.asarray(h, m.dtype),
                jnp.abs(h - self.h_prepared) > 1e-12 * jnp.abs(self.h_prepared),
                "PreprocessedMoserVeselov was prepared for another step size `h`: call "
                "`.prepare(system, m0, h)` with the `h` you simulate with.",
            )
            alpha, beta = self.alpha.astype(m.dtype), self.beta.astype(m.dtype)
        g_next, m_next, info = self.method.step(modified_body(system, alpha, beta), g, m, h)
        if self.alpha is None:
            return g_next, m_next, info
        result = jnp.where(self._prepared_for(system, m), info.result, RESULTS.invalid_input)
        return g_next, m_next, StepInfo(result, info.iterations, info.residual)

    def _prepared_for(self, system, m):
        """Whether the prepared moments belong to this state: a valid prepared `h`, and
        the Casimir and energy of `m` equal those of the prepared `m0` (DMV keeps both to
        round-off; √ε relative allows for their drift over very long runs). Another
        momentum would silently give a low-order step."""
        valid_h = step_size_valid(self.h_prepared)
        if self.invariants is None:
            return valid_h
        tolerance = jnp.sqrt(jnp.finfo(m.dtype).eps)
        casimir, energy = self.invariants.astype(m.dtype)
        same_casimir = jnp.abs(jnp.dot(m, m) - casimir) <= tolerance * casimir
        same_energy = jnp.abs(system.energy(m) - energy) <= tolerance * energy
        return valid_h & same_casimir & same_energy


def _check_system(system) -> None:
    if not isinstance(system, RigidBody):
        raise ValueError(
            "PreprocessedMoserVeselov integrates the free rigid body on SO(3) only: pass a "
            f"`lievi.RigidBody`, got {type(system).__name__}. For SO(n) use `lievi.MoserVeselov` "
            "or `lievi.Composition(lievi.MoserVeselov(), order)`."
        )
    if system.potential is not None:
        raise ValueError(
            "PreprocessedMoserVeselov is exact to its order for the free rigid body only (its "
            "preprocessing uses the free body's energy and Casimir): a system with a potential "
            "would run at order 2. Use `lievi.Composition(lievi.MoserVeselov(), order)` or "
            "`lievi.Composition(lievi.DEP(), order)`."
        )
