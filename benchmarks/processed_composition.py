"""Processed compositions of the heavy top's splitting: order, and cost at equal error.

An experiment, not a lievi integrator: does processing (Blanes, Casas & Murua, "Composition
methods for differential equations with processing", SIAM J. Sci. Comput. 27 (2006),
1817–1843) make the structure-preserving high-order methods cheaper on the heavy top?
A processed method is `ψ_h = P ∘ K_h ∘ P⁻¹`: `N` steps cost `N` kernels `K_h` and two
processors, `P⁻¹` once at the start and `P` at each output. The kernel is a symmetric
composition of the symmetric basic method `S_h` (`LiePoissonSplitting`) with fewer or
better-conditioned stages than a plain composition of the same effective order; `P` is a
composition of `S` too, so the momentum map and the Casimirs are kept to round-off.

Coefficients (`KERNELS`, `PROCESSORS`): Blanes, Casas & Murua (2006), as tabulated in
Blanes, Casas & Murua, "Splitting methods for differential equations", Acta Numerica
(2024; arXiv 2401.01722), Table 8.1: order 6 with an 11- and a 13-stage kernel (12-stage
processors), order 8 with a 13-stage kernel (20-stage processor). Their processor is listed
as `z_1 … z_r` with `Σ z_i = 0` and `z_{r+i} = −z_i`; as a composition applied first-to-last
the processor is `S_{y_1 h}, …, S_{y_{2r} h}` with `y = reverse(−z, z)` (`processor`):
the order check below decides the convention, the other three give order 4 only.

Measured (one core, float64, the heavy top of `work_precision.py`, T = 20, errors the
largest over the saved times and the reference bodies): the observed order (log–log fit of
the final error at T = 2 against h); the CPU cost of each method at each h, the processors
included (`P⁻¹` once, `P` at each of the 25 saves); the kernel alone; interpolated cost at
equal attitude and energy errors against `Composition(LiePoissonSplitting(), 6 | 8)` and
diffrax `Dopri8` (constant steps, the batch in the state, as in `work_precision.py`).

Result (`results/processed_composition.json`, a loaded 2-core machine, batch 256; cost in
CPU s per million bodies): observed orders 6.00, 6.02, 8.02. At equal attitude error
1e-8 … 1e-11 the 13-stage order-8 kernel costs 0.82–0.92× `Composition(…, 8,
"sofroniou-spaletta")` and 0.82–0.85× Kahan–Li's, at equal energy error 0.72–0.83×, when
`P` is applied only at the end; the 11-stage order-6 kernel 0.6× Kahan–Li's order 6. With `P` at
each of 25 saves they cost more than the plain compositions down to ~1e-10. Diffrax
`Dopri8` stays cheaper at T = 20: 1.5× cheaper at attitude 1e-10, 2.3× at energy 1e-10.
At T = 2000 (`--long`, the largest over 25 saves) the processed output's energy error is
1e-11 for the order-8 kernel at h = 0.2 (`Composition(…, 8)`: 1.6e-11, 8e-13 for
Sofroniou–Spaletta's); the kernel's own output, unprocessed, is off by ~3e-7, scaling as
h⁴: the processor is what brings it to order 6 or 8.

    python benchmarks/processed_composition.py              # ~10 min on one core
    python benchmarks/processed_composition.py --long       # energy to T = 2000
    python benchmarks/processed_composition.py --summarise  # the tables from the JSON
"""

from __future__ import annotations

import json
import pathlib
import sys

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import work_precision as wp  # noqa: E402  (pins one core, enables x64)

import lievi  # noqa: E402

PROBLEM = "heavy top"


def _palindrome(half):
    return tuple(half) + tuple(reversed(half[:-1]))


def _kernel(half_without_middle):
    """A symmetric kernel from its first stages; the middle one makes `Σγ = 1`."""
    half = list(half_without_middle)
    return _palindrome(half + [1.0 - 2.0 * sum(half)])


