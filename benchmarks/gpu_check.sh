#!/usr/bin/env bash
# One run of everything a CUDA machine is needed for, each step time-boxed and within one overall
# budget (BUDGET_S, default 585 s), each result written under $OUT as soon as it exists:
#   env.txt          the GPU, core count, torch / triton / numba versions
#   step.json        benchmarks/gpu_step.py: lmgs's time per training step by stage, the host syncs of a few
#                    traced steps (file:line, counted) and a profile of five dynamic steps
#   step_base.json   the same for the model library of another tree (BASE, a folder holding its lmgs/:
#                    e.g. `git archive REV lmgs | tar -x -C .gpu/base`), when BASE is set
#   lmgs_512.json    lmgs, quick preset, a packed 512 px clip (benchmarks/gpu_clip.py) trained and rendered on CUDA
#   parity.txt       the CUDA tests: test_cuda_paths_match_cpu in tests/test_render.py (Triton, numba-split, torch; gsplat where
#                    installed) and tests/test_train_device.py (a fit and renders on CUDA against the CPU)
#   lmgs_512_base.json  the training above with BASE's model library, when BASE is set
#   raster_cuda.json benchmarks/gpu_raster.py: the Triton path's cost per call split into projection,
#                    compositor and binning, then Triton configurations, the split and the torch compositor
#                    against numba on every core of the same machine (rewritten after each row)
#   s256.json, s512.json  the numba rasterizer by thread count (python -m lmgs.render.bench --threads ...)
# STEPS (default: all of "step train parity raster scaling") picks which run, in that order.
# Run from the repository root with a python3 that has torch (CUDA), triton and numba:
#   OUT=/tmp/out BASE=.gpu/base bash benchmarks/gpu_check.sh .gpu/astronaut512.npz
set -u
OUT=${OUT:-/tmp/gpu_check}
CLIP=${1:-.gpu/astronaut512.npz}
BUDGET_S=${BUDGET_S:-585}
STEPS=${STEPS:-step train parity raster scaling}
BASE=${BASE:-}
mkdir -p "$OUT"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s] $*" | tee -a "$OUT/steps.txt"; }
left() { local l=$(( BUDGET_S - ($(date +%s) - t0) )); (( l < 1 )) && l=1; (( l < $1 )) && echo "$l" || echo "$1"; }
want() { [[ " $STEPS " == *" $1 "* ]]; }
figures() { tr -d '\n ' < "$1" 2>/dev/null | grep -o '"fit_s":[0-9.]*\|"render_fps":[0-9.]*\|"psnr_mean_of_frames":[0-9.]*\|"median_ms":[0-9.]*' | tr '\n' ' '; }
{ nvidia-smi -L; nproc; python3 -c "import torch, triton, numba; print(torch.__version__, triton.__version__, numba.__version__, torch.cuda.get_device_name())"; } > "$OUT/env.txt" 2>&1
stamp "env: $(tail -1 "$OUT/env.txt")"
TRAIN="benchmarks/gpu_clip.py train $CLIP --device cuda --set train.budget_density=0.107531 --backend-note auto --progress"
if want step; then
  timeout "$(left 90)" python3 benchmarks/gpu_step.py "$CLIP" --device cuda --profile 5 --json "$OUT/step.json" > "$OUT/step.log" 2>&1
  stamp "step rc=$? $(figures "$OUT/step.json")"
  if [[ -n "$BASE" ]]; then
    PYTHONPATH="$PWD/$BASE:$PYTHONPATH" timeout "$(left 90)" python3 benchmarks/gpu_step.py "$CLIP" --device cuda \
      --profile 5 --json "$OUT/step_base.json" > "$OUT/step_base.log" 2>&1
    stamp "step base rc=$? $(figures "$OUT/step_base.json")"
  fi
fi
if want train; then
  timeout "$(left 200)" python3 $TRAIN --json "$OUT/lmgs_512.json" > "$OUT/train.log" 2>&1
  stamp "train rc=$? $(figures "$OUT/lmgs_512.json")"
fi
if want parity; then
  timeout "$(left 150)" python3 -m pytest -q -p no:cacheprovider tests/test_render.py::test_cuda_paths_match_cpu \
    tests/test_train_device.py > "$OUT/parity.txt" 2>&1
  stamp "parity rc=$? $(tail -1 "$OUT/parity.txt")"
fi
if want train && [[ -n "$BASE" ]]; then
  PYTHONPATH="$PWD/$BASE:$PYTHONPATH" timeout "$(left 200)" python3 $TRAIN --json "$OUT/lmgs_512_base.json" \
    > "$OUT/train_base.log" 2>&1
  stamp "train base rc=$? $(figures "$OUT/lmgs_512_base.json")"
fi
if want raster; then
  timeout "$(left 130)" python3 benchmarks/gpu_raster.py --json "$OUT/raster_cuda.json" > "$OUT/raster_cuda.log" 2>&1
  stamp "raster rc=$?"
fi
if want scaling; then
  B="python3 -m lmgs.render.bench --threads 1,2,4,8,16 --wait-too --repeats 5 --json"
  timeout "$(left 70)" $B --sizes 256 --counts 10000 > "$OUT/s256.json" 2> "$OUT/s256.log"
  stamp "scaling 256 rc=$?"
  timeout "$(left 90)" $B --sizes 512 --counts 50000 > "$OUT/s512.json" 2> "$OUT/s512.log"
  stamp "scaling 512 rc=$?"
fi
