#!/usr/bin/env bash
# One device call when a Triton kernel fails on a GPU: which one (gpu_kernel_check.py:
# every render in a fresh process), compute-sanitizer's word on it where the machine
# allows, then a `fast-gpu` run of the 256 px scene rendered at 128 / 256 / 512 px with the
# largest set of kernels that rendered right (bench_render.py). Figures in $OUT.
#   on the GPU machine:  bash benchmarks/gpu_kernel_targets.sh
set -uo pipefail
OUT=${OUT:?set OUT to the folder for the figures}
PY=${PYTHON:-python3}
export PYTHONPATH="$PWD/src${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
LOG=$OUT/log.txt
: >"$LOG"
say() { echo "== $(date -u +%T) (${SECONDS} s) $*" | tee -a "$LOG"; }
WORK=$(mktemp -d)
say "$("$PY" -c 'import torch, triton; print(torch.__version__, torch.cuda.get_device_name(0), "triton", triton.__version__)')"
"$PY" benchmarks/gpu_kernel_check.py --device cuda --sizes 128 --timeout 90 \
  --heads 16,4,16 64,8 128,4 128,8 --json "$OUT/check128.json" 2>&1 | tee -a "$LOG"
"$PY" benchmarks/gpu_kernel_check.py --device cuda --sizes 512 --timeout 90 \
  --only "off,all,all but field_heads,all but hashgrid,all but knn" --json "$OUT/check512.json" 2>&1 | tee -a "$LOG"
SAN=$(command -v compute-sanitizer || ls /usr/local/cuda*/bin/compute-sanitizer 2>/dev/null | head -1)
if [[ -n "$SAN" ]]; then
  say "compute-sanitizer (all kernels, 128 px)"
  timeout 90 "$SAN" --tool memcheck --print-limit 3 "$PY" benchmarks/gpu_kernel_check.py --child \
    --device cuda --size 128 --save "$WORK/san.npy" 2>&1 | head -40 | tee -a "$LOG"
fi
KEEP=$("$PY" - "$OUT/check128.json" "$OUT/check512.json" <<'PYEOF'
import json, sys
ok = {}
for f in sys.argv[1:]:
    for r in json.load(open(f))["rows"]:
        if r.get("heads"):
            continue
        good = r["rc"] == 0 and r.get("max_abs_diff", 1) < 0.05 and not r.get("nan")
        ok[r["env"]] = ok.get(r["env"], True) and good
order = ["1"] + [e for e in ok if e.count(",") == 1] + [e for e in ok if "," not in e and e not in ("0", "1")]
print(next((e for e in order if ok.get(e)), "0"))
PYEOF
)
say "kernels kept for the figures: FLAMENERF_GPU_KERNELS=$KEEP"
"$PY" -c "from flamenerf.synthetic.scene import make_scene; make_scene('$WORK/scene', size=256, frames=300)" 2>&1 | tail -2 | tee -a "$LOG"
say "fast-gpu seed 0"
FLAMENERF_GPU_KERNELS=$KEEP "$PY" benchmarks/bench_train.py --scene "$WORK/scene" --size 256 --budget 70 \
  --eval-every 100 --eval-frames 6 --eval-fit-steps 60 --final-fit-steps 60 --skip-throughput \
  --targets 30 --quality-preset fast-gpu --seed 0 --keep-run "$WORK/run" \
  --json "$OUT/train_s0.json" 2>&1 | tee -a "$LOG"
say "render with FLAMENERF_GPU_KERNELS=$KEEP"
FLAMENERF_GPU_KERNELS=$KEEP "$PY" benchmarks/bench_render.py --run "$WORK/run" --dataset "$WORK/scene" \
  --device cuda --sizes 128 256 512 --presets fast --repeats 5 --out "$OUT/render" 2>&1 | tee -a "$LOG"
say "done: $(ls "$OUT" | tr '\n' ' ')"