def _processor(z):
    """`(z_1, …, z_r)`, the one `None` being the entry that makes `Σ z_i = 0`; the
    composition's stages, first applied first."""
    z = np.array([-sum(x for x in z if x is not None) if x is None else x for x in z])
    return tuple(float(x) for x in np.concatenate([-z, z])[::-1])


A6 = 0.1705768865009222157
A8 = (0.168, 0.168, 0.585550530805562, -0.460090457516872, 0.172863148729731, 0.179664539695039)
KERNELS = {
    "BCM 6/11": _kernel([A6] * 4 + [-0.423366140892658048]),
    "BCM 6/13": _kernel([0.125696288720106] * 4 + [0.148070660114965, -0.350856370823828]),
    "BCM 8/13": _kernel(list(A8)),
}
PROCESSORS = {
    "BCM 6/11": _processor([None, -0.20621953139126, 0.23651387483203, 0.09086982276241,
                            0.24687306977659, -0.1]),
    "BCM 6/13": _processor([0.1, 0.225080298761176, 0.191244694511161, -0.212763792194890,
                            -0.09660157306582295, None]),
    "BCM 8/13": _processor([None, -0.008488123494574411, -0.337188967354338, 0.333987768164597,
                            0.588351189003849, 0.162324207599241, -0.511744926116413,
                            0.236885952363384, 0.598212975943381, -0.543415765371656]),
}  # fmt: skip
ORDERS = {"BCM 6/11": 6, "BCM 6/13": 6, "BCM 8/13": 8}
PLAIN = {"KL 6": (6, "kahan-li"), "SS 6": (6, "sofroniou-spaletta"),
         "KL 8": (8, "kahan-li"), "SS 8": (8, "sofroniou-spaletta")}  # fmt: skip


def composition(coefficients):
    """`Composition` of the splitting with arbitrary stages. Its constructor only takes the
    published plain schemes; the fields are set after it, so that the fused batch kernel
    (`own_step`) is kept — an experiment's shortcut, not an API."""
    c = lievi.Composition(lievi.LiePoissonSplitting(), 6)
    object.__setattr__(c, "coefficients", tuple(float(x) for x in coefficients))
    return c


def inverse(coefficients):
    """`S` symmetric: `(S_{y_s h} ∘ … ∘ S_{y_1 h})⁻¹ = S_{−y_1 h} ∘ … ∘ S_{−y_s h}`."""
    return tuple(-x for x in reversed(coefficients))


def processed_run(name, h, batch, t1, repeats, kernel_only=False):
    """`P⁻¹` at the start, the kernel's steps with the 25 saves, `P` at each save: one jit."""
    system = wp.system_of(PROBLEM)
    g0, m0 = wp.initial_states(PROBLEM, batch)
    n = int(round(t1 / h))
    every = wp.sample_every(n)
    kernel = composition(KERNELS[name])
    P, P_inv = composition(PROCESSORS[name]), composition(inverse(PROCESSORS[name]))

    def apply(method, g, m):
        # One step of the processor on every state, on the fused batch path as the kernel.
        sol = lievi.simulate_batch(
            system, method, g, m, h=h, n_steps=1, throw=False,
            save=lievi.Save(g=True, m=True, stats=False, every=1),
        )  # fmt: skip
        return sol.g[:, -1], sol.m[:, -1]

    @jax.jit
    def run(m0):
        g = jnp.broadcast_to(jnp.asarray(g0), (batch, 3, 3))
        if not kernel_only:
            g, m = apply(P_inv, g, m0)
        else:
            m = m0
        sol = lievi.simulate_batch(
            system, kernel, g, m, h=h, n_steps=n, throw=False,
            save=lievi.Save(g=True, m=True, stats=False, every=every),
        )  # fmt: skip
        g, m = sol.g[:, 1:], sol.m[:, 1:]
        if not kernel_only:
            shape = g.shape
            g, m = apply(P, g.reshape(-1, 3, 3), m.reshape(-1, 3))
            g, m = g.reshape(shape), m.reshape(shape[:-1])
        return g, m, sol.result

    (g, m, result), seconds = wp.best_cpu_seconds(run, (jnp.asarray(m0),), repeats)
    return g, m, seconds, bool(np.all(np.asarray(result) == 0))


