"""Modified moments of inertia of the DMV step, in exact rational arithmetic (no sympy).

Run: `python tools/derive_preprocessed_dmv.py [I1 I2 I3]` (moments as fractions, default
`3/5 4/5 1`, the Hairer–Vilmart body; ~15 s of CPU, standard library only).

It derives, independently of the JAX code in `lievi/_integrators/_preprocessed_dmv.py`,
the series behind `lievi.PreprocessedMoserVeselov` (Hairer & Vilmart, J. Phys. A 39 (2006)
13225): the inverse inertia `Î⁻¹(h) = α(h) I⁻¹ + β(h)·Id` for which one DMV step of size
`h` is the exact rigid-body flow over `h` (momentum and attitude), and

1. checks the structure the method rests on, exactly (rational numbers, no round-off):
   at each power `h^(k+1)` the whole mismatch between the DMV step and the exact flow —
   three momentum and three attitude components — is removed by the two numbers
   `a_k, b_k` (the remaining four components vanish identically), and `a_k = b_k = 0` for
   odd `k` (symmetry);
2. shows that each coefficient is a homogeneous polynomial in the invariants
   `h²H` and `h²N`, `H = ½ yᵀI⁻¹y`, `N = ½|y|²`, as in Hairer–Vilmart: it fits the
   polynomial exactly on `k + 1` momenta and checks it on two more; prints it;
3. checks the `h²` terms against Hairer–Vilmart's closed forms
   `a₂ = tr(I)/(6 det I)·N − tr(I⁻¹)/3·H`, `b₂ = −N/(3 det I) + tr(I)/(6 det I)·H`;
4. cross-checks the floating-point coefficients of the library
   (`modified_moments_series`) against the exact ones (needs JAX; skipped without it);
5. prints, for comparison, the forward series `τ(s)` (the exact-flow time reached by one
   *plain* DMV step of size `s`): its coefficients grow fast, those of `α`, `β` do not —
   the reason the library truncates the modified moments.

Conventions of `lievi.MoserVeselov`: `F = cay(x)`, `x = h Î⁻¹ vee((1 − X/2)Ŷ(1 + X/2))`,
`y₁ = Fᵀy`, `Q₁ = QF`. Exact flow: `ẏ = y × I⁻¹y`, `Ṗ = P (I⁻¹y)^`, `P(0) = Id`.
"""

from __future__ import annotations

import sys
from fractions import Fraction as Q

DEGREE = 9  # powers of h matched: enough for a₂ … a₈ (order 10)


# ---- 3-vectors and 3×3 matrices of Fractions ------------------------------------------
def zeros3():
    return [Q(0)] * 3


def zeros33():
    return [[Q(0)] * 3 for _ in range(3)]


def eye33():
    return [[Q(int(i == j)) for j in range(3)] for i in range(3)]


def add(a, b):
    if isinstance(a[0], list):
        return [add(r, s) for r, s in zip(a, b)]
    return [x + y for x, y in zip(a, b)]


def scale(c, a):
    if isinstance(a[0], list):
        return [scale(c, r) for r in a]
    return [c * x for x in a]


def matmul(A, B):
    return [[sum(A[i][k] * B[k][j] for k in range(3)) for j in range(3)] for i in range(3)]


def matvec(A, v):
    return [sum(A[i][k] * v[k] for k in range(3)) for i in range(3)]


def transpose(A):
    return [[A[j][i] for j in range(3)] for i in range(3)]


def hat(v):
    return [[Q(0), -v[2], v[1]], [v[2], Q(0), -v[0]], [-v[1], v[0], Q(0)]]


def vee(M):
    return [M[2][1], M[0][2], M[1][0]]


def cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def dot(a, b):
    return sum(x * y for x, y in zip(a, b))


def cauchy(a, b, k, product):
    """Coefficient `k` of the product of two series (lists of coefficients)."""
    terms = [product(a[i], b[k - i]) for i in range(k + 1) if i < len(a) and k - i < len(b)]
    total = terms[0]
    for t in terms[1:]:
        total = add(total, t)
    return total


# ---- exact flow ------------------------------------------------------------------------
def exact_series(A, y, degree):
    """Taylor coefficients of `y(t)` and `P(t)`."""
    ys, Ps = [y], [eye33()]
    for k in range(degree):
        omegas = [matvec(A, yj) for yj in ys]
        ys.append(scale(Q(1, k + 1), cauchy(ys, omegas, k, cross)))
        Ps.append(scale(Q(1, k + 1), cauchy(Ps, [hat(w) for w in omegas], k, matmul)))
    return ys, Ps


