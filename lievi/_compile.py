"""How the eager run's programs are compiled: XLA's options chosen by the bodies a step advances.

XLA's CPU backend turns each fused group of operations into a loop, by default with its
"fusion emitters". A closed-form step (the SE(3) DEP kernel, a system of several bodies) is
hundreds to thousands of scalar operations, many small fused loops, and those emitters
take longer to compile them than XLA's older loop emitter does. Where a step advances one
or two bodies, nothing is vectorised across a batch, and the older emitter's program runs
as fast; from eight bodies on, the default's runs faster. So the programs that hold a run's
steps (`_simulate_kernel._block`, `_simulate_generic._block`) are compiled with
`SMALL_RUN_OPTIONS` for a run of at most `SMALL_RUN_BODIES` bodies on CPU, and with XLA's
defaults otherwise.

Measured on a 2-core CPU, float64, the option set for the whole process (`XLA_FLAGS`), a
first `simulate` of 100 steps and then the best of five of 2000 steps, the final state
kept: one `RigidBodySE3`, `DEP()` first call 3.1 → 2.2–2.5 s, run 8.7 → 9.3 ms; its
Cayley chart 2.1–2.3 → 1.4–1.6 s, 6.6–7.3 → 6.4–7.5 ms; `RKMK8` 4.1–4.3 → 2.9–3.2 s,
33–34 → 31 ms; the binary asteroid (`RigidBodies`, two bodies) with `DEP()` 4.8 → 3.4 s,
18.5 → 17.3 ms; a batch of SE(3) bodies runs 1.0× as fast at 2 bodies, 0.8× at 8 and
0.55× at 64. `benchmarks/compile_time.py` records the effect of this module itself.

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


class RunProgram:
    """A run's program (`eqx.filter_jit` of `fn`) in two compilations: with
    `SMALL_RUN_OPTIONS` for a run of at most `SMALL_RUN_BODIES` bodies, XLA's defaults
    otherwise. `for_bodies(n)` is the one for a run of `n` bodies."""

    def __init__(self, fn):
        self.default = eqx.filter_jit(fn)
        self.small = eqx.filter_jit(fn, compiler_options=SMALL_RUN_OPTIONS)

    def for_bodies(self, n: int):
        if n <= SMALL_RUN_BODIES and small_run_options_apply():
            return self.small
        return self.default
