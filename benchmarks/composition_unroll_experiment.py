"""An experiment: `Composition`'s stage loop as the loop it is, or unrolled, forward and gradient.

The batched gradient of `splitting ∘ 4` costs 8.5× its forward run on an H200
(`gradients.py --batch`). This replaces `CompositionKernel.step` (private, patched in this
process only) by the same stages in `lax.scan(..., unroll=True)` and times both, the loop
a second time last: a batch of BODIES free rigid bodies, 100 steps, float64, wall time,
best of 3 after a warm-up.

    python benchmarks/composition_unroll_experiment.py BODIES   # e.g. 1000000 on a GPU

On the H200 both took the same time to three digits
(`benchmarks/results/composition_unroll_h200.log`).
"""

from __future__ import annotations

import pathlib
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import lievi  # noqa: E402
from lievi._kernels import _composition  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
import gradients  # noqa: E402

STEPS = 100
LOOP = _composition.CompositionKernel.step


def unrolled(self, params, g, m, alive):
    """`CompositionKernel.step` with the stages unrolled (`unroll=True`)."""
    return self.stages(params, g, m, alive, unroll=True)


def timed(fn, args):
    """`(compile seconds, best of 3 run seconds)`."""
    start = time.perf_counter()
    compiled = fn.lower(*args).compile()
    compile_s = time.perf_counter() - start
    jax.block_until_ready(compiled(*args))
    best = np.inf
    for _ in range(3):
        start = time.perf_counter()
        jax.block_until_ready(compiled(*args))
        best = min(best, time.perf_counter() - start)
    return compile_s, best


def main():
    bodies = int(sys.argv[1])
    args = gradients.batch_inputs(bodies)
    for label, step in (("loop", LOOP), ("unrolled", unrolled), ("loop again", LOOP)):
        _composition.CompositionKernel.step = step
        integrator = lievi.Composition(lievi.LiePoissonSplitting(), order=4)
        loss = gradients.batch_loss(integrator, STEPS, True, False)
        fc, fr = timed(jax.jit(loss), args)
        gc, gr = timed(jax.jit(jax.value_and_grad(loss)), args)
        print(
            f"{label:10s} forward {fr:.4f} s (compile {fc:.1f}), grad {gr:.4f} s "
            f"(compile {gc:.1f}), grad/fwd {gr / fr:.2f}, fwd body-steps/s {bodies * STEPS / fr:.3g}",
            flush=True,
        )


if __name__ == "__main__":
    main()
