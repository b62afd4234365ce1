"""Backward error analysis of the discrete Moser–Veselov (DMV) step on SO(3), in sympy.

Run: `python tools/derive_preprocessed_dmv.py [N]` (needs sympy, a dev-only tool; N = the
highest power of h kept, default 5; N = 5 takes ~4 min on one core). It checks, with
symbolic moments and initial value, that one DMV step is the exact flow over a modified
time `τ(h)` to the order kept — the structure `lievi/_integrators/_preprocessed_dmv.py` relies on — and
prints `c₃, c₅` of `τ = h + c₃h³ + c₅h⁵ + …`. (The library computes these series
numerically in JAX at run time, including the attitude rotation `ρ` below, whose symbolic
check is not part of this script; the tests check the resulting orders.)

Why the modification is a time rescaling and a rotation about the momentum. DMV preserves
the Casimir C = |y|² and the energy H = ½ Σ y_k²/I_k exactly (checked numerically and in the
tests) and is a symplectic map of T*SO(3) that commutes with the left SO(3) action. On
each invariant torus it is therefore a translation in the angle variables: it is the time-1
flow of a Hamiltonian S_h(H, C), i.e. the exact rigid-body flow over a time τ(h; H, C)
followed by the flow of C, a rotation of the attitude about the body momentum by an angle
that again depends only on (h, H, C):

    DMV_h(Q, y) = (Q P(τ) exp(ρ ŷ₁), y(τ)),   τ = h + c₃h³ + c₅h⁵ + …,   ρ = ρ₃h³ + ρ₅h⁵ + …,

where y(t) is the exact momentum and P(t) the exact body propagator (Ṗ = P Ω̂, P(0) = I).
This script computes c_k by expanding both sides in h at a symbolic initial value
y = (y1, y2, y3) with symbolic inverse moments a_k = 1/I_k, and checks that the expansion is
consistent (the residual of the ansatz vanishes identically in all three components: the
structure is confirmed, not assumed). Running DMV with the step h' solving τ(h') = h, and undoing the rotation by
ρ(h'), then gives the exact flow up to the truncation of the series.

Conventions of `lievi.MoserVeselov` (NOTES §1): F = cay(x) = Ωᵀ with I x = h·vee((1 − X/2)Ŷ(1 + X/2)),
y₁ = Fᵀ y, Q₁ = Q F. Exact: ẏ = y × Ω, Ω = A y (A = diag(a)), Ṗ = P Ω̂.
"""

import sys
import time

import sympy as sp

N = int(sys.argv[1]) if len(sys.argv) > 1 else 5
h = sp.Symbol("h")
y = sp.Matrix(sp.symbols("y1 y2 y3"))
a = sp.symbols("a1 a2 a3")  # inverse principal moments 1/I_k
A = sp.diag(*a)
Id = sp.eye(3)


def hat(v):
    return sp.Matrix([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def vee(M):
    return sp.Matrix([M[2, 1], M[0, 2], M[1, 0]])


def trunc(e, order=N):
    """Drop powers of h above `order` (e is a polynomial in h)."""
    e = sp.expand(e)
    return sum(e.coeff(h, k) * h**k for k in range(order + 1))


def truncm(M, order=N):
    return M.applyfunc(lambda e: trunc(e, order))


t0 = time.time()
# --- DMV: x = h A vee((1 − X/2) Ŷ (1 + X/2)) by fixed-point iteration (one order per sweep).
x = sp.zeros(3, 1)
for _ in range(N):
    X = hat(x)
    x = truncm(h * A * vee((Id - X / 2) * hat(y) * (Id + X / 2)))
X = hat(x)
# cay(x) = (1 − X/2)⁻¹(1 + X/2), (1 − X/2)⁻¹ = Σ (X/2)^k (X = O(h)).
inv = Id
power = Id
for _ in range(N):
    power = truncm(power * X / 2)
    inv = inv + power
F = truncm(inv * (Id + X / 2))
y1 = truncm(F.T * y)
print(f"DMV expanded to h^{N} in {time.time() - t0:.1f}s", file=sys.stderr)


# --- Exact flow: Taylor coefficients by repeated Lie derivatives along ẏ = y × Ay.
def lie(e):
    """d/dt of a polynomial expression in y along the Euler vector field."""
    f = y.cross(A * y)
    return sp.expand(sum(sp.diff(e, y[i]) * f[i] for i in range(3)))


ys = [y]  # y^(k)(0)
for _ in range(N):
    ys.append(ys[-1].applyfunc(lie))
print(f"exact Taylor series in {time.time() - t0:.1f}s", file=sys.stderr)

# --- Match y₁ = y(τ) with τ = h + Σ c_k h^k (odd k): solve order by order.
cs = {k: sp.Symbol(f"c{k}") for k in range(3, N + 1, 2)}
tau = h + sum(c * h**k for k, c in cs.items())
tau_powers = [sp.Integer(1)]
for _ in range(N):
    tau_powers.append(trunc(tau_powers[-1] * tau))
y_tau = sum((tau_powers[k] / sp.factorial(k) * ys[k] for k in range(N + 1)), sp.zeros(3, 1))
y_tau = truncm(y_tau)
solution = {}
velocity = ys[1]
for k in range(1, N + 1):
    residual = (y1 - y_tau).applyfunc(lambda e: sp.expand(e.coeff(h, k).subs(solution)))
    if k in cs:
        # residual = r − c_k y'(0): project on y'(0), then check the rest vanishes.
        c = sp.Symbol(f"c{k}")
        r0 = residual.subs(c, 0)
        # The coefficient of c_k is −y'(0); pick c_k from the first component where y'_i ≠ 0.
        value = sp.cancel(r0[0] / velocity[0])
        solution[c] = value
        residual = residual.subs(c, value).applyfunc(sp.cancel)
    assert all(sp.simplify(e) == 0 for e in residual), f"ansatz fails for y at order h^{k}"
    print(f"y matched at h^{k} ({time.time() - t0:.1f}s)", file=sys.stderr)

c_values = {k: sp.factor(solution[cs[k]]) for k in cs}

print(f"done in {time.time() - t0:.1f}s", file=sys.stderr)
for k, v in c_values.items():
    print(f"c{k} =", v)
# Cross-check with the run-time series of lievi/_integrators/_preprocessed_dmv.py (`modification_series`):
# on the Hairer–Vilmart body I = (0.6, 0.8, 1), y = (1.8, 0.4, −0.9) it gives c₃ = 2.43013889,
# c₅ = 11.8982886.
point = {a[0]: 1 / sp.Rational(6, 10), a[1]: 1 / sp.Rational(8, 10), a[2]: 1}
point.update({y[0]: sp.Rational(18, 10), y[1]: sp.Rational(4, 10), y[2]: sp.Rational(-9, 10)})
for k, v in c_values.items():
    print(f"c{k} at the Hairer–Vilmart point = {float(v.subs(point)):.9g}")
