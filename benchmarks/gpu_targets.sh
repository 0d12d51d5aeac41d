#!/usr/bin/env bash
# The GPU targets (docs/results.md) in one call of a lent GPU machine (on an H200, 2026-11-28, one
# seed, the check at 128 px only, the A/B and the paper's preset: 434 s in all; the check
# 31 s, the scene 23 s, a seed 99 s, the three frame timings 50 s, the A/B 40 s, choices
# and profile 22 s, the paper's preset 162 s):
#   0. which Triton kernels render a frame right (gpu_kernel_check.py: off, all, today's
#      default, the field heads at their old widths; each kernel alone and all but each
#      where one fails; each render in a fresh process); the rest runs with the largest
#      set that did (FLAMENERF_GPU_KERNELS), and compute-sanitizer looks at all of them
#      where that set is not all (the last stage);
#   1. the built-in scene at 256 px;
#   2. `fast-gpu` under bench_train.py's 70 s budget on seeds 0 and 1: the held-out curve
#      (6 val frames every 10 s) and the final held-out PSNR on all 30 val frames: the
#      target is >= 30 dB within 60 s; beside it the driven re-animation's face PSNR
#      (6 reanimate frames every 10 s, all of them at the end: the second curve);
#   3. the seed-0 run's frames per second at 128 / 256 / 512 px (bench_render.py), with
#      the second pass over unfinished rays and without it: the targets are 60 fps at
#      256 px and 20 fps at 512 px, within 0.2 dB of the reference renderer; where every
#      kernel rendered right, also without the field heads' kernel (does it pay?).
#   4. a profile of one 512 px frame (profile_render.py: where the GPU's time goes), in
#      the log, and the nearest-vertex kernel's and the field heads' launch choices timed
#      on that frame's calls (gpu_choices.py);
#   5. with OLD_SRC set (source trees of earlier commits, oldest first): the same run's
#      frames at 256 and 512 px with them and with this checkout's src, alternated in
#      fresh processes (bench_render_ab.py), so that a change to the GPU's inference path
#      is measured against what it replaced on one warm machine (run before 4);
#   6. with PAPER_BUDGET set (seconds): `flame-in-nerf` under the same protocol as 2
#      (PAPER_EVAL_EVERY, 10 s unless set), its curves beside fast-gpu's, within what is
#      left before DEADLINE (seconds since the start; unset, no limit). On a CPU its fits
#      of 2048 / 4096 rays need over 16 GB. Likewise FAST_BUDGET (FAST_EVAL_EVERY, 20 s):
#      `fast`'s 1800 steps of 2048 rays beside fast-gpu (its driven face at 256 px was the
#      better on a CPU: docs/presets.md).
# SEEDS (default "0 1"), CHECK_SIZES ("128 512") and CHECK_BUDGET (240 s) trim a call that
# must fit a short lease.
# Everything it prints is also in $OUT/log.txt; the figures (JSON and Markdown) in
# $OUT/figures.tar, made again after every stage (a call brings back 8 files at most, and
# what it holds when cut off). A stage that fails is logged and the next one runs.
#
#   on the GPU machine (its python3 has torch and Triton; nothing is installed):
#       bash benchmarks/gpu_targets.sh
#   a variant of the preset, timed as the preset is (bench_train.py --set; first see on a
#   CPU whether it keeps the quality per step: docs/presets.md, fast-gpu on a CPU):
#       SET=KEY=VALUE,KEY=VALUE bash benchmarks/gpu_targets.sh
#   the GPU inference path of commit C beside this one (a plain copy of its src inside the
#   checkout, git-ignored, so that the device tool carries it: name it in `carry`; a git
#   worktree would travel without its files):
#       here:   mkdir gpu_old && git archive C src | tar -x -C gpu_old
#       there:  OLD_SRC=gpu_old/src bash benchmarks/gpu_targets.sh   (carry: gpu_old)
#   here, to check the script itself on a CPU in a few minutes (tiny sizes):
#       SMOKE=1 OUT=/tmp/gpu_targets bash benchmarks/gpu_targets.sh
set -uo pipefail
OUT=${OUT:?set OUT to the folder for the figures}
mkdir -p "$OUT"
PY=${PYTHON:-python3}
# the package from this checkout: the GPU machine lacks the CLI's extras (tyro, MediaPipe,
# viser), which training and the benchmarks do not import
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
SEEDS=${SEEDS:-0 1}
SET=${SET:-}
if [[ -n "${SMOKE:-}" ]]; then
  SIZE=32 BUDGET=3 EVAL_FIT=2 FINAL_FIT=2 SIZES="32 64" DEVICE=cpu REPEATS=1 CHOICE_POINTS=128
  CHECK_SIZES=8 CHECK_TIMEOUT=300 CHECK_BUDGET=1500
  CHOICE_SIZE=16  # the interpreter renders the frame: slow
  EXTRA_TRAIN=(--steps 4 --batch-rays 1024)
