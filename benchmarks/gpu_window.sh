#!/usr/bin/env bash
# One GPU window (docs/bench.md, "A GPU window"): run from the repository root on the bare
# GPU machine, with build/gpu_window/ (made by benchmarks/gpu_window_prepare.py) carried:
#
#   bash benchmarks/gpu_window.sh
#
# Installs the carried wheels the image lacks (into a temporary folder, nothing from a
# network), puts this tree's src/ on PYTHONPATH, then hands the time left to
# benchmarks/gpu_window.py, which writes OUT/summary.{md,json} and one OUT/<stage>.tar.gz
# per stage.  Environment:
#   GPU_WINDOW_BUDGET_S  seconds for the whole run, set-up included (default 550: it ends
#                        before 9.5 minutes)
#   DEVICE               cuda (default) or cpu (a dry run on a machine without a GPU)
#   OUT                  where the results go (the device tool sets it; default
#                        /tmp/gpu_window_out)
#   PYTHON               the interpreter (default python3, the image's torch)
#   GPU_WINDOW_DIR       the carried folder (default build/gpu_window)
#   GPU_WINDOW_SCRIPT    the script handed the time left (default benchmarks/gpu_window.py;
#                        benchmarks/mgn_levers.py takes the same options)
# Further arguments go to benchmarks/gpu_window.py (e.g. --stages inference).
set -u
start=$(date +%s)
budget=${GPU_WINDOW_BUDGET_S:-550}
dir=${GPU_WINDOW_DIR:-build/gpu_window}
py=${PYTHON:-python3}
out=${OUT:-/tmp/gpu_window_out}
mkdir -p "$out"
work=$(mktemp -d /tmp/gpu_window.XXXXXX)
log=$work/setup.log
export PYTHONUNBUFFERED=1
{
    echo "python: $($py -V 2>&1) at $(command -v "$py")"
    if $py -c "import trimesh, meshio, jsonargparse, docstring_parser, typeshed_client" \
            2>/dev/null; then
        echo "wheels: not needed (every package imports)"
    elif ls "$dir"/wheels/*.whl >/dev/null 2>&1; then
        echo "wheels: $(cd "$dir/wheels" && ls *.whl | tr '\n' ' ')"
        $py -m pip install -q --no-index --no-deps --no-compile --no-cache-dir \
            --target "$work/site" "$dir"/wheels/*.whl \
            && export PYTHONPATH="$work/site${PYTHONPATH:+:$PYTHONPATH}"
    else
        echo "wheels: none in $dir/wheels and some packages are missing; run"
        echo "  python benchmarks/gpu_window_prepare.py   (where pip reaches an index)"
    fi
    export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}"
    $py -c "import garmentgnn, garmentgnn.training, lightning.pytorch.cli, torch; \
print('garmentgnn', garmentgnn.__version__, 'torch', torch.__version__, \
'cuda', torch.cuda.is_available())" || echo "garmentgnn does not import: see above"
    command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version \
        --format=csv,noheader
    echo "set-up: $(( $(date +%s) - start )) s"
} > "$log" 2>&1
cat "$log"
left=$(( budget - ($(date +%s) - start) ))
exec $py "${GPU_WINDOW_SCRIPT:-benchmarks/gpu_window.py}" --dir "$dir" --out "$out" --work "$work" \
    --device "${DEVICE:-cuda}" --budget-s "$left" --setup-log "$log" "$@"
