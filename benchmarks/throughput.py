"""Throughput of batched rigid-body rollouts: body-steps per second against batch size.

Every integrator lievi has for the free rigid body (DEP exp and Cayley charts, and when
present Moser–Veselov, Lie–Poisson splitting and RK4), run through
`lievi.simulate_batch` (its structure-of-arrays fast path where there is one), against,
in the same run and on the same rigid-body ODE (Euler's equations plus `ġ = gΩ̂`),
diffrax `Tsit5` with a constant step — and the naive `jax.vmap(simulate)` DEP
for reference. Random bodies (inertia and momentum per body), `--steps` steps of size
0.1, only the final state kept. Compile time is reported separately (first call minus
the best of the timed calls). The device is the one JAX picks; on a GPU the default
dtype is float32 only.

The diffrax baseline ("diffrax Tsit5", every ratio is taken against it) is the fastest
formulation of the same solver, the same ODE and the same step that we found:

- the batch as rows: a (12, B) array Π₁ Π₂ Π₃ g₁₁ … g₃₃ is the diffrax state, solved in
  blocks of 5000 bodies one after another (`lax.map`) above 1e4 bodies on a CPU, in one solve up to
  1e4, each block one `diffeqsolve` (with
  a constant step nothing adapts per body, so each body takes exactly the steps of its own
  solve; the final states agree with the per-body solve to ≈ 1e-14);
- the vector field written out as 12 row expressions (row i of `gΩ̂` is `gᵢ × Ω`; no
  3×3 matrices built), the inverse inertia passed in;
- `ConstantStepSize()`, `SaveAt(t1=True)`, `max_steps = steps`, and for this forward-only
  run `throw=False`, `adjoint=ForwardMode()` (the step loop a plain `while_loop`, not the
  checkpointed one of the default `RecursiveCheckpointAdjoint`) and
  `Tsit5(scan_kind="lax")` (the stage loop a plain `lax` loop).

What was tried (`--diffrax-variants` times every formulation in `DIFFRAX_VARIANTS` in
interleaved rounds, each checked against the weak formulation's final state; the
figures are in the run's JSON, with the load they were taken at): the pytree `(Π,
g)` with `g @ SO3.hat(Ω)`, one solve per body under `jax.vmap` (the former baseline,
kept as the row "diffrax Tsit5, (Π, g) pytree — weak formulation"; no ratio is published
against it); a flat 12-vector per body with `R @ hat(Ω)` or with the 12 scalar
expressions, vmapped, with diffrax's defaults or the options above; the batch as one (B,
12) state (columns) or (12, B) state (rows) in one solve, each option alone and all
together; the rows in blocks of 1000, 5000 and 20000 bodies; `Dopri5` in place of
`Tsit5` (the same cost per step: 6 evaluations, FSAL). What paid: the batch inside the
solve on rows (no `vmap` of diffrax's loops, which turns every loop iteration into
selects over the whole state) and, at batch 1e5, blocks of a few thousand bodies (2.8×
over one solve; 20000 already too many; at 1e4 one solve was faster); `throw=False`,
`ForwardMode` and the `lax` stage loop together +29 % (1e5) and +54 % (1e4) on one
solve, each alone within the scatter of a loaded machine, `DirectAdjoint` slower; Dopri5
ran 1.13× the Tsit5 baseline in one run (within the scatter), and the baseline stays
Tsit5, the method the ratios name. `--acceptance` also times "diffrax Tsit5, independent
flat runner" (`_independent_flat_diffrax`, no code shared with the baseline: a flat
12-vector per body, `R @ hat(Ω)`, vmapped, as a diffrax user would write it for speed)
and checks that the baseline is within 10 % of it or faster.

    python benchmarks/throughput.py [--quick] [--batches 1 100 10000] [--steps 100]
                                    [--dtypes float64 float32] [--out throughput]
                                    [--cpu-devices N]
    python benchmarks/throughput.py --acceptance [--cpu-devices 2]
    python benchmarks/throughput.py --heavy-top [--methods "DEP exp" splitting]
    python benchmarks/throughput.py --diffrax-variants [--batches 10000] [--rounds 3]

Writes `benchmarks/results/<out>.json` and `<out>.png`.

`--acceptance` is the CPU acceptance configuration of the design targets alone (a few minutes): batch
1e5, 100 steps, float64, final state only, every lievi method and the three diffrax rows,
checked against the targets (DEP exp ≥ 1e7, Moser–Veselov and splitting ≥ 3e7
body-steps/s, every method ≥ 10× the diffrax baseline, `jax.vmap(simulate)` included),
into `throughput_cpu_acceptance.json`,
with each method's operation count per body-step (XLA's `cost_analysis`, as written and as
executed after fusion) and the achieved fraction of the flop limit (`PEAK_FLOPS_PER_CORE`
times the cores this process may run on: with one XLA device, XLA's CPU runtime still runs
the independent loops of a step concurrently on its thread pool, one thread a core). `--cpu-devices N` splits
the host CPU into N XLA devices (`--xla_force_host_platform_device_count`) and shards the
batch over them with `lievi.shard_batch` — every loop is then split over the devices, not
only independent loops run side by side (every method, diffrax included, gets the same
sharded inputs).

`--heavy-top` times the heavy top (`lievi.heavy_top`: asymmetric bodies, off-axis centres
of mass, `γ = 1`; batch 1e5, 100 steps, float64, final state only) through the fast path
on the reduced state `(Π, Γ)` (`g` not saved: the paper's §7) and on `(Π, g)`, against
diffrax `Tsit5` on the heavy top's equations `Π̇ = Π × Ω + mγ Γ × ρ`, `Γ̇ = Γ × Ω`
(formulated as the free body's baseline: the batch as (6, B) rows in blocks of 5000, the
field written out on rows; the pytree formulation vmapped is timed too, as the weak row) and
against the free body's fast path (same method), in one run, into
`throughput_heavy_top.json`; the design bars are ≥ 10× diffrax and within 2× of the
free body.
"""

from __future__ import annotations

import argparse
import datetime
import functools
import json
import os
import pathlib
import platform
import sys
import time
from functools import partial


def _early_cpu_devices():
    """`--cpu-devices N` must reach XLA before jax is imported."""
    if "--cpu-devices" in sys.argv:
        n = int(sys.argv[sys.argv.index("--cpu-devices") + 1])
        flags = os.environ.get("XLA_FLAGS", "")
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


_early_cpu_devices()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402
from lievi._kernels._base import AbstractBatchKernel  # noqa: E402
from lievi._kernels._composition import CompositionKernel  # noqa: E402

H = 0.1
# Row labels of the two extra diffrax rows (no ratio is published against either).
WEAK = "diffrax Tsit5, (Π, g) pytree — weak formulation"
INDEPENDENT = "diffrax Tsit5, independent flat runner"


