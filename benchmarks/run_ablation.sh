#!/usr/bin/env bash
# The ablation of issue 30, judged by the detector: every arm at 60 training frames (25 % of the
# pool) against cda and paper (the arms of the deleted sensor-true steps: docs/detection.md).
# One command; finished runs are cached in --work by their samples, so a grid stopped half-way
# (or run again after a change that leaves augmentation alone) goes on where it was. Extra arguments go to bench_detection.py, e.g.
#   bash benchmarks/run_ablation.sh --work /tmp/det --seeds 0 1          # screening, CPU
#   bash benchmarks/run_ablation.sh --work /tmp/det --device cuda --workers 12   # a lent GPU
set -euo pipefail
cd "$(dirname "$0")/.."
arms=(
  cda paper
  # paper without the obstacle check's allowance: no frame return in the box
  paper:placement.max_non_ground_points=0
  # labels: construction keeps no point outside the source box, so the label is the source box
  # (by default points up to 5 cm outside are kept and the label grows to hold them)
  paper:construction.margin=0.0
  # the paper's own ablations: construction, location, heading range (Tables 4-6)
  paper:construction.max_iterations=0
  paper:construction.max_iterations=1
  paper:placement.location=source
  paper:placement.heading_range=0.7853981633974483
  paper:placement.heading_range=1.5707963267948966
  paper:placement.heading_range=2.356194490192345
)
exec python benchmarks/bench_detection.py --fractions 0.25 --arms "${arms[@]}" "$@"