# ---- one DMV step as a series in h, power by power --------------------------------------
class DMVSeries:
    """Coefficients of `x(h)`, `F(h) = cay(x)`, `y₁(h) = Fᵀy` for a series-valued `Î⁻¹(h)`.

    `x_k` needs `Î⁻¹_{k−1}` and `x_{<k}` only (`x = h Î⁻¹ v`, `v = vee((1 − X/2)Ŷ(1 + X/2))`,
    `v_j` needs `x_{≤j}`), so the series are built one power at a time while the
    coefficients of `Î⁻¹` are being determined.
    """

    def __init__(self, y):
        self.y, self.Y = y, hat(y)
        self.M, self.x, self.v, self.F = [], [zeros3()], [], [eye33()]

    def v_coefficient(self, j):
        # (1 − X/2) Ŷ (1 + X/2) = Ŷ + ½(ŶX − XŶ) − ¼ XŶX, at power j (X_0 = 0).
        X = [hat(xi) for xi in self.x]
        half = Q(1, 2)
        total = self.Y if j == 0 else zeros33()
        if j >= 1:
            total = add(
                total, scale(half, add(matmul(self.Y, X[j]), scale(-1, matmul(X[j], self.Y))))
            )
        for i in range(1, j):
            total = add(total, scale(-Q(1, 4), matmul(matmul(X[i], self.Y), X[j - i])))
        return vee(total)

    def extend(self, M_next):
        """Append `Î⁻¹_{k−1} = M_next` and compute `x_k`, `F_k`; return `k`."""
        self.M.append(M_next)
        k = len(self.x)
        self.v.append(self.v_coefficient(k - 1))
        self.x.append(cauchy(self.M, self.v, k - 1, matvec))
        self.F.append(self.F_coefficient(k))
        return k

    def F_coefficient(self, k):
        # (1 − X/2) F = 1 + X/2:  F_k = X_k/2 + ½ Σ_{j=1..k} X_j F_{k−j}  (F_0 = Id).
        X = [hat(xi) for xi in self.x]
        total = scale(Q(1, 2), X[k])
        for j in range(1, k + 1):
            total = add(total, scale(Q(1, 2), matmul(X[j], self.F[k - j])))
        return total

    def y1(self, k):
        return matvec(transpose(self.F[k]), self.y)


def modified_moments(I, y, degree=DEGREE):
    """Exact `a_k, b_k` (k = 0 … degree − 1) with the structure checks of the docstring."""
    A = [[Q(int(i == j)) / I[i] for j in range(3)] for i in range(3)]
    ys, Ps = exact_series(A, y, degree + 1)
    velocity, Ay = ys[1], matvec(A, y)
    dmv = DMVSeries(y)
    dmv.extend(A)  # Î⁻¹_0 = I⁻¹  →  x_1
    a, b = [Q(1)], [Q(0)]
    for k in range(1, degree):
        # Tentative Î⁻¹_k = 0; its effect on x_{k+1} is + (a_k I⁻¹y + b_k y).
        trial = DMVSeries(y)
        for M in dmv.M:
            trial.extend(M)
        trial.extend(zeros33())
        mismatch_y = add(ys[k + 1], scale(-1, trial.y1(k + 1)))
        R = cauchy([transpose(P) for P in Ps], trial.F, k + 1, matmul)
        a_k = dot(mismatch_y, velocity) / dot(velocity, velocity)
        # The whole momentum mismatch must be a_k ẏ(0):
        assert add(mismatch_y, scale(-a_k, velocity)) == zeros3(), f"momentum at h^{k + 1}"
        # R_{k+1} + (a_k I⁻¹y + b_k y)^ = 0, and R_{k+1} has no symmetric part:
        assert add(R, transpose(R)) == zeros33(), f"symmetric attitude mismatch at h^{k + 1}"
        rotation = add(scale(-1, vee(R)), scale(-a_k, Ay))
        b_k = dot(rotation, y) / dot(y, y)
        assert add(rotation, scale(-b_k, y)) == zeros3(), f"attitude at h^{k + 1}"
        a.append(a_k)
        b.append(b_k)
        dmv.extend(add(scale(a_k, A), scale(b_k, eye33())))
    assert all(c == 0 for c in a[1::2] + b[1::2]), "odd powers must vanish"
    return a, b, (ys, A)


def tau_series(I, y, degree=DEGREE):
    """Forward series `τ(s)`: plain DMV of step `s` reaches the exact momentum at time τ."""
    A = [[Q(int(i == j)) / I[i] for j in range(3)] for i in range(3)]
    ys, _ = exact_series(A, y, degree)
    dmv = DMVSeries(y)
    for _ in range(degree):
        dmv.extend(A if not dmv.M else zeros33())
    velocity = ys[1]
    tau = [Q(0), Q(1)]
    for k in range(2, degree + 1):
        # y(τ(s)) at s^k with τ_k = 0, then τ_k from the projection on ẏ(0).
        composed = zeros3()
        power = [Q(1)]  # τ(s)^j, truncated
        for j in range(k + 1):
            if j > 0:
                power = [
                    sum(
                        power[i] * tau[m - i]
                        for i in range(m + 1)
                        if i < len(power) and m - i < len(tau)
                    )
                    for m in range(k + 1)
                ]
            if k < len(power):
                composed = add(composed, scale(power[k], ys[j]))
        mismatch = add(dmv.y1(k), scale(-1, composed))
        tau.append(dot(mismatch, velocity) / dot(velocity, velocity))
    return tau