@functools.lru_cache(maxsize=4)
def rigid_body_inputs(batch: int, dtype, seed: int = 0):
    """Random bodies: principal moments in [0.5, 2], unit-scale momenta, random attitudes."""
    rng = np.random.default_rng(seed)
    inertia = rng.uniform(0.5, 2.0, size=(batch, 3))
    m0 = rng.normal(size=(batch, 3))
    q, r = np.linalg.qr(rng.normal(size=(batch, 3, 3)))
    q = q * np.sign(np.diagonal(r, axis1=-2, axis2=-1))[:, None, :]
    q[np.linalg.det(q) < 0, :, 0] *= -1
    return jnp.asarray(inertia, dtype), jnp.asarray(q, dtype), jnp.asarray(m0, dtype)


def lievi_runner(integrator, steps: int, fast: bool = True, **options):
    def run(inertia, g0, m0):
        bodies = jax.vmap(lievi.RigidBody)(inertia)
        sol = lievi.simulate_batch(
            bodies,
            integrator,
            g0,
            m0,
            h=jnp.asarray(H, m0.dtype),
            n_steps=steps,
            system_axis=0,
            save=lievi.Save(stats=False, every=steps),
            tuning=lievi.advanced.Tuning(fast=fast, **options),
            throw=False,
        )
        return sol.g[:, -1], sol.m[:, -1], sol.result

    return jax.jit(run)


# --- diffrax baselines -------------------------------------------------------------------
#
# The baseline every published ratio is taken against ("diffrax Tsit5") is the fastest
# formulation of the same solver on the same ODE and step that we found (see the module
# docstring and `--diffrax-variants`): the whole batch as ONE diffrax state, a (12, B)
# array of rows Π₁ Π₂ Π₃ g₁₁ … g₃₃, in ONE `diffeqsolve`; the vector field written out as
# 12 scalar-row expressions (row i of g Ω̂ is gᵢ × Ω, no matrices built); the inverse
# inertia passed in; `ConstantStepSize`, `SaveAt(t1=True)`, `max_steps = steps`,
# `throw=False`, `adjoint=ForwardMode()` (a plain `while_loop`: nothing is saved for a
# backward pass) and the Runge–Kutta stages as a plain `lax` loop (`scan_kind="lax"`). With a
# constant step no error estimate steers anything, so one solve over the batch takes
# exactly the steps each body's own solve takes (checked against the per-body solve).


def _rigid_body_rows(y, inv_inertia):
    """Euler's equations and `ġ = gΩ̂` on rows: `y = (Π₁, Π₂, Π₃, g₁₁, g₁₂, …, g₃₃)`,
    `inv_inertia = (1/I₁, 1/I₂, 1/I₃)`, each entry an array of any shape (one per body).
    Row i of `gΩ̂` is `gᵢ × Ω`."""
    p1, p2, p3, a, b, c, d, e, f, g, h, k = y
    w1, w2, w3 = p1 * inv_inertia[0], p2 * inv_inertia[1], p3 * inv_inertia[2]
    return (
        p2 * w3 - p3 * w2,
        p3 * w1 - p1 * w3,
        p1 * w2 - p2 * w1,
        b * w3 - c * w2,
        c * w1 - a * w3,
        a * w2 - b * w1,
        e * w3 - f * w2,
        f * w1 - d * w3,
        d * w2 - e * w1,
        h * w3 - k * w2,
        k * w1 - g * w3,
        g * w2 - h * w1,
    )


def _pytree_field(t, y, inertia):
    """The weak formulation's field: the pytree `(Π, g)`, `g @ SO3.hat(Ω)`."""
    Pi, g = y
    omega = Pi / inertia
    return jnp.cross(Pi, omega), g @ lievi.SO3.hat(omega)


def _flat_matrix_field(t, y, inertia):
    """One body, one flat 12-vector `(Π, vec g)`, `R @ hat(Ω)` on its reshaped last nine."""
    Pi, R = y[:3], y[3:].reshape(3, 3)
    omega = Pi / inertia
    return jnp.concatenate([jnp.cross(Pi, omega), (R @ lievi.SO3.hat(omega)).reshape(9)])


def _flat_scalar_field(t, y, inv_inertia):
    """One body, one flat 12-vector, 12 scalar expressions."""
    return jnp.stack(_rigid_body_rows(y, inv_inertia))


def _rows_field(t, y, inv_inertia):
    """The whole batch: `y` (12, B), `inv_inertia` (3, B)."""
    return jnp.stack(_rigid_body_rows(y, inv_inertia))


def _columns_field(t, y, inv_inertia):
    """The whole batch: `y` (B, 12), `inv_inertia` (B, 3)."""
    return jnp.stack(_rigid_body_rows(y.T, inv_inertia.T), axis=-1)


# The diffrax options of the strong baseline (forward only: nothing is differentiated), and
# the bodies per solve: on a CPU the batch is cut into blocks of `chunk` bodies, solved one
# after another (`lax.map`), so that a block's stage arrays stay in cache; on a GPU one
# solve over the whole batch ("auto": blocks one after another would leave the GPU idle).
STRONG_DIFFRAX = {"scan_kind": "lax", "adjoint": "forward", "throw": False, "chunk": "auto"}
CPU_CHUNK = 5000


