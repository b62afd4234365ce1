"""Why the CPU fast paths stop short of the flop limit: XLA fusion duplicates work.

For each rigid-body fast path (one step, 1000 bodies, float64) this prints the
elementwise operation count of the traced program (`jit(...).lower().cost_analysis()`)
against that of the optimised, fused program XLA runs (`.compile().cost_analysis()`),
per body-step, and the number and total size (HLO lines) of the fused computations. A
ratio above 1 is work XLA's fusion pass recomputes: it duplicates cheap elementwise
producers into every consumer rather than storing them, so the 12 outputs of a step
(9 entries of g, 3 of Π) each re-evaluate much of the shared arithmetic.

    python benchmarks/fusion_report.py

Writes `benchmarks/results/fusion_report.json`. (Static counts: the Newton tail's
while-loop body is counted once, though it rarely runs.)
"""

from __future__ import annotations

import json
import pathlib
import re
import sys

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402

sys.path.insert(0, str(pathlib.Path(__file__).parent))
import throughput  # noqa: E402

METHODS = ("DEP exp", "DEP cayley", "Moser-Veselov", "splitting", "RK4")
BATCH = 1000


def cost(analysis):
    analysis = analysis[0] if isinstance(analysis, list) else analysis
    return analysis["flops"] / BATCH


def main():
    print(
        f"device: {jax.devices()[0].device_kind}, jax {jax.__version__}; one step, {BATCH} bodies, float64"
    )
    print(
        f"{'method':<16}{'traced ops/body':>17}{'fused ops/body':>16}{'ratio':>7}{'fusions':>9}{'fused HLO lines':>17}"
    )
    rows = []
    for name in METHODS:
        fn = throughput.methods(1)[name]
        lowered = fn.lower(*throughput.rigid_body_inputs(BATCH, jnp.float64))
        compiled = lowered.compile()
        traced, fused = cost(lowered.cost_analysis()), cost(compiled.cost_analysis())
        text = compiled.as_text()
        computations = [
            c for c in re.split(r"\n(?=\S)", text) if re.match(r"%?fused_computation", c)
        ]
        lines = sum(c.count("\n") for c in computations)
        rows.append(
            {
                "method": name,
                "traced_ops_per_body_step": traced,
                "fused_ops_per_body_step": fused,
                "ratio": fused / traced,
                "fused_computations": len(computations),
                "fused_hlo_lines": lines,
            }
        )
        print(
            f"{name:<16}{traced:>17.0f}{fused:>16.0f}{fused / traced:>7.1f}{len(computations):>9}{lines:>17}"
        )
    out = pathlib.Path(__file__).parent / "results" / "fusion_report.json"
    out.write_text(
        json.dumps(
            {"device": jax.devices()[0].device_kind, "jax": jax.__version__, "rows": rows}, indent=2
        )
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