def observed_order(name, hs=(0.4, 0.2, 0.1), t1=2.0):
    """Final-state error of `P ∘ K^N ∘ P⁻¹` (one body) at T = `t1` against the reference."""
    system = wp.system_of(PROBLEM)
    g0, m0 = wp.initial_states(PROBLEM, 1)
    g0, m0 = jnp.asarray(g0), jnp.asarray(m0[0])
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, jnp.asarray([0.0, t1]))
    kernel = composition(KERNELS[name])
    P, P_inv = composition(PROCESSORS[name]), composition(inverse(PROCESSORS[name]))
    errs = []
    for h in hs:
        n = int(round(t1 / h))

        @jax.jit
        def run(g, m, h=h, n=n):
            g, m = P_inv.step(system, g, m, h)[:2]
            g, m = jax.lax.fori_loop(
                0, n, lambda i, s: kernel.step(system, s[0], s[1], h)[:2], (g, m)
            )
            return P.step(system, g, m, h)[:2]

        g, m = run(g0, m0)
        errs.append(float(jnp.linalg.norm(g - g_ref[-1]) + jnp.linalg.norm(m - m_ref[-1])))
    slope = float(np.polyfit(np.log(hs), np.log(errs), 1)[0])
    return dict(hs=list(hs), errors=errs, fitted_order=slope)


def long_energy(t1=2000.0, batch=64, hs=(0.4, 0.2)):
    """The largest relative energy error over the saves up to `t1` (no reference needed):
    the processed output against the plain compositions, and the kernel's own (unprocessed)
    output, whose energy error is that of an order-4 method."""
    system = wp.system_of(PROBLEM)
    g0, m0 = wp.initial_states(PROBLEM, batch)
    H0 = np.asarray(lievi.diagnostics.energy(system, jnp.asarray(g0), jnp.asarray(m0)))

    def worst(g, m):
        H = np.asarray(lievi.diagnostics.energy(system, jnp.asarray(g), jnp.asarray(m)))
        return float(np.max(np.abs(H - H0[:, None]) / np.abs(H0[:, None])))

    rows = []
    for h in hs:
        for name in KERNELS:
            for kernel_only in (False, True):
                g, m, sec, ok = processed_run(name, h, batch, t1, 1, kernel_only)
                label = f"{name} kernel alone" if kernel_only else name
                rows.append(dict(method=label, h=h, ok=ok, seconds=sec, energy=worst(g, m)))
                print(rows[-1], flush=True)
        for name, (order, scheme) in PLAIN.items():
            integrator = lievi.Composition(lievi.LiePoissonSplitting(), order, scheme)
            g, m, sec, ok, _ = wp.lievi_run(PROBLEM, None, h, batch, t1, 1, integrator)
            rows.append(dict(method=name, h=h, ok=ok, seconds=sec, energy=worst(g, m)))
            print(rows[-1], flush=True)
    return rows


def summarise(results, batch):
    """Cost (CPU s per million bodies) at equal attitude and energy error, interpolated
    log–log between each method's runs: with the processor at each of the 25 saves, and
    with the kernel's steps alone (a run that outputs only its end: `N` kernels and two
    processors, the processors' 2·12–2·20 stages neglected)."""
    methods = list(dict.fromkeys(r["method"] for r in results["rows"]))
    for key, seconds in (("", "seconds"), ("_final_only", "kernel_seconds")):
        results["cost_at_equal_error" + key] = {
            q: {
                f"{t:.0e}": {
                    name: wp.cost_at(
                        [
                            (r[seconds] / batch * 1e6, r[q])
                            for r in results["rows"]
                            if r["method"] == name
                        ],
                        t,
                    )  # fmt: skip
                    for name in methods
                }
                for t in [10.0**-k for k in range(4, 12)]
            }
            for q in ("attitude", "energy")
        }


