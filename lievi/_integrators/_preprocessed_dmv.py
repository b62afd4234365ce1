"""The preprocessed discrete Moser–Veselov algorithm (after Hairer & Vilmart 2006).

Hairer & Vilmart, J. Phys. A 39 (2006) 13225.

Why a modified step and one extra rotation suffice (our derivation; the tests check the
order, not this argument). The DMV step of `lievi.MoserVeselov` on the free rigid body
keeps the Casimir `C = |y|²` *and* the energy `H = ½ yᵀI⁻¹y` exactly (the tests check it),
is symplectic on `T*SO(3)` and commutes with left rotations `Q ↦ RQ`. On each invariant
torus of the (integrable) rigid body it is therefore a translation in the angle variables:
it is the time-1 flow of a Hamiltonian `S_h(H, C)`, that is

    DMV_h(Q, y) = (Q · P(τ) · exp(ρ ŷ₁), y(τ)),       y₁ = y(τ),

the exact flow over a modified time `τ = h + c₂h² + c₃h³ + …` (the flow of `H`) followed by
a rotation of the attitude about the body momentum by the angle `ρ|y|` (the flow of `C`);
`τ` and `ρ` depend only on `(h, H, C)`. Here `y(t)` is the exact momentum and `P(t)` the
exact body propagator, `Ṗ = P Ω̂`, `P(0) = I`. (In Hairer–Vilmart's terms: DMV is the exact
solution of a rigid body with modified moments of inertia, which is the same thing since
DMV with moments `I/α` and step `h` is DMV with moments `I` and step `αh`.)

Preprocessing. Run DMV with the step `h'` solving `τ(h') = h` (equivalently, moments
`I·h/h'`) and undo the rotation: `Q_{k+1} = Q_k F_k exp(−ρ(h') ŷ_{k+1})`. With `τ` and `ρ`
truncated after the power `h^p`, the local error is `O(h^{p+1})`: order `p`.

How `τ` and `ρ` are obtained: by truncated power series in the DMV step `s`, computed in
JAX at run time (so they are differentiable in the momentum, the inertia and `h`, and
batch under `vmap`): the Taylor coefficients of the DMV step `(F(s), y₁(s))` follow from
its Cayley-form equation `I x = s·vee((1 − X/2)Ŷ(1 + X/2))` by fixed-point iteration on
series (each sweep fixes one more power), those of the exact flow from the recurrences
`(k+1) y_{k+1} = Σ_j y_j × I⁻¹y_{k−j}`, `(k+1) P_{k+1} = Σ_j P_j (I⁻¹y_{k−j})^`; then
`c_k` is fixed power by power by projecting the mismatch of `y₁(s)` and `y(τ(s))` on `ẏ(0)`,
and `ρ` is read off `R = P(τ)ᵀF = exp(ρŷ₁)`: `y₁·vee(R − Rᵀ)/2 = |y| sin(ρ|y|)`.
`tools/derive_preprocessed_dmv.py` checks the time-rescaling structure symbolically (sympy).
The series depend only on `(h, H, C)`, so `prepare` computes them once per trajectory; the
step then costs one DMV step plus one small rotation.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._groups._so3 import SO3
from .._simulate import state_dtype
from .._systems._base import AbstractLieSystem
from .._systems._rigid_body import RigidBody
from ._base import AbstractIntegrator, StepInfo
from ._moser_veselov import MoserVeselov

ORDERS = (4, 6, 8, 10)


def _cauchy_mask(n: int) -> np.ndarray:
    """`mask[i, j, k] = 1` iff `i + j = k`: the Cauchy product of truncated series."""
    i, j, k = np.ogrid[:n, :n, :n]
    return (i + j == k).astype(float)


def _mul(a, b, mask, spec):
    """Truncated product of two series (leading axis = power of the variable)."""
    return jnp.einsum(f"i{spec[0]},j{spec[1]},ijk->k{spec[2]}", a, b, mask)


def _shift(a):
    """Multiply a series by the variable: coefficients move up one power."""
    return jnp.concatenate([jnp.zeros_like(a[:1]), a[:-1]])


def _hat(v):
    return SO3.hat(v)


def _vee(M):
    return jnp.stack([M[..., 2, 1], M[..., 0, 2], M[..., 1, 0]], axis=-1)


def dmv_series(inverse_inertia: Float[Array, "3 3"], y: Float[Array, "3"], degree: int):
    """Taylor coefficients in the step `s` of the DMV step: `(F(s), y₁(s))`, degree `degree`.

    `F = cay(x)`, `I x = s·vee((1 − X/2) Ŷ (1 + X/2))`, `y₁ = Fᵀy` (as in `MoserVeselov`).
    """
    n = degree + 1
    mask = jnp.asarray(_cauchy_mask(n), y.dtype)
    eye = jnp.eye(3, dtype=y.dtype)
    Y = _hat(y)
    x = jnp.zeros((n, 3), y.dtype)
    for _ in range(degree):  # each sweep fixes one more power of s
        X = _hat(x)
        left = eye[None] * (jnp.arange(n) == 0)[:, None, None] - X / 2
        right = eye[None] * (jnp.arange(n) == 0)[:, None, None] + X / 2
        middle = jnp.einsum("kab,bc->kac", left, Y)
        inner = _mul(middle, right, mask, ("ab", "bc", "ac"))
        x = _shift(jnp.einsum("ab,kb->ka", inverse_inertia, _vee(inner)))
    X = _hat(x)
    one = eye[None] * (jnp.arange(n) == 0)[:, None, None]
    # (1 − X/2) F = 1 + X/2  ⇔  F = 1 + X/2 + (X/2) F: one more power per sweep.
    F = one
    for _ in range(degree):
        F = one + X / 2 + _mul(X / 2, F, mask, ("ab", "bc", "ac"))
    y1 = jnp.einsum("kba,b->ka", F, y)
    return F, y1


def exact_series(inverse_inertia: Float[Array, "3 3"], y: Float[Array, "3"], degree: int):
    """Taylor coefficients in `t` of the exact `y(t)` (Euler) and `P(t)` (`Ṗ = PΩ̂`)."""
    ys = [y]
    Ps = [jnp.eye(3, dtype=y.dtype)]
    for k in range(degree):
        omegas = [inverse_inertia @ yj for yj in ys]
        ys.append(sum(jnp.cross(ys[j], omegas[k - j]) for j in range(k + 1)) / (k + 1))
        Ps.append(sum(Ps[j] @ _hat(omegas[k - j]) for j in range(k + 1)) / (k + 1))
    return jnp.stack(ys), jnp.stack(Ps)


def _compose(coefficients, tau, mask, spec):
    """`Σ_k a_k τ(s)^k` for a series `τ` with `τ_0 = 0`, truncated."""
    result = jnp.zeros_like(coefficients)
    power = jnp.zeros_like(tau).at[0].set(1.0)
    for k in range(coefficients.shape[0]):
        result = result + jnp.einsum(f"i,{spec}->i{spec}", power, coefficients[k])
        power = _mul(power, tau, mask, ("", "", ""))
    return result


def modification_series(inverse_inertia, y, degree: int):
    """`(τ, S)`: series in the DMV step `s` of the exact-flow time `τ(s)` of one DMV step,
    and of `S(s) = y₁·vee(R − Rᵀ)/2 = |y| sin(ρ|y|)`, `R = P(τ)ᵀF` (module docstring)."""
    n = degree + 1
    mask = jnp.asarray(_cauchy_mask(n), y.dtype)
    F, y1 = dmv_series(inverse_inertia, y, degree)
    ys, Ps = exact_series(inverse_inertia, y, degree)
    velocity = ys[1]
    speed2 = jnp.dot(velocity, velocity)
    # At a relative equilibrium (ẏ = 0) τ is not determined by y: take τ = s there; the
    # rotation ρ then accounts for the whole attitude error (double `where`: safe gradients).
    moving = speed2 > 1e3 * jnp.finfo(y.dtype).tiny
    safe_speed2 = jnp.where(moving, speed2, 1.0)
    tau = jnp.zeros(n, y.dtype).at[1].set(1.0)
    for k in range(2, n):
        mismatch = y1[k] - _compose(ys, tau, mask, "a")[k]
        tau = tau.at[k].set(jnp.where(moving, jnp.dot(mismatch, velocity) / safe_speed2, 0.0))
    P_tau = _compose(Ps, tau, mask, "ab")
    R = _mul(jnp.swapaxes(P_tau, 1, 2), F, mask, ("ab", "bc", "ac"))
    axis = _vee(R - jnp.swapaxes(R, 1, 2)) / 2
    S = _mul(y1, axis, mask, ("a", "a", ""))
    return tau, S


def _polyval(coefficients, s):
    return sum(c * s**k for k, c in enumerate(coefficients))


def preprocessing(system: RigidBody, m: Float[Array, "3"], h: Scalar, order: int):
    """`(h', φ)`: the DMV step `h'` with `τ(h') = h` and the correction angle `φ = ρ(h')|y|`,
    with `τ`, `S` truncated after `h^order`."""
    inverse_inertia = jnp.linalg.inv(system.inertia_tensor.astype(m.dtype))
    tau, S = modification_series(inverse_inertia, m, order)
    # Newton on τ(h') = h from h' = h: τ(s) = s + O(s²), a few iterations reach round-off.
    dtau = tau[1:] * jnp.arange(1, order + 1)
    h_mod = h
    for _ in range(6):
        h_mod = h_mod - (_polyval(tau, h_mod) - h) / _polyval(dtau, h_mod)
    norm = jnp.sqrt(jnp.dot(m, m))
    safe_norm = jnp.where(norm > 0, norm, 1.0)
    angle = jnp.where(norm > 0, jnp.arcsin(jnp.clip(_polyval(S, h_mod) / safe_norm, -1, 1)), 0.0)
    return h_mod, angle


class PreprocessedMoserVeselov(AbstractIntegrator):
    """DMV with a preprocessed step size and an attitude correction: orders 4, 6, 8, 10.

    For the free rigid body on SO(3) (`lievi.RigidBody`, principal moments or a full
    tensor). Each step is one `MoserVeselov` step with the modified step `h'` (equivalently,
    modified moments of inertia `I·h/h'`, Hairer–Vilmart's preprocessing), followed by a
    rotation of the attitude about the new body momentum by `−φ` (see the module
    docstring). `h'` and `φ` depend only on `h`, the energy and the Casimir, which DMV keeps
    exactly; Casimir, energy and spatial momentum are kept to round-off. Differentiable
    (Newton by the implicit function theorem, the series by ordinary autodiff) and batched.

    **Arguments:**

    - `order`: 4, 6, 8 or 10 (where the series for `h'` and `φ` are cut).
    - `method`: the inner `MoserVeselov` (its Newton tolerances).

    `step` computes `h'` and `φ` from the current momentum (a few thousand flops). For long
    runs call `prepare(system, m0, h)` once: it returns a copy that stores them, and whose
    step then costs one DMV step and one 3×3 rotation. A prepared integrator must be used
    with that same `h` (and on the trajectory of `m0`, or any state with the same energy
    and Casimir).
    """

    order_: int = eqx.field(static=True)
    method: MoserVeselov
    h_prepared: Array | None
    h_modified: Array | None
    angle: Array | None

    def __init__(self, order: int = 6, method: MoserVeselov | None = None, *, _prepared=None):
        if isinstance(order, bool) or order not in ORDERS:
            raise ValueError(f"`order` must be one of {ORDERS}, got {order!r}.")
        method = MoserVeselov() if method is None else method
        if not isinstance(method, MoserVeselov):
            raise ValueError(f"`method` must be a lievi.MoserVeselov, got {type(method).__name__}.")
        self.order_ = order
        self.method = method
        self.h_prepared, self.h_modified, self.angle = _prepared or (None, None, None)

    def order(self) -> int:
        return self.order_

    def is_symmetric(self) -> bool:
        # h' and φ are odd in h (τ and ρ are), and depend on conserved quantities only.
        return True

    def prepare(
        self, system: AbstractLieSystem, m0: Float[Array, "3"], h
    ) -> PreprocessedMoserVeselov:
        """A copy with `h'` and `φ` computed once for step `h` on the trajectory of `m0`."""
        _check_system(system)
        system.check_momentum("m0", m0)
        dtype = state_dtype(system, m0, h)
        m0, h = jnp.asarray(m0, dtype), jnp.asarray(h, dtype)
        h_mod, angle = preprocessing(system, m0, h, self.order_)
        return PreprocessedMoserVeselov(self.order_, self.method, _prepared=(h, h_mod, angle))

    def step(self, system: AbstractLieSystem, g, m, h: Scalar):
        _check_system(system)
        if self.h_modified is None:
            h_mod, angle = preprocessing(system, m, h, self.order_)
        else:
            # The prepared series belong to one step size: a different `h` would silently
            # give a low-order (wrong-time) step, so it is an error, also under `jit`.
            h = eqx.error_if(
                jnp.asarray(h, m.dtype),
                jnp.abs(h - self.h_prepared) > 1e-12 * jnp.abs(self.h_prepared),
                "PreprocessedMoserVeselov was prepared for another step size `h`: call "
                "`.prepare(system, m0, h)` with the `h` you simulate with.",
            )
            h_mod, angle = self.h_modified.astype(m.dtype), self.angle.astype(m.dtype)
            h_mod = h_mod + 0 * h  # keeps the check in the computation graph
        g_next, m_next, info = self.method.step(system, g, m, h_mod)
        norm = jnp.sqrt(jnp.dot(m_next, m_next))
        safe_norm = jnp.where(norm > 0, norm, 1.0)
        g_next = g_next @ SO3.exp(-angle * m_next / safe_norm)
        return g_next, m_next, StepInfo(info.result, info.iterations, info.residual)


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