def _in_chunks(solve_rows, y0, args, chunk: int | None):
    """`solve_rows(y0, args)` on (n, B) rows, in blocks of `chunk` bodies one after another
    (`lax.map`; the last block padded with copies of the last body) when `B > 2 chunk`, in
    one solve otherwise (at batch 1e4 one solve was 1.3× two blocks of 5000, at 1e5 blocks
    of 5000 2.8× one solve: `--diffrax-variants`). Returns the final rows (n, B) and the
    worst result code. `chunk="auto"`: `CPU_CHUNK` on a CPU, one solve on a GPU."""
    batch = y0.shape[1]
    if chunk == "auto":
        chunk = CPU_CHUNK if jax.default_backend() == "cpu" else None
    if chunk is None or batch <= 2 * chunk:
        return solve_rows(y0, args)
    blocks = -(-batch // chunk)
    pad = blocks * chunk - batch

    def split(x):
        x = jnp.pad(x, ((0, 0), (0, pad)), mode="edge")
        return x.reshape(x.shape[0], blocks, chunk).transpose(1, 0, 2)

    ys, results = jax.lax.map(lambda a: solve_rows(*a), (split(y0), split(args)))
    return ys.transpose(1, 0, 2).reshape(y0.shape[0], -1)[:, :batch], jnp.max(results)


def diffrax_rigid_body(
    steps: int,
    layout: str = "rows",
    solver: str = "Tsit5",
    scan_kind: str | None = STRONG_DIFFRAX["scan_kind"],
    adjoint: str | None = STRONG_DIFFRAX["adjoint"],
    throw: bool = STRONG_DIFFRAX["throw"],
    chunk: int | str | None = STRONG_DIFFRAX["chunk"],
):
    """diffrax on the free rigid body, final `(g, Π, result)` of a batch, jitted.

    `layout`: `"rows"` — the batch as one (12, B) state, one solve (the strong baseline);
    `"columns"` — one (B, 12) state, one solve; `"flat-scalar"`, `"flat-matrix"`, `"pytree"`
    — one solve per body (a 12-vector with scalar expressions, a 12-vector with
    `R @ hat(Ω)`, the pytree `(Π, g)` with `g @ SO3.hat(Ω)`), `jax.vmap`ped over the batch.
    `solver`: `"Tsit5"` or `"Dopri5"`; `scan_kind`: the Runge–Kutta stage loop
    (diffrax's default `None` is a checkpointed loop); `adjoint`: `None` (diffrax's
    default, `RecursiveCheckpointAdjoint`), `"direct"` or `"forward"`; `chunk`: with
    `"rows"`, bodies per solve (`None`: the whole batch in one solve; `"auto"`: see
    `_in_chunks`)."""
    import diffrax

    method = getattr(diffrax, solver)(scan_kind=scan_kind)
    options = {
        "stepsize_controller": diffrax.ConstantStepSize(),
        "saveat": diffrax.SaveAt(t1=True),
        "max_steps": steps,
        "throw": throw,
    }
    if adjoint is not None:
        options["adjoint"] = {"direct": diffrax.DirectAdjoint, "forward": diffrax.ForwardMode}[
            adjoint
        ]()

    def solve(field, y0, args):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field),
            method,
            t0=0.0,
            t1=steps * H,
            dt0=H,
            y0=y0,
            args=args,
            **options,
        )
        return sol.ys, sol.result._value

    if layout == "rows":

        def solve_rows(y0, inv_inertia):
            ys, result = solve(_rows_field, y0, inv_inertia)
            return ys[-1], result

        def run(inertia, g0, m0):
            y0 = jnp.concatenate([m0.T, g0.reshape(-1, 9).T])
            y, result = _in_chunks(solve_rows, y0, 1 / inertia.T, chunk)
            return y[3:].T.reshape(-1, 3, 3), y[:3].T, result

        return jax.jit(run)
    if layout == "columns":

        def run(inertia, g0, m0):
            y0 = jnp.concatenate([m0, g0.reshape(-1, 9)], axis=1)
            ys, result = solve(_columns_field, y0, 1 / inertia)
            return ys[-1, :, 3:].reshape(-1, 3, 3), ys[-1, :, :3], result

        return jax.jit(run)
    if layout == "pytree":

        def one(inertia, g0, m0):
            ys, result = solve(_pytree_field, (m0, g0), inertia)
            return ys[1][-1], ys[0][-1], result

        return jax.jit(jax.vmap(one))
    field, scale = {
        "flat-scalar": (_flat_scalar_field, lambda i: 1 / i),
        "flat-matrix": (_flat_matrix_field, lambda i: i),
    }[layout]

    def one(inertia, g0, m0):
        ys, result = solve(field, jnp.concatenate([m0, g0.reshape(9)]), scale(inertia))
        return ys[-1, 3:].reshape(3, 3), ys[-1, :3], result

    return jax.jit(jax.vmap(one))


def diffrax_runner(steps: int):
    """The strong baseline: diffrax Tsit5, the batch as one (12, B) state in one solve."""
    return diffrax_rigid_body(steps)


def diffrax_weak_runner(steps: int):
    """The weak formulation, kept for comparison only (no ratio is taken against it): one
    solve per body on the pytree `(Π, g)` with `g @ SO3.hat(Ω)`, vmapped, diffrax's
    default options (the baseline of this script before the strong one)."""
    return diffrax_rigid_body(steps, *DIFFRAX_VARIANTS[DIFFRAX_WEAK_LABEL])


def _independent_flat_diffrax(steps: int):
    """A second diffrax runner that shares no code with `diffrax_rigid_body`, written as a
    diffrax user would for speed: one flat array of 12 numbers per body (`R` in the first
    nine, `Π` in the last three), `R @ hat(Ω)` on the reshaped first nine,
    `SaveAt(t1=True)`, `ConstantStepSize`, `max_steps = steps`, vmapped over the bodies.
    The strong baseline must be within 10 % of it or faster (`--acceptance` checks)."""
    import diffrax

    def vector_field(t, y, inertia):
        R, Pi = y[:9].reshape(3, 3), y[9:]
        w = Pi / inertia
        w_hat = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        return jnp.concatenate([(R @ w_hat).ravel(), jnp.cross(Pi, w)])

    def one(inertia, g0, m0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(vector_field),
            diffrax.Tsit5(),
            t0=0.0,
            t1=steps * H,
            dt0=H,
            y0=jnp.concatenate([g0.ravel(), m0]),
            args=inertia,
            stepsize_controller=diffrax.ConstantStepSize(),
            saveat=diffrax.SaveAt(t1=True),
            max_steps=steps,
        )
        y = sol.ys[0]
        return y[:9].reshape(3, 3), y[9:], sol.result._value

    return jax.jit(jax.vmap(one))


DIFFRAX_WEAK_LABEL = "pytree (Π, g), vmap, defaults (weak)"
DIFFRAX_STRONG_LABEL = "rows (12, B), blocks of 5000, lax+forward+no throw (strong)"
_ALL = ("lax", "forward", False)  # scan_kind, adjoint, throw of the strong baseline
_DEFAULTS = (None, None, True)
# `--diffrax-variants`: every formulation tried for the baseline,
# `(layout, solver, scan_kind, adjoint, throw, chunk)` (see `diffrax_rigid_body`).
DIFFRAX_VARIANTS = {
    DIFFRAX_WEAK_LABEL: ("pytree", "Tsit5", *_DEFAULTS, None),
    "flat 12, R @ hat, vmap, defaults": ("flat-matrix", "Tsit5", *_DEFAULTS, None),
    "flat 12, scalar field, vmap, defaults": ("flat-scalar", "Tsit5", *_DEFAULTS, None),
    "flat 12, scalar field, vmap, lax+forward+no throw": ("flat-scalar", "Tsit5", *_ALL, None),
    "columns (B, 12), one solve, defaults": ("columns", "Tsit5", *_DEFAULTS, None),
    "columns (B, 12), one solve, lax+forward+no throw": ("columns", "Tsit5", *_ALL, None),
    "rows (12, B), one solve, defaults": ("rows", "Tsit5", *_DEFAULTS, None),
    "rows (12, B), one solve, throw=False": ("rows", "Tsit5", None, None, False, None),
    "rows (12, B), one solve, DirectAdjoint": ("rows", "Tsit5", None, "direct", True, None),
    "rows (12, B), one solve, ForwardMode": ("rows", "Tsit5", None, "forward", True, None),
    "rows (12, B), one solve, scan_kind=lax": ("rows", "Tsit5", "lax", None, True, None),
    "rows (12, B), one solve, lax+forward+no throw": ("rows", "Tsit5", *_ALL, None),
    "rows (12, B), blocks of 1000, lax+forward+no throw": ("rows", "Tsit5", *_ALL, 1000),
    DIFFRAX_STRONG_LABEL: ("rows", "Tsit5", *_ALL, 5000),
    "rows (12, B), blocks of 20000, lax+forward+no throw": ("rows", "Tsit5", *_ALL, 20000),
    "rows (12, B), blocks of 5000, defaults": ("rows", "Tsit5", *_DEFAULTS, 5000),
    "rows (12, B), one solve, Dopri5, defaults": ("rows", "Dopri5", *_DEFAULTS, None),
    "rows (12, B), blocks of 5000, Dopri5, lax+forward+no throw": ("rows", "Dopri5", *_ALL, 5000),
}


