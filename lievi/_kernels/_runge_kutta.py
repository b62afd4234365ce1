"""Explicit Runge–Kutta tableaux, and one step of an explicit method in a chart.

The Lie-group Runge–Kutta methods (`lievi/_integrators/_rkmk.py`) run a classical
explicit method on `(u, m)`, `u` the Lie-algebra coordinate of the exponential chart about
the step's start. The tableau is the only thing that differs between the methods of
order 4, 5 and 8, and it is used here only: by `rk_in_the_chart` (the stages unrolled, for
the fast kernels on tuples of `(B,)` arrays, whose stages XLA fuses) and by
`rk_in_the_chart_looped` (the stages in a loop, for the generic step on arrays, whose
stage is compiled once).

The coefficients are the published ones:
- `CLASSICAL_RK4`: Kutta's classical method (order 4, 4 stages);
- `DORMAND_PRINCE5`: the order-5 solution of Dormand & Prince's 5(4) pair (J. Comput.
  Appl. Math. 6, 1980; 6 stages, the seventh being only for its error estimate);
- `DOP853`: the order-8 solution of Hairer's DOP853 (Prince & Dormand's order-8 method
  with Hairer's 5- and 3-order estimators; Hairer–Nørsett–Wanner, *Solving ODEs I*,
  §II.10; 12 stages).

`imaginary_stability` is the end of the segment `[0, y]` of the imaginary axis on which
the stability polynomial `R(iy)` has `|R| ≤ 1` (the test computes it from the tableau):
rotation at rate `|ω|` is stepped without growth while `h|ω| ≤ y`.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp


@dataclasses.dataclass(frozen=True)
class ButcherTableau:
    """An explicit tableau: `a[i]` the `i` coefficients of stage `i` (row 0 empty), `b` the
    weights. Hashable (kernels hold it as a static field)."""

    order: int
    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    imaginary_stability: float

    @property
    def c(self) -> tuple[float, ...]:
        """The nodes, `c[i] = Σ_j a[i][j]` (the stage times `t_k + c_i h`)."""
        return tuple(float(sum(row)) for row in self.a)

    @property
    def dexpinv_degree(self) -> int:
        """The last power of `ad_u` kept of `dexp⁻¹_u`'s commutator series when this
        tableau runs in the exponential chart: `order`. Munthe-Kaas's bound is
        `order − 1` (the dropped terms are then `O(h^order)` in `u̇`, `u = O(h)`: the
        order is kept; Hairer–Lubich–Wanner, *Geometric Numerical Integration*, §IV.8.2);
        the `ad_u^order` term too keeps the error at the methods' largest steps that of the
        exact `dexp⁻¹` (`RKMK8`, HLW's free body, T = 2, h = 1, 0.5, 0.25: final errors
        1.15e-7, 4.7e-10, 1.9e-12 against the exact 1.11e-7, 4.7e-10, 1.9e-12; truncated
        after `ad_u⁷`, 2.25e-7, 4.0e-10, 1.3e-12). A stage is a polynomial in `u`, not
        two series and a division."""
        return self.order


def _combine(y, coefficients, increments):
    """`y + Σ c_j k_j` (`y = None`: without it) over the pytrees `increments`, skipping the
    zero coefficients (so a tableau's zeros cost nothing)."""
    terms = [(c, k) for c, k in zip(coefficients, increments) if c != 0]

    def leaf(y_leaf, *ks):
        total = sum(c * k for (c, _), k in zip(terms, ks))
        return total if y_leaf is None else y_leaf + total

    if y is None:
        return jax.tree.map(lambda *ks: leaf(None, *ks), *(k for _, k in terms))
    return jax.tree.map(leaf, y, *(k for _, k in terms))


def rk_in_the_chart(tableau: ButcherTableau, stage, m, store=None):
    """One step of the explicit method `tableau` on `(u, m)` from `u = 0`.

    `stage(u, m, c) = (h u̇, h ṁ)` at the stage `(u, m)` at time `t_k + c h` (`u = None`
    at the first stage, where `u = 0`); `u` and `m` any pytrees (a vector as an array, or
    a tuple of component arrays). `store`, if given, is applied to each stage's
    inputs and increments before anything reads them (the kernels pass `materialise`: every later
    stage reads every earlier one, and XLA's CPU fusion would otherwise recompute each
    stage inside each of its readers — exponential in the number of stages, measured as a
    compile that does not finish for DOP853's 12). Returns `(u_{k+1}, m_{k+1})`.

    Unrolled, not in a loop as `rk_in_the_chart_looped`: with the stages in a
    `lax.fori_loop` (the increments in `(stages, B)` arrays) DOP853's step for 64 bodies
    compiled in 2.0 s instead of 4.8 s, but ran at a quarter to a sixth of the
    body-steps/s for 64 bodies and half for 4096 (2-core CPU, loaded); with the stages
    stacked into `(6, B)` arrays, unrolled, it compiled no faster and ran at 0.6×.
    Measured again with the increments in `(stages, B)` arrays written by
    `dynamic_update_slice` and each input summed term by term (fused, no `tensordot`):
    the step for 64 bodies fell from 5,900 to 1,600 optimised HLO operations and compiled
    in 0.45 s instead of 2.7 s, but ran at 0.3–0.4× the body-steps/s at 64, 512 and 4096
    bodies; with only stages 5–11 rolled (and only the increments they read kept) 3,300
    operations, 0.45×; a rolled stage without the input sums still ran at 0.5× — the
    rolled stage itself, not the reads, is the cost (2-core CPU).
    """
    du, dm = [], []
    for row, c in zip(tableau.a, tableau.c):
        if not row:
            u_i, m_i = None, m
        else:
            u_i, m_i = _combine(None, row, du), _combine(m, row, dm)
            if store is not None:
                u_i, m_i = store(u_i, m_i)
        k_u, k_m = stage(u_i, m_i, c)
        if store is not None:
            k_u, k_m = store(k_u, k_m)
        du.append(k_u)
        dm.append(k_m)
    return _combine(None, tableau.b, du), _combine(m, tableau.b, dm)


def rk_in_the_chart_looped(tableau: ButcherTableau, stage, u0, m):
    """`rk_in_the_chart` (`u0` the chart's origin, zeros of `u`'s shape; `m` one array; no
    `store`) with its stages in a `lax.fori_loop`: the stage is traced and compiled once,
    not once per stage. For the generic step, whose stage holds a whole group's `exp` and
    `dexpinv` (on SO(n) matrix exponentials): an unrolled 12-stage step compiled for
    seconds. The kernels keep the unrolled form, whose stages XLA fuses. The first stage
    gets `u0`, not `None`.

    The increments (of the shapes of `u0` and `m`) are kept in arrays `(stages, …)`, zero
    where not yet computed, and a stage's input is its row of `a` (zero-padded) against
    all of them: the zero terms are exact, so the iterates are those of `rk_in_the_chart`
    up to the summation order.
    """
    s = len(tableau.a)
    dtype = m.dtype
    a = jnp.asarray([list(row) + [0.0] * (s - len(row)) for row in tableau.a], dtype)
    c = jnp.asarray(tableau.c, dtype)
    b = jnp.asarray(tableau.b, dtype)
    ku = jnp.zeros((s, *u0.shape), u0.dtype)
    km = jnp.zeros((s, *m.shape), dtype)

    def one_stage(i, increments):
        ku, km = increments
        u_i = u0 + jnp.tensordot(a[i], ku, axes=1)
        m_i = m + jnp.tensordot(a[i], km, axes=1)
        k_u, k_m = stage(u_i, m_i, c[i])
        return ku.at[i].set(k_u), km.at[i].set(k_m)

    ku, km = jax.lax.fori_loop(0, s, one_stage, (ku, km))
    return u0 + jnp.tensordot(b, ku, axes=1), m + jnp.tensordot(b, km, axes=1)


CLASSICAL_RK4 = ButcherTableau(
    order=4,
    a=((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0)),
    b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
    imaginary_stability=2.8284271247461903,  # 2√2
)

DORMAND_PRINCE5 = ButcherTableau(
    order=5,
    a=(
        (),
        (1 / 5,),
        (3 / 40, 9 / 40),
        (44 / 45, -56 / 15, 32 / 9),
        (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729),
        (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656),
    ),
    b=(35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84),
    # |R(iy)| ≤ 1 only to y ≈ 0.997: the pair was tuned for its error estimate, not for
    # rotation; beyond it a rotating mode grows slowly (0.3 % a step at y = 1.5).
    imaginary_stability=0.99,
)

DOP853 = ButcherTableau(
    order=8,
    a=(
        (),
        (5.26001519587677318785587544488e-2,),
        (1.97250569845378994544595329183e-2, 5.91751709536136983633785987549e-2),
        (2.95875854768068491816892993775e-2, 0.0, 8.87627564304205475450678981324e-2),
        (
            2.41365134159266685502369798665e-1,
            0.0,
            -8.84549479328286085344864962717e-1,
            9.24834003261792003115737966543e-1,
        ),
        (
            3.7037037037037037037037037037e-2,
            0.0,
            0.0,
            1.70828608729473871279604482173e-1,
            1.25467687566822425016691814123e-1,
        ),
        (
            3.7109375e-2,
            0.0,
            0.0,
            1.70252211019544039314978060272e-1,
            6.02165389804559606850219397283e-2,
            -1.7578125e-2,
        ),
        (
            3.70920001185047927108779319836e-2,
            0.0,
            0.0,
            1.70383925712239993810214054705e-1,
            1.07262030446373284651809199168e-1,
            -1.53194377486244017527936158236e-2,
            8.27378916381402288758473766002e-3,
        ),
        (
            6.24110958716075717114429577812e-1,
            0.0,
            0.0,
            -3.36089262944694129406857109825,
            -8.68219346841726006818189891453e-1,
            2.75920996994467083049415600797e1,
            2.01540675504778934086186788979e1,
            -4.34898841810699588477366255144e1,
        ),
        (
            4.77662536438264365890433908527e-1,
            0.0,
            0.0,
            -2.48811461997166764192642586468,
            -5.90290826836842996371446475743e-1,
            2.12300514481811942347288949897e1,
            1.52792336328824235832596922938e1,
            -3.32882109689848629194453265587e1,
            -2.03312017085086261358222928593e-2,
        ),
        (
            -9.3714243008598732571704021658e-1,
            0.0,
            0.0,
            5.18637242884406370830023853209,
            1.09143734899672957818500254654,
            -8.14978701074692612513997267357,
            -1.85200656599969598641566180701e1,
            2.27394870993505042818970056734e1,
            2.49360555267965238987089396762,
            -3.0467644718982195003823669022,
        ),
        (
            2.27331014751653820792359768449,
            0.0,
            0.0,
            -1.05344954667372501984066689879e1,
            -2.00087205822486249909675718444,
            -1.79589318631187989172765950534e1,
            2.79488845294199600508499808837e1,
            -2.85899827713502369474065508674,
            -8.87285693353062954433549289258,
            1.23605671757943030647266201528e1,
            6.43392746015763530355970484046e-1,
        ),
    ),
    b=(
        5.42937341165687622380535766363e-2,
        0.0,
        0.0,
        0.0,
        0.0,
        4.45031289275240888144113950566,
        1.89151789931450038304281599044,
        -5.8012039600105847814672114227,
        3.1116436695781989440891606237e-1,
        -1.52160949662516078556178806805e-1,
        2.01365400804030348374776537501e-1,
        4.47106157277725905176885569043e-2,
    ),
    imaginary_stability=5.96,
)
