#!/bin/bash
# GarTrans `garmentgnn predict` on a 60-frame walk of a 288-vertex skirt, twice; prints the
# summary line of each run.  Run from the repository root:
#   bash docs/results/predict_compile/measure.sh LABEL SRC [predict flags ...]
# LABEL names the logs, SRC is the source tree the package is imported from (PYTHONPATH).
label=$1; src=$2; shift 2
runs=${RUNS:-/tmp/predict_compile}
mkdir -p "$runs"
for rep in 1 2; do
  log="$runs/$label-$rep.log"
  OMP_NUM_THREADS=2 PYTHONPATH=$src /usr/bin/time -f "wall %e s" python -W ignore -c \
    "import sys; from garmentgnn.cli import main; sys.exit(main(sys.argv[1:]))" predict \
    --ckpt tests/data/gartrans_learn.ckpt --garment skirt --resolution 288 --motion walk \
    --frames 60 --out "$runs/$label-$rep" "$@" > "$log" 2>&1
  echo "$label rep $rep: $(grep -E 'frame-parallel' "$log") | $(grep wall "$log")"
done
