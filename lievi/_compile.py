"""How the eager run's programs are compiled: XLA's options chosen by the bodies a step advances.

XLA's CPU backend turns each fused group of operations into a loop, by default with its
"fusion emitters". A closed-form step (the SE(3) DEP kernel, a system of several bodies) is
hundreds to thousands of scalar operations, many small fused loops, and those emitters
take longer to compile them than XLA's older loop emitter does. Where a step advances one
or two bodies, nothing is vectorised across a batch, and the older emitter's program runs
as fast; from eight bodies on, the default's runs faster for the structure-of-arrays
kernels (free bodies). So the blocks of steps of an eager run (`_block` in
`_simulate_kernel` and `_simulate_generic`) are compiled with
`SMALL_RUN_OPTIONS` on CPU for a run of at most `SMALL_RUN_BODIES` bodies, and for a run
of systems of several bodies (`lievi.RigidBodies`, `lievi.RigidRotors`: a coupling
potential, each system's step under `jax.vmap` for a batch) whatever their number; with
XLA's defaults otherwise. Under the caller's `jax.jit` or `jax.grad` they are part of the
caller's program, compiled with its options.

Measured on a 2-core CPU, float64 (docs/compile-times.md): first `simulate` calls 0.06–1.3 s
(7–40 %) sooner (one `RigidBodySE3` with `DEP()` 3.06 → 2.57 s, the binary asteroid on
SE(3)² 4.49 → 3.42 s), one-system run times 0.97–1.01×. With the option set for the whole
process, a batch of free SE(3) bodies with `DEP()` ran as fast at 2 bodies, at 0.8× at 8
and at 0.55× at 64: hence `SMALL_RUN_BODIES`. For systems of several bodies (batches of
64 and 1024 binary asteroids, one system of 512 or 2048 Lennard-Jones bodies, a batch of
coupled rotors) the first calls took 0.64–0.98× and the runs 0.61–1.04× their time with
the defaults, but for one run at 1.11× (64 binaries with the composition, every step
saved; `python benchmarks/coupled_emitter.py`): hence the systems of several bodies.

The programs an eager call runs once (its input checks, a run's set-up and the join of
its blocks, the check of its result) take the option whatever the call's size
(`once_per_call`).

The option is XLA's own: if the installed XLA does not know it, every program keeps the
defaults (`small_run_options_apply`).
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp

SMALL_RUN_OPTIONS = {"xla_cpu_use_fusion_emitters": False}
# The most bodies (batch × bodies of a system) a small run steps together: the measured
# crossing point lies between 2 (as fast) and 8 (0.8×).
SMALL_RUN_BODIES = 2


@functools.cache
def small_run_options_apply() -> bool:
    """Whether the default backend is a CPU whose XLA accepts `SMALL_RUN_OPTIONS` (tried
    once, on a program of one addition)."""
    if jax.default_backend() != "cpu":
        return False
    try:
        jax.jit(lambda x: x + 1, compiler_options=SMALL_RUN_OPTIONS).lower(0.0).compile()
    except Exception:  # an unknown option or a `jax.jit` without `compiler_options`
        return False
    return True


def bodies_of(elements) -> int:
    """The bodies a run steps together, from its elements' shape `(…, n, n)`: one for a
    single body, the product of the leading axes for a batch or a system of several."""
    return math.prod(jnp.shape(elements)[:-2])


def bodies_per_system(system) -> int:
    """The bodies of one system: one, or several (`lievi.RigidBodies`), from the shape of
    its configuration (`AbstractLieSystem.element_shape`)."""
    return math.prod(system.element_shape()[:-2])


class RunProgram:
    """A run's program (`eqx.filter_jit` of `fn`) in two compilations: with
    `SMALL_RUN_OPTIONS` for a run of at most `SMALL_RUN_BODIES` bodies or of systems of
    several bodies, XLA's defaults otherwise. `for_bodies(n, per_system)` is the one for a
    run of `n` bodies in systems of `per_system` bodies each."""

    def __init__(self, fn):
        self.default = eqx.filter_jit(fn)
        self.small = eqx.filter_jit(fn, compiler_options=SMALL_RUN_OPTIONS)

    def for_bodies(self, n: int, per_system: int = 1):
        if n <= SMALL_RUN_BODIES or per_system > 1:
            return self.small_where_applies()
        return self.default

    def small_where_applies(self):
        """`small` where `SMALL_RUN_OPTIONS` apply (`small_run_options_apply`), else
        `default`."""
        return self.small if small_run_options_apply() else self.default


def tracing() -> bool:
    """Whether a JAX transformation (`jit`, `vmap`, `grad`, a loop's body) is tracing the
    caller: JAX's own test, private, hence guarded (without it, assume so)."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:
        return True
    return not trace_state_clean()


def once_per_call(fn):
    """`eqx.filter_jit(fn)` for a program an eager call runs once, whatever its size: its
    input checks, its set-up, the join of its blocks, the check of its result. Compiled
    with `SMALL_RUN_OPTIONS` where they apply (`small_run_options_apply`): the program
    runs once a call, a pass over the call's inputs or outputs, and its compile is most
    of what it costs. Measured on the 2-core CPU (`benchmarks/once_per_call.py`,
    docs/compile-times.md): in first `simulate_batch` calls of 64 bodies they compiled in
    0.50–0.77 s with the option against 0.68–1.08 s without, and calls of 10⁴ bodies that
    lean on them (every step saved) ran at 0.98–1.03× the time."""
    program = RunProgram(fn)

    @functools.wraps(fn)
    def call(*args, **kwargs):
        # Under a transformation the program is part of the caller's, compiled with its
        # options (and JAX accepts `compiler_options` only on an outermost `jax.jit`).
        chosen = program.default if tracing() else program.small_where_applies()
        return chosen(*args, **kwargs)

    call.program = program
    return call