def timed(name, h, batch, t1, repeats):
    """`(g, m, seconds, kernel seconds, ok, stages)` of one method at one `h`: a processed
    method (its kernel alone timed too), a plain composition, or diffrax `Dopri8` with
    constant steps and the batch in the state (`work_precision.diffrax_run`)."""
    if name in PLAIN:
        integrator = lievi.Composition(lievi.LiePoissonSplitting(), *PLAIN[name])
        g, m, sec, ok, _ = wp.lievi_run(PROBLEM, None, h, batch, t1, repeats, integrator)
        return g, m, sec, sec, ok, len(integrator.coefficients)
    if name == "Dopri8":
        g, m, sec, ok, _ = wp.diffrax_run(PROBLEM, name, h, False, batch, t1, repeats)
        return g, m, sec, sec, ok, None
    g, m, sec, ok = processed_run(name, h, batch, t1, repeats)
    kernel_sec = processed_run(name, h, batch, t1, repeats, kernel_only=True)[2]
    return g, m, sec, kernel_sec, ok, len(KERNELS[name])


def main():
    if "--summarise" in sys.argv:
        out = pathlib.Path(__file__).parent / "results" / "processed_composition.json"
        results = json.loads(out.read_text())
        summarise(results, 256)
        out.write_text(json.dumps(results, indent=1))
        return
    if "--long" in sys.argv:
        out = pathlib.Path(__file__).parent / "results" / "processed_composition_long.json"
        out.write_text(json.dumps(dict(T=2000.0, batch=64, rows=long_energy()), indent=1))
        return
    out = pathlib.Path(__file__).parent / "results" / "processed_composition.json"
    batch, repeats, t1 = 256, 3, wp.T_SHORT
    ref = wp.reference(PROBLEM, 4, t1)
    results = dict(orders={}, rows=[], per_step_ns={})
    for name in KERNELS:
        results["orders"][name] = observed_order(
            name, (0.4, 0.2, 0.1) if ORDERS[name] == 6 else (0.5, 0.4, 0.25, 0.2)
        )
        print(name, results["orders"][name], flush=True)
        # Wrong or misread coefficients show as order 4 (the kernel's own): stop there.
        if abs(results["orders"][name]["fitted_order"] - ORDERS[name]) > 0.1:
            raise RuntimeError(f"{name}: observed order {results['orders'][name]}")
    hs = [0.8, 0.4, 0.2, 0.1, 0.05]
    methods = [*KERNELS, *PLAIN, "Dopri8"]
    for name in methods:
        for h in hs:
            n = int(round(t1 / h))
            g, m, sec, kernel_sec, ok, stages = timed(name, h, batch, t1, repeats)
            row = dict(method=name, h=h, stages=stages, ok=ok, seconds=sec,
                       kernel_seconds=kernel_sec, ns_per_body_step=1e9 * sec / (batch * n),
                       **wp.errors(PROBLEM, g, m, ref))  # fmt: skip
            results["rows"].append(row)
            print(row, flush=True)
    for B in (256, 4096):
        for name in methods:
            h = 0.2
            kernel_sec = timed(name, h, B, t1, repeats)[3]
            results["per_step_ns"][f"{name} B={B}"] = 1e9 * kernel_sec / (B * int(round(t1 / h)))
            print(name, B, results["per_step_ns"][f"{name} B={B}"], flush=True)
    summarise(results, batch)
    out.write_text(json.dumps(results, indent=1))
    print(json.dumps(results["cost_at_equal_error"], indent=1))
    print(json.dumps(results["cost_at_equal_error_final_only"], indent=1))


if __name__ == "__main__":
    sys.exit(main())