else
  SIZE=256 BUDGET=70 EVAL_FIT=60 FINAL_FIT=100 SIZES="128 256 512" DEVICE=cuda REPEATS=5
  CHOICE_POINTS=0 CHOICE_SIZE=512 CHECK_SIZES=${CHECK_SIZES:-128 512} CHECK_TIMEOUT=60
  # the check as a whole: a GPU that hangs must leave time for the rest
  CHECK_BUDGET=${CHECK_BUDGET:-240}
  EXTRA_TRAIN=()
fi
WORK=$(mktemp -d)
SCENE=$WORK/scene
FIG=$WORK/figures  # brought back as one file, figures.tar: a call returns 8 files at most
mkdir -p "$FIG"
LOG=$OUT/log.txt
: >"$LOG"
say() { echo "== $(date -u +%T) (${SECONDS} s) $*" | tee -a "$LOG"; }
pack() { tar -cf "$OUT/.figures.tar" -C "$FIG" . && mv "$OUT/.figures.tar" "$OUT/figures.tar"; }
# a stage that fails is logged and the next one runs (a kernel fault once stopped the
# whole call at its first frame)
stage() { local what=$1; shift; say "$what"; { "$@" 2>&1 | tee -a "$LOG"; } || say "$what: failed"; pack; }

say "$(date -u +%FT%TZ) $("$PY" -c 'import torch; print(torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else "no GPU")') triton $("$PY" -c 'import triton; print(triton.__version__)' 2>/dev/null || echo none)"
say "commit $(git rev-parse --short HEAD 2>/dev/null || echo unknown)${SET:+, set $SET}"
# shellcheck disable=SC2086  # the sizes are separate arguments
stage "which kernels render right ($CHECK_SIZES px, each render in a fresh process)" \
  timeout "$CHECK_BUDGET" "$PY" benchmarks/gpu_kernel_check.py --device "$DEVICE" \
  --sizes $CHECK_SIZES --timeout "$CHECK_TIMEOUT" --json "$FIG/check.json" --keep "$WORK/keep"
KEEP=$(cat "$WORK/keep" 2>/dev/null || echo 0)
export FLAMENERF_GPU_KERNELS=$KEEP
say "the rest with FLAMENERF_GPU_KERNELS=$KEEP"
stage "the scene" "$PY" -c "from flamenerf.synthetic.scene import make_scene; make_scene('$SCENE', size=$SIZE, frames=300)"
for seed in $SEEDS; do
  stage "fast-gpu seed $seed" "$PY" benchmarks/bench_train.py --scene "$SCENE" --size "$SIZE" \
    --budget "$BUDGET" --eval-every 10 --eval-frames 6 --eval-fit-steps "$EVAL_FIT" \
    --final-fit-steps "$FINAL_FIT" --skip-throughput --targets 25,28,29,30 \
    --quality-preset fast-gpu --seed "$seed" --set "$SET" --keep-run "$WORK/run_s$seed" \
    --json "$FIG/train_s$seed.json" "${EXTRA_TRAIN[@]}"
done
first=${SEEDS%% *}
for refine in -1 0; do
  name=render; [[ $refine == 0 ]] && name=render_no_second_pass
  # shellcheck disable=SC2086  # the sizes are separate arguments
  stage "$name (seed $first's run)" "$PY" benchmarks/bench_render.py --run "$WORK/run_s$first" \
    --dataset "$SCENE" --device "$DEVICE" --sizes $SIZES --presets fast --repeats "$REPEATS" \
    --refine-main "$refine" --out "$FIG/$name"