# The high-order compositions on the fast path (order 4 and 6 of the splitting): one
# fused batched step of 3 and 9 splitting stages.
COMPOSITIONS = {
    "splitting ∘ 4": lievi.Composition(lievi.LiePoissonSplitting(), order=4),
    "splitting ∘ 6": lievi.Composition(lievi.LiePoissonSplitting(), order=6),
}


# Rows named differently from their lievi class (row name, class), no arguments.
NAMED_METHODS = (
    ("Moser-Veselov", "MoserVeselov"),
    ("splitting", "LiePoissonSplitting"),
    ("RK4", "RK4"),
    ("RKMK4", "RKMK4"),
    ("RKMK5", "RKMK5"),
    ("RKMK8", "RKMK8"),
)


def methods(steps: int):
    rows = {
        "DEP exp": lievi_runner(lievi.DEP(chart="exp"), steps),
        "DEP cayley": lievi_runner(lievi.DEP(chart="cayley"), steps),
        # Exactly three Newton iterations and a check, no convergence tail (no
        # data-dependent loop: on a GPU no device-to-host sync per step), 4 steps per
        # loop iteration.
        "DEP exp, 3 its, unroll 4": lievi_runner(
            lievi.DEP(chart="exp", max_steps=3), steps, unroll=4
        ),
    }
    for name, cls in NAMED_METHODS:
        if hasattr(lievi, cls):
            rows[name] = lievi_runner(getattr(lievi, cls)(), steps)
    for name, integrator in COMPOSITIONS.items():
        rows[name] = lievi_runner(integrator, steps)
    rows["diffrax Tsit5"] = diffrax_runner(steps)
    rows[WEAK] = diffrax_weak_runner(steps)
    rows[INDEPENDENT] = _independent_flat_diffrax(steps)
    rows["DEP exp, vmap(simulate)"] = lievi_runner(lievi.DEP(chart="exp"), steps, fast=False)
    return rows


def check_against_generic(name, fn, dtype, steps: int):
    """Max |difference| of the final state from the `vmap(simulate)` path (64 bodies); for
    a diffrax row, from the weak formulation's (the same solver on the same ODE)."""
    if "vmap" in name or name == WEAK:
        return None
    inputs = rigid_body_inputs(64, dtype, seed=1)
    if "diffrax" in name:
        a, b = fn(*inputs), diffrax_weak_runner(steps)(*inputs)
        return float(max(jnp.max(jnp.abs(a[0] - b[0])), jnp.max(jnp.abs(a[1] - b[1]))))
    integrator = {"DEP cayley": lievi.DEP(chart="cayley"), **COMPOSITIONS}.get(
        name, lievi.DEP(chart="exp")
    )
    for label, cls in NAMED_METHODS:
        if name == label:
            integrator = getattr(lievi, cls)()
    fast = fn(*inputs)
    generic = lievi_runner(integrator, steps, fast=False)(*inputs)
    return float(
        max(jnp.max(jnp.abs(fast[0] - generic[0])), jnp.max(jnp.abs(fast[1] - generic[1])))
    )


# The design's CPU acceptance targets (float64, batch 1e5, 100 steps), body-steps/s.
TARGETS = {"DEP exp": 1e7, "Moser-Veselov": 3e7, "splitting": 3e7}
ACCEPTANCE_METHODS = (
    "DEP exp",
    "DEP cayley",
    "Moser-Veselov",
    "splitting",
    "RK4",
    "RKMK4",
    "diffrax Tsit5",
    WEAK,
    INDEPENDENT,
    "DEP exp, vmap(simulate)",
)
# The flop limit one core can reach in float64: 2.5 GHz × 16 flops per cycle (two 4-wide
# FMA units). An assumption about this class of machine, stated, not measured; the achieved
# fraction below is relative to it times the cores (`cpu_cores`).
PEAK_FLOPS_PER_CORE = 40e9


def cpu_cores() -> int:
    """The cores this process may run on: the size of XLA's CPU thread pool."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()


def flops_per_body_step(fn, dtype, batch: int = 1000):
    """XLA's own operation counts for one step of `fn`'s method (built with 1 step):
    `(traced, executed)` per body-step — the program as written, and the optimised one
    XLA runs (fusion may duplicate work: executed counts ran 2–2.5× the traced ones)."""

    def count(analysis):
        analysis = analysis[0] if isinstance(analysis, list) else analysis
        return analysis["flops"] / batch

    lowered = fn.lower(*rigid_body_inputs(batch, dtype))
    return count(lowered.cost_analysis()), count(lowered.compile().cost_analysis())


def executed_counts(fn, inputs, batch: int):
    """XLA's counts of the optimised program `fn(*inputs)` runs, per body: flops and bytes
    accessed, each loop's body counted once (so for a composition: the step's fixed part and
    one stage) — independent of the machine's load, unlike the times."""
    analysis = fn.lower(*inputs).compile().cost_analysis()
    analysis = analysis[0] if isinstance(analysis, list) else analysis
    return {
        "executed_flops_per_body": analysis.get("flops", float("nan")) / batch,
        "executed_bytes_per_body": analysis.get("bytes accessed", float("nan")) / batch,
    }


def baseline_summary(rates):
    """The diffrax rows: the strong baseline, the weak formulation and the independent
    flat runner, and the check that the strong one is within 10 % of the independent one
    or faster. Returns the record for the JSON."""
    strong, weak, independent = (rates.get(k) for k in ("diffrax Tsit5", WEAK, INDEPENDENT))
    print("baselines (diffrax, same run):")
    print(f"{'diffrax Tsit5 (strong: the baseline)':<48}{strong:>12.3g}")
    line = {"diffrax_tsit5_strong": strong}
    if weak:
        print(f"{WEAK:<48}{weak:>12.3g}  (strong / weak: {strong / weak:.1f}×)")
        line.update({"diffrax_tsit5_weak": weak, "strong_over_weak": strong / weak})
    if independent:
        ok = strong >= 0.9 * independent
        print(
            f"{INDEPENDENT:<48}{independent:>12.3g}  (strong / independent: "
            f"{strong / independent:.2f}×: {'ok, ≥ 0.9' if ok else 'FAILED, below 0.9'})"
        )
        line.update(
            {
                "diffrax_tsit5_independent_flat": independent,
                "strong_over_independent": strong / independent,
                "strong_within_10_percent_of_independent": ok,
            }
        )
    return line


