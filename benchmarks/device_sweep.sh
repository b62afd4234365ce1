#!/usr/bin/env bash
# The GPU figures of docs/performance.md in one run (a machine with one NVIDIA GPU and
# jax, equinox, optax, diffrax installed; lievi from this checkout). Writes into $OUT
# (default benchmarks/results): the throughput sweep of every fast method in float32 and
# float64 up to 10⁷ bodies, against diffrax Tsit5 (throughput_<tag>_float{32,64}.json and
# .png), batched gradients through the fast path (gradients_batch_<tag>.json), interacting
# bodies (rigid_bodies_throughput_<tag>.json: 10⁵ binaries, one system of 10⁴ bodies with
# all pairs and with a neighbour list, gradients), and the log. PARTS picks the parts.
#
#     TAG=h100 bash benchmarks/device_sweep.sh
#     TAG=h100 PARTS=bodies bash benchmarks/device_sweep.sh           # interacting bodies only
#     BATCHES="100 1000" STEPS=10 bash benchmarks/device_sweep.sh   # a smoke run
#
# SWEEP_METHODS and GRAD_METHODS ('|'-separated row names) narrow the sweep and the
# gradients; BODY_ARGS is added to rigid_bodies_throughput.py's arguments (e.g.
# "--gradient-only"); PART_TIMEOUT (seconds) ends any one part that runs longer, so that
# the parts after it still run inside a lease.
set -uo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON:-python3}" OUT="${OUT:-benchmarks/results}" TAG="${TAG:-gpu}" STEPS="${STEPS:-100}"
BATCHES="${BATCHES:-100000 1000000 10000000}" GRAD_BODIES="${GRAD_BODIES:-1000000}"
PARTS="${PARTS:-sweep gradients bodies}" SYSTEMS="${SYSTEMS:-100000}" NBODIES="${NBODIES:-10000}"
SWEEP_METHODS="${SWEEP_METHODS:-DEP exp|DEP cayley|Moser-Veselov|splitting|RK4|RKMK4|splitting ∘ 4|splitting ∘ 6|diffrax Tsit5|DEP exp, vmap(simulate)}"
GRAD_METHODS="${GRAD_METHODS:-DEP exp|splitting|RKMK4|splitting ∘ 4}" BODY_ARGS="${BODY_ARGS:-}"
IFS='|' read -r -a sweep_methods <<<"$SWEEP_METHODS"
IFS='|' read -r -a grad_methods <<<"$GRAD_METHODS"
limit=(timeout "${PART_TIMEOUT:-0}")  # timeout 0: no limit
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
log="$OUT/device_sweep_$TAG.log"
mkdir -p "$OUT"
{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || true
  "$PY" -c "import jax, equinox, optax, diffrax; print('jax', jax.__version__, 'equinox', equinox.__version__, 'diffrax', diffrax.__version__, jax.devices())"
  if [[ " $PARTS " == *" sweep "* ]]; then
    for dtype in float32 float64; do
      # --budget 10: a method's larger batches are skipped once one run takes over 1 s.
      # shellcheck disable=SC2086
      "${limit[@]}" "$PY" benchmarks/throughput.py --batches $BATCHES --steps "$STEPS" \
        --dtypes "$dtype" --budget 10 --outdir "$OUT" --out "throughput_${TAG}_$dtype" \
        --methods "${sweep_methods[@]}"
    done
  fi
  if [[ " $PARTS " == *" gradients "* ]]; then
    "${limit[@]}" "$PY" benchmarks/gradients.py --batch --bodies "$GRAD_BODIES" \
      --steps "$STEPS" --methods "${grad_methods[@]}" --outdir "$OUT" --out "gradients_batch_$TAG"
  fi
  if [[ " $PARTS " == *" bodies "* ]]; then
    # shellcheck disable=SC2086
    "${limit[@]}" "$PY" benchmarks/rigid_bodies_throughput.py --systems "$SYSTEMS" \
      --bodies "$NBODIES" --neighbor-bodies "$NBODIES" --gradient-bodies 1000 \
      --steps "$STEPS" --out "rigid_bodies_throughput_$TAG" --outdir "$OUT" $BODY_ARGS
  fi
} 2>&1 | tee -a "$log"