def invariants(I, y):
    H = sum(yi * yi / Ii for yi, Ii in zip(y, I)) / 2
    N = dot(y, y) / 2
    return H, N


def solve(matrix, rhs):
    """Exact Gaussian elimination."""
    n = len(rhs)
    M = [row[:] + [r] for row, r in zip(matrix, rhs)]
    for c in range(n):
        p = next(r for r in range(c, n) if M[r][c] != 0)
        M[c], M[p] = M[p], M[c]
        for r in range(n):
            if r != c and M[r][c] != 0:
                f = M[r][c] / M[c][c]
                M[r] = [u - f * v for u, v in zip(M[r], M[c])]
    return [M[i][n] / M[i][i] for i in range(n)]


SAMPLES = [(18, 4, -9), (1, 2, 3), (3, -1, 2), (2, 5, -1), (-4, 1, 1), (1, 1, -2), (5, 3, 2)]


def main():
    I = [Q(s) for s in sys.argv[1:4]] if len(sys.argv) > 1 else [Q(3, 5), Q(4, 5), Q(1)]
    print(f"I = ({', '.join(str(i) for i in I)})")
    runs = []
    for sample in SAMPLES:
        y = [Q(c, 10) for c in sample]
        a, b, _ = modified_moments(I, y)
        runs.append((invariants(I, y), a, b))
    print(f"structure checked exactly on {len(SAMPLES)} momenta up to h^{DEGREE}: ok")

    # 2. homogeneous polynomials in (h²H, h²N): fit on k + 1 momenta, check on the rest.
    for name, index in (("α", 1), ("β", 2)):
        for k in range(1, (DEGREE - 1) // 2 + 1):
            rows = [[H**j * N ** (k - j) for j in range(k + 1)] for (H, N), *_ in runs]
            values = [run[index][2 * k] for run in runs]
            coefficients = solve(rows[: k + 1], values[: k + 1])
            for row, value in zip(rows[k + 1 :], values[k + 1 :]):
                assert sum(c * r for c, r in zip(coefficients, row)) == value, (name, k)
            terms = " + ".join(
                f"({float(c):+.10g}) H^{j} N^{k - j}" for j, c in enumerate(coefficients)
            )
            print(f"{name}: h^{2 * k} coefficient = {terms}")
    print(
        f"homogeneous polynomials in (H, N), checked on {len(SAMPLES) - (DEGREE - 1) // 2 - 1}+ extra momenta: ok"
    )

    # 3. the h² terms against Hairer–Vilmart's closed forms.
    trace, det = sum(I), I[0] * I[1] * I[2]
    trace_inverse = sum(1 / i for i in I)
    for (H, N), a, b in runs:
        assert a[2] == trace / (6 * det) * N - trace_inverse / 3 * H
        assert b[2] == -N / (3 * det) + trace / (6 * det) * H
    print("h² terms equal Hairer–Vilmart's closed forms: ok")

    (H, N), a, b = runs[0]
    print("at y = (1.8, 0.4, -0.9):")
    print("  α:", ", ".join(f"{float(c):.9g}" for c in a[::2]))
    print("  β:", ", ".join(f"{float(c):.9g}" for c in b[::2]))
    tau = tau_series(I, [Q(c, 10) for c in SAMPLES[0]], DEGREE + 2)
    print("  τ (plain DMV, forward):", ", ".join(f"{float(c):.6g}" for c in tau[1::2]))

    # 4. the library's floating-point coefficients.
    try:
        import jax

        jax.config.update("jax_enable_x64", True)
        import jax.numpy as jnp

        from lievi._integrators._preprocessed_dmv import modified_moments_series
    except ImportError:
        print("JAX/lievi not importable: library cross-check skipped")
        return
    worst = 0.0
    for sample, ((H, N), a, b) in zip(SAMPLES, runs):
        inverse_inertia = jnp.diag(jnp.array([1 / float(i) for i in I]))
        alpha, beta = modified_moments_series(inverse_inertia, jnp.array(sample) / 10.0, DEGREE - 1)
        for lib, exact in ((alpha, a), (beta, b)):
            for c_lib, c_exact in zip(lib, exact):
                worst = max(
                    worst, abs(float(c_lib) - float(c_exact)) / max(1.0, abs(float(c_exact)))
                )
    print(f"library (float64) vs exact coefficients: max relative difference {worst:.1e}")
    assert worst < 1e-12


if __name__ == "__main__":
    main()