def acceptance_summary(records):
    """Each method against its target and against the strong diffrax Tsit5 (≥ 10×), in
    this run; the diffrax rows apart (no ratio is taken against the weak formulation)."""
    rates = {r["method"]: r["body_steps_per_s"] for r in records}
    base = rates.get("diffrax Tsit5")
    lines = []
    for name, rate in rates.items():
        if "diffrax" in name:
            continue
        ratio = rate / base if base else float("nan")
        target = TARGETS.get(name)
        verdict = "" if target is None else (" ≥ target" if rate >= target else " BELOW target")
        line = {
            "method": name,
            "body_steps_per_s": rate,
            "target": target,
            "vs_diffrax_tsit5": ratio,
            "meets_target": None if target is None else rate >= target,
            "meets_10x_diffrax": ratio >= 10,
        }
        # The flop limit is the CPU's (`PEAK_FLOPS_PER_CORE`); a GPU's cost analysis is None.
        one_step = methods(1).get(name) if jax.default_backend() == "cpu" else None
        if one_step is not None:
            traced, executed = flops_per_body_step(one_step, jnp.float64)
            peak = PEAK_FLOPS_PER_CORE * cpu_cores()
            line.update(
                {
                    "flops_per_body_step_traced": traced,
                    "flops_per_body_step_executed": executed,
                    "flop_limit_body_steps_per_s": peak / traced,
                    "fraction_of_flop_limit": rate * traced / peak,
                    "executed_flops_fraction_of_peak": rate * executed / peak,
                }
            )
        lines.append(line)
        flops = (
            f"  {line['flops_per_body_step_traced']:6.0f} flops/body-step, {100 * line['fraction_of_flop_limit']:5.1f}% of the flop limit"
            if "fraction_of_flop_limit" in line
            else ""
        )
        print(
            f"{name:<26}{rate:>12.3g}  target {target or '-':>8}{verdict:<14}"
            f"{ratio:>8.1f}× diffrax Tsit5 (strong){'' if ratio >= 10 else ' (below 10×)'}{flops}"
        )
    if base:
        print()
        lines.append(baseline_summary(rates))
    return lines


# --- The heavy top: rigid bodies in uniform gravity ----------------------------------------


class _StageByStageKernel(CompositionKernel):
    """`CompositionKernel` with the default stage loop of `AbstractBatchKernel`: each stage
    its own kick – free step – kick (2s kicks a step, not s + 1)."""

    def prepare(self, constants, h):
        return AbstractBatchKernel.prepare_stages(self.inner, constants, h, self.coefficients)

    def step(self, params, g, m, alive):
        return AbstractBatchKernel.step_stages(self.inner, params, g, m, alive)


class StageByStage(lievi.Composition):
    """`lievi.Composition` whose batched kernel runs the stages one after the other."""

    def batch_kernel(self, system, batched: bool = False):
        kernel = super().batch_kernel(system, batched)
        return None if kernel is None else _StageByStageKernel(kernel.inner, kernel.coefficients)


# Nondimensional gravity: m γ |ρ| ≈ 0.5 against |Π| ≈ 1.7 and I ∈ [0.5, 2], so the steps
# turn about as far as the free bodies' (h|Ω| ≲ 0.5) and the two are comparable.
GRAVITY = 1.0
HEAVY_TOP_METHODS = {
    "DEP exp": lambda: lievi.DEP(chart="exp"),
    "DEP cayley": lambda: lievi.DEP(chart="cayley"),
    "Moser-Veselov": lambda: lievi.MoserVeselov(),
    "splitting": lambda: lievi.LiePoissonSplitting(),
    "RKMK4": lambda: lievi.RKMK4(),
    "RKMK5": lambda: lievi.RKMK5(),
    "RKMK8": lambda: lievi.RKMK8(),
    **{
        f"splitting ∘ {order}": partial(lievi.Composition, lievi.LiePoissonSplitting(), order)
        for order in (4, 6, 8)
    },
    # The same compositions with the stages run one after the other, two half kicks each:
    # the kernel before the kicks of adjacent stages were merged (before/after rows).
    **{
        f"splitting ∘ {order}, stage by stage": partial(
            StageByStage, lievi.LiePoissonSplitting(), order
        )
        for order in (4, 6, 8)
    },
}
# The methods timed by default (DEP's Cayley chart with --methods).
HEAVY_TOP_DEFAULT = ("DEP exp", "Moser-Veselov", "splitting")


@functools.lru_cache(maxsize=4)
def heavy_top_inputs(batch: int, dtype, seed: int = 0):
    """The free bodies of `rigid_body_inputs` with a mass in [0.5, 1.5] and an off-axis
    centre of mass `ρ ~ 0.3 N(0, 1)` each: asymmetric heavy tops."""
    inertia, g0, m0 = rigid_body_inputs(batch, dtype, seed)
    rng = np.random.default_rng(seed + 100)
    mass = jnp.asarray(rng.uniform(0.5, 1.5, size=batch), dtype)
    com = jnp.asarray(0.3 * rng.normal(size=(batch, 3)), dtype)
    return inertia, mass, com, g0, m0


def heavy_tops(inertia, mass, com):
    return jax.vmap(lambda i, m, c: lievi.heavy_top(i, m, c, gravity=GRAVITY))(inertia, mass, com)


def heavy_top_runner(integrator, steps: int, reduced: bool, fast: bool = True):
    """Final `(Γ, Π)` of a batch of heavy tops. `reduced`: `g` not saved, so the fast path
    carries `(Π, Γ)` (paper §7); else `g` is saved and carried, and `Γ = g_Nᵀe₃`."""

    def run(inertia, mass, com, g0, m0):
        sol = lievi.simulate_batch(
            heavy_tops(inertia, mass, com),
            integrator,
            g0,
            m0,
            h=jnp.asarray(H, m0.dtype),
            n_steps=steps,
            system_axis=0,
            save=lievi.Save(g=not reduced, stats=False, advected=reduced, every=steps),
            tuning=lievi.advanced.Tuning(fast=fast),
            throw=False,
        )
        gamma = sol.advected[:, -1] if reduced else sol.g[:, -1, 2]
        return gamma, sol.m[:, -1], sol.result

    return jax.jit(run)


def heavy_top_field(t, y, args):
    """The heavy top's reduced equations `Π̇ = Π × Ω + mγ Γ × ρ`, `Γ̇ = Γ × Ω`, `Ω = I⁻¹Π`
    (the torque `mγ Γ × ρ` of `lievi.UniformGravity`; checked against `system.force`)."""
    Pi, Gamma = y
    inertia, m_rho = args
    omega = Pi / inertia
    return jnp.cross(Pi, omega) + GRAVITY * jnp.cross(Gamma, m_rho), jnp.cross(Gamma, omega)


def _heavy_top_rows(y, args):
    """`heavy_top_field` on rows, written out: `y = (Π₁, Π₂, Π₃, Γ₁, Γ₂, Γ₃)`, `args =
    (1/I₁, 1/I₂, 1/I₃, γmρ₁, γmρ₂, γmρ₃)`, each an array with one entry per body."""
    p1, p2, p3, c1, c2, c3 = y
    j1, j2, j3, r1, r2, r3 = args
    w1, w2, w3 = p1 * j1, p2 * j2, p3 * j3
    return (
        p2 * w3 - p3 * w2 + c2 * r3 - c3 * r2,
        p3 * w1 - p1 * w3 + c3 * r1 - c1 * r3,
        p1 * w2 - p2 * w1 + c1 * r2 - c2 * r1,
        c2 * w3 - c3 * w2,
        c3 * w1 - c1 * w3,
        c1 * w2 - c2 * w1,
    )


