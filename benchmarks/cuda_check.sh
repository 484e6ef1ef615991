#!/usr/bin/env bash
# The GPU checks of meshseq in one run, for a machine with an NVIDIA GPU (issue 10, item 5):
#   1. the CUDA tests (tests/test_train.py -k cuda: train, resume, CPU/CUDA agreement);
#   2. benchmarks/train_speed.py --device cuda at the paper configuration (horse, 8 x 32),
#      variants fast / bf16 / reference, with the profile and the scaling table;
#   3. `meshseq train --device auto` on pcow (picks CUDA), then --resume to more iterations;
#   4. the same under torchrun (one process, NCCL): the DistributedDataParallel path on CUDA;
#   5. with a third argument `suite`, first the whole test suite there (pytest-xdist, one worker a
#      core, `-v` so that failures are named as they come, even if the time limit cuts the run),
#      the files needing the viz, bodies or USD extras or Blender left out.
#
#   benchmarks/cuda_check.sh DATA_DIR OUT_DIR [suite]
#
# DATA_DIR holds horse-gallop.npz, pcow.npz and crane.npz (the team's ../shared/data); every
# step's output goes to OUT_DIR/*.log and the benchmark's figures to OUT_DIR/speed.json.
# Each step has its own time limit, so one slow step does not take the others with it. On the
# `device` tool's H200: carry the data and wheels of libigl, cholespy, trimesh and cma
# (its image lacks them; docs/performance.md), install them with pip --target, then
# `pip install -e . --no-deps --no-build-isolation` for the suite's `meshseq` command.
set -u
data=${1:?usage: cuda_check.sh DATA_DIR OUT_DIR}
out=${2:?usage: cuda_check.sh DATA_DIR OUT_DIR}
mkdir -p "$out"
export PYTHONUNBUFFERED=1 MESHSEQ_SHARED_DATA=$data
py=${PYTHON:-python3}
run=$(mktemp -d)

step() {  # step NAME SECONDS CMD...: run CMD with a time limit, its output in OUT/NAME.log
    local name=$1 limit=$2; shift 2
    echo "== $name (limit ${limit} s): $*"
    local t0=$SECONDS
    timeout "$limit" "$@" >"$out/$name.log" 2>&1
    local rc=$?
    echo "== $name: exit $rc after $((SECONDS - t0)) s"
    tail -n 25 "$out/$name.log"
}

nvidia-smi -L
if [ "${3:-}" = suite ]; then  # about 6 minutes on 16 cores; needs meshseq installed (pip install -e . --no-deps)
    step suite 420 $py -m pytest -v -n auto -p no:cacheprovider --tb=line tests \
        --ignore tests/test_render.py --ignore tests/test_viewer.py --ignore tests/test_export.py \
        --ignore tests/test_bodies.py --ignore tests/test_formats.py --ignore tests/test_blender.py
    grep -E "FAILED|ERROR" "$out/suite.log" | head -40
fi
$py -c "import torch; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name())"
step tests 120 $py -m pytest -q -rs tests/test_train.py -k cuda
step speed 200 $py benchmarks/train_speed.py "$data/horse-gallop.npz" --device cuda --iterations 10 \
    --variants fast,bf16,reference --profile --scaling --json "$out/speed.json"
printf 'eval_every = 100\ncheckpoint_every = 100\n' > "$run/every100.toml"
printf 'eval_every = 50\ncheckpoint_every = 50\n' > "$run/every50.toml"
step train 80 $py -m meshseq train "$data/pcow.npz" --out "$run/pcow" --device auto --iterations 200 \
    --config "$run/every100.toml" --no-progress
step resume 50 $py -m meshseq train "$data/pcow.npz" --out "$run/pcow" --device auto --iterations 300 \
    --config "$run/every100.toml" --no-progress --resume
step torchrun 80 torchrun --standalone --nproc_per_node 1 -m meshseq train "$data/pcow.npz" --out "$run/ddp" \
    --device cuda --iterations 100 --config "$run/every50.toml" --no-progress
cp "$run/pcow/metrics.csv" "$out/pcow-metrics.csv" 2>/dev/null
rm -rf "$run"