done
if [[ $KEEP == 1 ]]; then
  # the field heads' kernel rendered right: does it still pay, padded to DOT_MIN, against
  # the PyTorch heads (on an H200, 2026-11-28: 512 px 33.2 against 30.1 fps)?
  # shellcheck disable=SC2086
  stage "render without the field heads' kernel (seed $first's run)" env \
    FLAMENERF_GPU_KERNELS=hashgrid,knn "$PY" benchmarks/bench_render.py --run "$WORK/run_s$first" \
    --dataset "$SCENE" --device "$DEVICE" --sizes ${SIZES#* } --presets fast \
    --repeats "$REPEATS" --out "$FIG/render_without_heads"
fi
if [[ -n "${OLD_SRC:-}" ]]; then
  # each old src knows FLAMENERF_GPU_KERNELS=0 alone: any other value turns on all of its
  # kernels (hashgrid and knn; none has a field heads' kernel), like for like with today's
  # default set; OLD_SRC may name several trees, oldest first
  # shellcheck disable=SC2086
  stage "render A/B: $OLD_SRC against src (seed $first's run)" "$PY" benchmarks/bench_render_ab.py \
    --run "$WORK/run_s$first" --dataset "$SCENE" --device "$DEVICE" --src $OLD_SRC src \
    --sizes ${SIZES#* } --rounds 3 --repeats "$REPEATS" --json "$FIG/render_ab.json"
fi
# on a CPU the interpreter checks the choices on a few points
CHOICE_ENV=(); [[ $DEVICE == cpu ]] && CHOICE_ENV=(TRITON_INTERPRET=1 FLAMENERF_CPU_KERNELS=0)
stage "the kernels' launch choices (seed $first's run, $CHOICE_SIZE px)" \
  env "${CHOICE_ENV[@]}" "$PY" benchmarks/gpu_choices.py --run "$WORK/run_s$first" \
  --dataset "$SCENE" --device "$DEVICE" --size "$CHOICE_SIZE" --repeats "$REPEATS" \
  --points "$CHOICE_POINTS" --json "$FIG/choices.json"
profile() {
  "$PY" benchmarks/profile_render.py --run "$WORK/run_s$first" --dataset "$SCENE" \
    --device "$DEVICE" --size "${SIZES##* }" --frames 3 --rows 45 2>&1 \
    | { grep -v "^\(STAGE\|USDT\)" || true; }
}
stage "profile of a ${SIZES##* } px frame (seed $first's run)" profile
# another preset under the same protocol as fast-gpu, side by side, for as long as the call
# has left (DEADLINE: seconds since the start by which the script must be done; the curve's
# lines are in the log as they come, should it be cut off)
beside() {
  local name=$1 budget=$2 every=$3 left=$(( ${DEADLINE:-100000} - SECONDS - 15 ))
  if (( left > 60 )); then
    stage "$name seed $first (at most $left s)" timeout "$left" "$PY" \
      benchmarks/bench_train.py --scene "$SCENE" --size "$SIZE" --budget "$budget" \
      --eval-every "$every" --eval-frames 6 --eval-fit-steps "$EVAL_FIT" \
      --final-fit-steps "$FINAL_FIT" --skip-throughput --targets 20,25,28,29,30 \
      --quality-preset "$name" --seed "$first" --json "$FIG/train_${name}_s$first.json" \
      "${EXTRA_TRAIN[@]}"
  else
    say "$name: skipped, $left s left"
  fi
}
[[ -n "${PAPER_BUDGET:-}" ]] && beside flame-in-nerf "$PAPER_BUDGET" "${PAPER_EVAL_EVERY:-10}"
[[ -n "${FAST_BUDGET:-}" ]] && beside fast "$FAST_BUDGET" "${FAST_EVAL_EVERY:-20}"
SAN=$(command -v compute-sanitizer || ls /usr/local/cuda*/bin/compute-sanitizer 2>/dev/null \
  | head -1 || true)
if [[ $KEEP != 1 && $DEVICE == cuda ]]; then
  if (( ${DEADLINE:-100000} - SECONDS < 170 )); then
    say "compute-sanitizer: skipped, too little time left"
  elif [[ -n "$SAN" ]]; then  # last: it can take minutes, and the figures come first
    stage "compute-sanitizer, every kernel on (128 px)" timeout 150 env FLAMENERF_GPU_KERNELS=1 \
      "$SAN" --tool memcheck --error-exitcode 1 --print-limit 5 "$PY" \
      benchmarks/gpu_kernel_check.py --child --device cuda --size 128 --save "$WORK/san.npy"
  else
    say "compute-sanitizer: not found"
  fi
fi
pack
rm -rf "$WORK"
say "done: $(tar -tf "$OUT/figures.tar" | tr '\n' ' ')"