def diffrax_heavy_top_runner(steps: int):
    """The strong baseline on the heavy top, as `diffrax_runner` on the free body: the
    batch as (6, B) rows `(Π, Γ)` solved as the free body's (`STRONG_DIFFRAX["chunk"]`), the
    field written out on rows, `throw=False`, `ForwardMode`, `scan_kind="lax"`."""
    import diffrax

    def solve_rows(y0, args):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: jnp.stack(_heavy_top_rows(y, args))),
            diffrax.Tsit5(scan_kind="lax"),
            t0=0.0,
            t1=steps * H,
            dt0=H,
            y0=y0,
            args=args,
            stepsize_controller=diffrax.ConstantStepSize(),
            saveat=diffrax.SaveAt(t1=True),
            max_steps=steps,
            throw=False,
            adjoint=diffrax.ForwardMode(),
        )
        return sol.ys[-1], sol.result._value

    def run(inertia, mass, com, g0, m0):
        y0 = jnp.concatenate([m0.T, g0[:, 2].T])  # Γ = gᵀe₃, the last row of g
        args = jnp.concatenate([1 / inertia.T, GRAVITY * (mass[:, None] * com).T])
        y, result = _in_chunks(solve_rows, y0, args, STRONG_DIFFRAX["chunk"])
        return y[3:].T, y[:3].T, result

    return jax.jit(run)


def diffrax_heavy_top_weak_runner(steps: int):
    """The weak formulation on the heavy top, for comparison only: one solve per body on
    the pytree `(Π, Γ)`, vmapped, diffrax's default options."""
    import diffrax

    def one(inertia, mass, com, g0, m0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(heavy_top_field),
            diffrax.Tsit5(),
            t0=0.0,
            t1=steps * H,
            dt0=H,
            y0=(m0, g0[2]),  # Γ = gᵀe₃, the last row of g
            args=(inertia, mass * com),
            stepsize_controller=diffrax.ConstantStepSize(),
            saveat=diffrax.SaveAt(t1=True),
            max_steps=steps,
        )
        return sol.ys[1][-1], sol.ys[0][-1], sol.result._value

    return jax.jit(jax.vmap(one))


HEAVY_TOP_STRONG = "heavy top: diffrax Tsit5 (Π, Γ)"
HEAVY_TOP_WEAK = "heavy top: diffrax Tsit5 (Π, Γ) pytree — weak formulation"


def heavy_top_rows(steps: int, names):
    """`(label, kind, runner)`: the free body's fast path, the heavy top's fast path on
    `(Π, Γ)` and on `(Π, g)`, for each method in `names`, and diffrax Tsit5 on `(Π, Γ)`."""
    rows = []
    for name in names:
        make = HEAVY_TOP_METHODS[name]
        rows.append((f"free body: {name}", "free", lievi_runner(make(), steps)))
        rows.append(
            (f"heavy top: {name} (Π, Γ)", "heavy", heavy_top_runner(make(), steps, reduced=True))
        )
        rows.append(
            (f"heavy top: {name} (Π, g)", "heavy", heavy_top_runner(make(), steps, reduced=False))
        )
    rows.append((HEAVY_TOP_STRONG, "heavy", diffrax_heavy_top_runner(steps)))
    rows.append((HEAVY_TOP_WEAK, "heavy", diffrax_heavy_top_weak_runner(steps)))
    return rows


def heavy_top_checks(names, dtype, steps: int):
    """Max |difference| of each heavy-top fast path's final `(Γ, Π)` from `vmap(simulate)`
    (64 bodies), and of diffrax's torque from `UniformGravity`'s autodiff force."""
    inputs = heavy_top_inputs(64, dtype, seed=1)
    checks = {}
    for name in names:
        generic = heavy_top_runner(HEAVY_TOP_METHODS[name](), steps, True, fast=False)(*inputs)
        for reduced in (True, False):
            fast = heavy_top_runner(HEAVY_TOP_METHODS[name](), steps, reduced)(*inputs)
            label = f"heavy top: {name} {'(Π, Γ)' if reduced else '(Π, g)'}"
            checks[label] = float(
                max(jnp.max(jnp.abs(a - b)) for a, b in zip(fast[:2], generic[:2]))
            )
    inertia, mass, com, g0, m0 = (x[0] for x in inputs)
    top = lievi.heavy_top(inertia, mass, com, gravity=GRAVITY)
    Pi_dot, _ = heavy_top_field(0.0, (m0, g0[2]), (inertia, mass * com))
    checks["diffrax torque vs system.force"] = float(
        jnp.max(jnp.abs(Pi_dot - jnp.cross(m0, m0 / inertia) - top.force(g0)))
    )
    strong = diffrax_heavy_top_runner(steps)(*inputs)
    weak = diffrax_heavy_top_weak_runner(steps)(*inputs)
    checks["diffrax strong vs weak formulation"] = float(
        max(jnp.max(jnp.abs(a - b)) for a, b in zip(strong[:2], weak[:2]))
    )
    return checks


def heavy_top_main(args, meta, out):
    """`--heavy-top`: batch 1e5, 100 steps, float64, final state only, in one run."""
    batch = (args.batches or [100_000])[-1]
    steps = args.steps or 100
    dtype_name = (args.dtypes or ["float64"])[0]
    dtype = jnp.dtype(dtype_name)
    names = args.methods or list(HEAVY_TOP_DEFAULT)
    meta.update({"steps": steps, "gravity": GRAVITY, "batch": batch, "dtype": dtype_name})
    checks = {} if args.no_checks else heavy_top_checks(names, dtype, steps)
    for label, value in checks.items():
        against = (
            "autodiff force"
            if "torque" in label
            else "64 bodies"
            if "weak" in label
            else "vmap(simulate), 64 bodies"
        )
        print(f"{label:<34} max |difference| vs {against}: {value:.2g}")
    meta["max_abs_difference_vs_vmap_simulate"] = checks
    print(
        f"\n{dtype_name}, batch {batch}\n{'method':<34}{'compile [s]':>13}{'run [s]':>11}{'body-steps/s':>15}"
    )
    records, timed_rows = [], []
    for label, kind, fn in heavy_top_rows(steps, names):
        inputs = (
            rigid_body_inputs(batch, dtype) if kind == "free" else heavy_top_inputs(batch, dtype)
        )
        if jax.device_count() > 1:
            inputs = lievi.shard_batch(inputs)
        timed_rows.append((fn, inputs))
        records.append(measure(label, fn, inputs, dtype_name, batch, steps))
        records[-1].update(executed_counts(fn, inputs, batch))
        compile_s, run_s, rate = (
            records[-1][k] for k in ("compile_s", "run_s", "body_steps_per_s")
        )
        print(f"{label:<34}{compile_s:>13.2f}{run_s:>11.4f}{rate:>15.3g}", flush=True)
        meta["load_average_at_end"] = os.getloadavg()
        (out / f"{args.out}.json").write_text(
            json.dumps({"meta": meta, "results": records}, indent=2)
        )
    # More rounds (`--rounds`), every row once a round, the best run kept: on a loaded
    # machine, rows timed minutes apart differ by more than the levers measured.
    for _ in range(args.rounds - 1):
        for record, (fn, inputs) in zip(records, timed_rows):
            run_s = timed(fn, inputs)[1]
            if run_s < record["run_s"]:
                record.update(run_s=run_s, body_steps_per_s=batch * steps / run_s)
    meta["rounds"] = args.rounds
    print(f"best of {args.rounds} interleaved rounds:")
    for record in records:
        ns = 1e9 / record["body_steps_per_s"]
        flops, bytes_ = record["executed_flops_per_body"], record["executed_bytes_per_body"]
        print(
            f"{record['method']:<44}{record['body_steps_per_s']:>12.3g} body-steps/s"
            f"{ns:8.1f} ns{flops:9.0f} flops{bytes_:8.0f} B (loop bodies once)"
        )
    rates = {r["method"]: r["body_steps_per_s"] for r in records}
    base = rates[HEAVY_TOP_STRONG]
    summary = []
    weak = rates[HEAVY_TOP_WEAK]
    print(
        f"\nbaselines: {HEAVY_TOP_STRONG} (strong) {base:.3g}, {HEAVY_TOP_WEAK} {weak:.3g} "
        f"(strong / weak {base / weak:.1f}×)"
    )
    meta["diffrax_strong_over_weak"] = base / weak
    print(
        "heavy top against the strong diffrax Tsit5 (Π, Γ) and the free body (same method, "
        "same run):"
    )
    for name in names:
        free = rates[f"free body: {name}"]
        for state in ("(Π, Γ)", "(Π, g)"):
            label = f"heavy top: {name} {state}"
            line = {
                "method": label,
                "body_steps_per_s": rates[label],
                "vs_diffrax_tsit5": rates[label] / base,
                "vs_free_body": rates[label] / free,
                "meets_10x_diffrax": rates[label] / base >= 10,
                "within_2x_of_free_body": rates[label] / free >= 0.5,
            }
            summary.append(line)
            print(
                f"{label:<34}{rates[label]:>12.3g}{line['vs_diffrax_tsit5']:>8.1f}× diffrax"
                f"{line['vs_free_body']:>8.2f}× free body"
            )
    meta["acceptance"] = summary
    save_results(records, meta, out / args.out, plot_heavy_top)


def _once(fn, args):
    """Seconds of one call of `fn(*args)` (the first includes compiling)."""
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


def diffrax_variants_main(args, meta, out):
    """`--diffrax-variants`: every formulation in `DIFFRAX_VARIANTS` and the independent flat
    runner, same inputs, timed in interleaved rounds (best of each); each checked against
    the weak formulation's final state (64 bodies)."""
    batch = (args.batches or [100_000])[-1]
    steps = args.steps or 100
    dtype = jnp.float64
    # (`--methods`: a subset; the strong baseline is always timed, the ratios are to it)
    names = [
        n
        for n in DIFFRAX_VARIANTS
        if not args.methods or n in args.methods or n == DIFFRAX_STRONG_LABEL
    ]
    runners = {n: diffrax_rigid_body(steps, *DIFFRAX_VARIANTS[n]) for n in names}
    if not args.methods or INDEPENDENT in args.methods:
        runners[INDEPENDENT] = _independent_flat_diffrax(steps)
    small = rigid_body_inputs(64, dtype, seed=1)
    reference = diffrax_weak_runner(steps)(*small)
    inputs = rigid_body_inputs(batch, dtype)
    meta.update({"batch": batch, "steps": steps, "dtype": "float64", "rounds": args.rounds})
    records = {}
    for name, fn in runners.items():
        got = fn(*small)
        difference = float(max(jnp.max(jnp.abs(a - b)) for a, b in zip(got[:2], reference[:2])))
        compile_s, run_s = _once(fn, inputs), _once(fn, inputs)
        records[name] = {
            "method": name,
            "max_abs_difference_vs_weak": difference,
            "first_call_s": compile_s,
            "run_s": [run_s],
        }
        print(f"{name:<58} compiled, first rate {batch * steps / run_s:10.3g}", flush=True)
    for _ in range(args.rounds - 1):
        for name, fn in runners.items():
            records[name]["run_s"].append(_once(fn, inputs))
    meta["load_average_at_end"] = os.getloadavg()
    strong = batch * steps / min(records[DIFFRAX_STRONG_LABEL]["run_s"])
    print(f"\nfloat64, batch {batch}, {steps} steps, best of {args.rounds} interleaved rounds")
    print(f"{'formulation':<58}{'body-steps/s':>13}{'vs strong':>11}{'vs weak':>10}")
    weak = records.get(DIFFRAX_WEAK_LABEL)
    weak = batch * steps / min(weak["run_s"]) if weak else float("nan")
    for record in records.values():
        rate = batch * steps / min(record["run_s"])
        record.update({"body_steps_per_s": rate, "vs_strong": rate / strong})
        print(f"{record['method']:<58}{rate:>13.3g}{rate / strong:>10.2f}×{rate / weak:>9.1f}×")
    print(f"load average at the end {meta['load_average_at_end']}")
    base = out / args.out
    base.with_suffix(".json").write_text(
        json.dumps({"meta": meta, "results": list(records.values())}, indent=2)
    )
    print(f"\nwrote {base.with_suffix('.json')}")


def save_results(records, meta, base, plot_fn):
    """`base.json` (meta and records) and `base.png` drawn by `plot_fn`."""
    base.with_suffix(".json").write_text(json.dumps({"meta": meta, "results": records}, indent=2))
    print(f"\nwrote {base.with_suffix('.json')}")
    try:
        plot_fn(records, meta, base.with_suffix(".png"))
        print(f"wrote {base.with_suffix('.png')}")
    except ImportError:
        print("matplotlib not installed: no plot")


def plot_heavy_top(records, meta, path):
    """Body-steps/s of every row, one bar each, coloured by free body / heavy top / diffrax."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = [r["method"] for r in records]
    rates = [r["body_steps_per_s"] for r in records]
    colours = [
        "tab:gray" if "free body" in m else "tab:red" if "diffrax" in m else "tab:blue"
        for m in labels
    ]
    fig, ax = plt.subplots(figsize=(8, 0.4 * len(labels) + 1.2))
    ax.barh(range(len(labels)), rates, color=colours)
    ax.set_yticks(range(len(labels)), labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel(
        f"body-steps / s ({meta['dtype']}, batch {meta['batch']}, {meta['steps']} steps, "
        "final state)"
    )
    ax.set_title(f"heavy top vs free body vs diffrax Tsit5, {meta['device']}", fontsize=9)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def measure(name, fn, inputs, dtype_name, batch: int, steps: int):
    """One row: `fn(*inputs)` timed (`timed`), as a record of the JSON."""
    compile_s, run_s = timed(fn, inputs)
    return {
        "method": name,
        "dtype": dtype_name,
        "batch": batch,
        "steps": steps,
        "compile_s": compile_s,
        "run_s": run_s,
        "body_steps_per_s": batch * steps / run_s,
    }


def timed(fn, args, min_total: float = 0.5, max_repeats: int = 5):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    first = time.perf_counter() - start
    best, total, repeats = np.inf, 0.0, 0
    # Slow runs (diffrax at 1e5 bodies on CPU: minutes) are timed once more, not twice.
    min_repeats = 1 if first > 20 else 2
    while repeats < max_repeats and (repeats < min_repeats or total < min_total):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        elapsed = time.perf_counter() - start
        best, total, repeats = min(best, elapsed), total + elapsed, repeats + 1
    return max(first - best, 0.0), best


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--quick", action="store_true", help="smoke run: batches 1 and 100, 10 steps"
    )
    parser.add_argument("--batches", type=int, nargs="+", default=None)
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--dtypes", nargs="+", default=None, choices=("float64", "float32"))
    parser.add_argument("--methods", nargs="+", default=None, help="names to run (default: all)")
    parser.add_argument(
        "--budget",
        type=float,
        default=60.0,
        help="skip larger batches of a method once one run takes longer than this [s]",
    )
    parser.add_argument(
        "--acceptance",
        action="store_true",
        help="only the CPU acceptance configuration: batch 1e5, 100 steps, float64, every method",
    )
    parser.add_argument(
        "--cpu-devices",
        type=int,
        default=None,
        help="split the CPU into this many XLA devices and shard the batch over them",
    )
    parser.add_argument(
        "--heavy-top",
        action="store_true",
        help="the heavy top (batch 1e5, 100 steps, float64) against diffrax Tsit5 on its "
        "equations and against the free body, in one run",
    )
    parser.add_argument(
        "--diffrax-variants",
        action="store_true",
        help="time every diffrax formulation tried for the baseline (float64, batch 1e5 "
        "unless --batches, 100 steps), interleaved in rounds (--rounds), in one run",
    )
    parser.add_argument(
        "--rounds", type=int, default=2, help="rounds of --diffrax-variants and --heavy-top"
    )
    parser.add_argument(
        "--no-checks", action="store_true", help="--heavy-top without its vmap(simulate) checks"
    )
    parser.add_argument("--out", default=None, help="basename of the JSON and PNG")
    parser.add_argument("--outdir", default=str(pathlib.Path(__file__).parent / "results"))
    args = parser.parse_args()

    device = jax.devices()[0]
    on_cpu = device.platform == "cpu"
    if args.acceptance:
        args.batches = args.batches or [100_000]
        args.steps = args.steps or 100
        args.dtypes = args.dtypes or ["float64"]
        args.methods = args.methods or list(ACCEPTANCE_METHODS)
        args.out = args.out or "throughput_cpu_acceptance"
    if args.heavy_top:
        args.out = args.out or "throughput_heavy_top"
    if args.diffrax_variants:
        args.out = args.out or "throughput_diffrax_variants"
    args.out = args.out or "throughput"
    batches = args.batches or (
        [1, 100] if args.quick else [1, 10, 100, 1_000, 10_000, 100_000, 1_000_000]
    )
    steps = args.steps or (10 if args.quick else 100)
    dtypes = args.dtypes or (["float64", "float32"] if on_cpu else ["float32"])
    n_devices = jax.device_count()
    load = os.getloadavg() if hasattr(os, "getloadavg") else None
    print(
        f"device: {device.device_kind} ({device.platform}, {jax.device_count()} device(s)), "
        f"jax {jax.__version__}, {os.cpu_count()} CPUs, load average {load}"
    )
    print(f"{steps} steps of h = {H}, final state only; body-steps/s (compile time apart)")

    out = pathlib.Path(args.outdir)
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "device": f"{device.device_kind} ({device.platform})",
        "device_count": jax.device_count(),
        "jax": jax.__version__,
        "cpus": os.cpu_count(),
        "machine": platform.machine(),
        "load_average_at_start": load,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "h": H,
        "steps": steps,
        "command": " ".join(["python benchmarks/throughput.py", *sys.argv[1:]]),
    }
    if args.heavy_top:
        return heavy_top_main(args, meta, out)
    if args.diffrax_variants:
        return diffrax_variants_main(args, meta, out)
    records = []
    for dtype_name in dtypes:
        dtype = jnp.dtype(dtype_name)
        runners = methods(steps)
        if args.methods:
            runners = {k: v for k, v in runners.items() if k in args.methods}
        print(
            f"\n{dtype_name}\n{'method':<48}{'batch':>9}{'compile [s]':>13}{'run [s]':>11}{'body-steps/s':>15}"
        )
        for name, fn in runners.items():
            difference = check_against_generic(name, fn, dtype, steps)
            if difference is not None:
                print(
                    f"{name:<48}final state vs "
                    f"{'the weak formulation' if 'diffrax' in name else 'vmap(simulate)'}, "
                    f"64 bodies: max |difference| {difference:.2g}"
                )
            for batch in sorted(batches):
                inputs = rigid_body_inputs(batch, dtype)
                if n_devices > 1:
                    if batch % n_devices:
                        continue
                    inputs = lievi.shard_batch(inputs)
                record = measure(name, fn, inputs, dtype_name, batch, steps)
                record["max_abs_difference_vs_vmap_simulate"] = difference
                records.append(record)
                compile_s, run_s, rate = (
                    record[k] for k in ("compile_s", "run_s", "body_steps_per_s")
                )
                print(
                    f"{name:<48}{batch:>9}{compile_s:>13.2f}{run_s:>11.4f}{rate:>15.3g}", flush=True
                )
                if run_s > args.budget / 10:  # the next batch (×10) would exceed the budget
                    print(
                        f"{'':<48}(larger batches skipped: over the --budget of {args.budget:g} s)"
                    )
                    break
            # Saved after every method, so an interrupted run keeps what it measured.
            meta["load_average_at_end"] = os.getloadavg() if hasattr(os, "getloadavg") else None
            (out / f"{args.out}.json").write_text(
                json.dumps({"meta": meta, "results": records}, indent=2)
            )

    if args.acceptance:
        print(
            f"\nacceptance (float64, batch {batches[-1]}, {steps} steps, final state only, "
            f"{n_devices} device(s); load average now {os.getloadavg()}):"
        )
        meta["acceptance"] = acceptance_summary([r for r in records if r["batch"] == batches[-1]])
    save_results(records, meta, out / args.out, plot)


def plot(records, meta, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dtypes = sorted({r["dtype"] for r in records}, reverse=True)
    fig, axes = plt.subplots(
        1, len(dtypes), figsize=(6 * len(dtypes), 4.5), squeeze=False, sharey=True
    )
    for ax, dtype in zip(axes[0], dtypes):
        for name in dict.fromkeys(r["method"] for r in records):
            rows = [r for r in records if r["method"] == name and r["dtype"] == dtype]
            if rows:
                ax.loglog(
                    [r["batch"] for r in rows],
                    [r["body_steps_per_s"] for r in rows],
                    "o-",
                    label=name,
                )
        ax.set_title(f"{dtype}, {meta['device']}")
        ax.set_xlabel("batch size (bodies)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].set_ylabel(f"body-steps / s ({meta['steps']} steps, final state)")
    axes[0][-1].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


if __name__ == "__main__":
    main()
