#!/usr/bin/env bash
# The GPU check: what to run on a lent GPU machine, as one prepared call (the machine is lent by the minute):
#   1. install the Mitsuba/Dr.Jit build carried in .whl/site.tar.xz (that machine reaches no package index)
#      and this checkout (editable, no dependencies: numpy, numba, torch... are already there);
#   2. the render-stage tests (photometry, motion, reproducibility, writer...) on the CUDA variant, forced by
#      RENDER2SPIKE_VARIANT so that they cannot pass by falling back to the CPU;
#   3. benchmarks/render_gpu.py: samples/s and frames/s of each working variant, against the 2-core CPU rows
#      measured earlier (--cpu-ref).
#   4. the README's main job (render2spike run scenes/rotating_disk.yaml) on the variant chosen automatically;
#   5. with FROZEN_T=seconds (0 or unset: skipped), benchmarks/render_frozen.py, the film launch against the
#      frozen launch (render2spike/render/frozen.py, the default launch) on the auto-selected variant, at
#      three points, or those FROZEN_ARGS gives (its tests run in step 2, as part of tests/render).
#   6. with LAUNCH_T=seconds (0 or unset: skipped), benchmarks/render_launch.py --launch frozen on each bundled scene's
#      window at 16 spp (LAUNCH_SCENES overrides the scenes): a frame's scene update (this project's pose vs Mitsuba's
#      update, an OptiX rebuild where an object moves), the frozen call and the wait, on the auto-selected variant.
#   7. with DATASET_T=seconds (0 or unset: skipped), benchmarks/dataset.py: camera-seconds of spikes plus truth per
#      hour of its small default spec, where each clip's time goes, the render's samples/s against a bare launch,
#      on the auto-selected variant (about a minute; report in OUT_DIR/dataset/dataset.md).
#   8. with GOAL_T=seconds (0 or unset: skipped), the throughput goal's commands, each timed end to end in a fresh
#      folder: render2spike run rotating_disk --set camera.profile=vidar-default --duration 0.2 at --lux 5 and 1
#      (full 250 x 400 sensor; goal: <= 2 s and <= 0.8 s), then benchmarks/static_reuse.py --rounds 1
#      (static-region reuse against whole frames) in what is left of GOAL_T.
#   9. with SPIKE_T=seconds (0 or unset: skipped), the spike stage on the GPU: the CUDA tests of the torch
#      implementation (tests/sensor/test_torch_models.py -m cuda: equality in distribution with the reference and
#      the numba kernels, on cuda), then benchmarks/spike_stage.py --device cuda on the full sensor with the numba
#      thread-scaling rows (RENDER2SPIKE_THREADS 1 2 4 8 16; SPIKE_ARGS overrides its options), in what is left of
#      SPIKE_T (report in OUT_DIR/spike/spike_stage.md).
#  10. with BLOCK_T=seconds (0 or unset: skipped), benchmarks/keyframe_blocks.py on room_pan (only the camera moves):
#      a keyframe's time in a block of 16 against a launch of its own and a bare mi.render, on the scene's window and
#      on the full sensor, at 16 and 121 spp (reports in OUT_DIR/blocks/window and OUT_DIR/blocks/full).
# REPRO_SPP="64 256 1024" also runs benchmarks/repro_check.py (two runs of one render compared value by value,
# the default launch) at those spp. BENCH_LIMIT_S=0 skips step 3; DEMO_LAUNCHES="film frozen" runs step 4 once per launch (default: auto
# only, the README's command as it stands; its log is demo.txt, another launch's demo_LAUNCH.txt).
# Usage: [TESTS="pytest paths"] [BENCH_ARGS="render_gpu.py options"] [FROZEN_T=120] [FROZEN_ARGS="..."] \
#        [DEMO_LAUNCHES="film frozen"] [LAUNCH_T=90] [LAUNCH_SCENES="room_pan ..."] [DATASET_T=120] [GOAL_T=120] \
#        [SPIKE_T=300] [SPIKE_ARGS="spike_stage.py options"] [BLOCK_T=120] \
#        bash benchmarks/gpu_check.sh OUT_DIR [TEST_TIMEOUT_S] [BENCH_LIMIT_S] [DEMO_TIMEOUT_S (0: no main job)]
# Making the carried file (here, on a machine with network):
#   bash benchmarks/make_gpu_site.sh (downloads the cp312 wheels, trims them, writes .whl/site.tar.xz)
set -u
OUT=${1:?usage: gpu_check.sh OUT_DIR [TEST_TIMEOUT_S] [BENCH_LIMIT_S] [DEMO_TIMEOUT_S]}
fail=0  # the exit status: 1 when a step failed (the later steps still run)
TEST_T=${2:-200}
BENCH_T=${3:-150}
DEMO_T=${4:-100}
mkdir -p "$OUT/bench"
export PYTHONUNBUFFERED=1
t0=$(date +%s)
stamp() { echo "[$(( $(date +%s) - t0 )) s, load $(cut -d' ' -f1-3 /proc/loadavg)] $*" | tee -a "$OUT/steps.txt"; }

stamp "machine"
{ nvidia-smi; uname -a; python3 --version; nproc; free -g
  echo "--- libLLVM:"; ls /usr/lib/x86_64-linux-gnu/libLLVM* /usr/lib/llvm-*/lib/libLLVM* 2>&1 | head
  echo "--- optix / cuda libraries:"; ldconfig -p | grep -i -E "optix|libcuda" ; ls /usr/local/nvidia/lib64 2>&1 | head -40
} > "$OUT/env.txt" 2>&1
[ -d /usr/local/nvidia/lib64 ] && export LD_LIBRARY_PATH=/usr/local/nvidia/lib64:${LD_LIBRARY_PATH:-}

stamp "install"
SITE=$(python3 -c "import site; print(site.getsitepackages()[0])")
if [ -f .whl/site.tar.xz ]; then  # behind the machine's own packages (a .pth entry goes last on sys.path)
  mkdir -p /tmp/r2s_site && tar -xJf .whl/site.tar.xz -C /tmp/r2s_site && echo /tmp/r2s_site > "$SITE/r2s_carried.pth" \
    || { stamp "unpacking .whl/site.tar.xz failed"; fail=1; }
fi
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >> "$OUT/env.txt" 2>&1 \
  || { stamp "pip install -e . failed (see env.txt): using PYTHONPATH"; export PYTHONPATH=$PWD; }
python3 -c "import mitsuba, drjit, render2spike; print('mitsuba', mitsuba.__version__, 'drjit', drjit.__version__)" \
  >> "$OUT/env.txt" 2>&1 || { stamp "imports failed (see env.txt)"; fail=1; }
stamp "auto variant: $(python3 -c 'from render2spike.render.backend import mitsuba; print(mitsuba().variant())' 2>&1 | tail -1)"

stamp "render tests on cuda_ad_spectral (timeout ${TEST_T} s)"
RENDER2SPIKE_TEST_WORKERS=0 RENDER2SPIKE_VARIANT=cuda_ad_spectral timeout "$TEST_T" python3 -m pytest ${TESTS:-tests/render} -q -p no:cacheprovider \
  -rfE --durations=10 > "$OUT/pytest_render_cuda.txt" 2>&1
rc=$?; [ $rc -eq 0 ] || fail=1
stamp "render tests exit $rc ($(tail -1 "$OUT/pytest_render_cuda.txt"))"

[ "$BENCH_T" -gt 0 ] && {
stamp "benchmark (start no point after ${BENCH_T} s)"
python3 benchmarks/render_gpu.py --frames 16 --cpu-frames 4 --time-limit-s "$BENCH_T" --point-timeout-s 120 \
  --cpu-ref benchmarks/results/render_gpu_cpu_2core.json --out "$OUT/bench" ${BENCH_ARGS:-} \
  > "$OUT/bench.txt" 2>&1
rc=$?; [ $rc -eq 0 ] || fail=1
stamp "benchmark exit $rc"
}

[ "$DEMO_T" -gt 0 ] && {
TIMEFORMAT='wall %R s, user %U s, sys %S s'
for launch in ${DEMO_LAUNCHES:-auto}; do
stamp "main job (README's command) on the auto-selected variant, --launch $launch (timeout ${DEMO_T} s)"
demo=$(mktemp -d)/demo  # a fresh folder: a rerun must not resume a finished job
log="$OUT/demo.txt"; [ "$launch" = auto ] || log="$OUT/demo_$launch.txt"
{ time timeout "$DEMO_T" python3 -m render2spike run scenes/rotating_disk.yaml --out "$demo" --launch "$launch"
  echo "exit $?"; cat "$demo/summary.md"; } > "$log" 2>&1
grep -qx "exit 0" "$log" || fail=1
stamp "main job, --launch $launch: $(grep -E '^wall|^exit' "$log" | tr '\n' ' ')"
done
}
[ "${FROZEN_T:-0}" -gt 0 ] && {
stamp "frozen launch against film launch (timeout ${FROZEN_T} s)"
timeout "$FROZEN_T" python3 benchmarks/render_frozen.py --rounds 1 --frames 16 --warm 4 --out "$OUT/frozen" \
  ${FROZEN_ARGS:---points lambertian_plane:window:16 rotating_disk:window:16 rotating_disk:full:16} \
  > "$OUT/frozen.txt" 2>&1
rc=$?; [ $rc -eq 0 ] || fail=1
stamp "frozen launch benchmark exit $rc"
}
[ "${LAUNCH_T:-0}" -gt 0 ] && {
stamp "launch split, frozen launch (benchmarks/render_launch.py, timeout ${LAUNCH_T} s)"
lt0=$(date +%s)
for sc in ${LAUNCH_SCENES:-lambertian_plane rotating_disk room_pan translating_object}; do
  left=$(( LAUNCH_T - ($(date +%s) - lt0) ))
  [ "$left" -gt 5 ] || { stamp "launch split: no time left for $sc"; break; }
  timeout "$left" python3 benchmarks/render_launch.py --launch frozen --scene "$sc" --spp 16 --frames 60 --warm 8 \
    --out "$OUT/launch" >> "$OUT/launch.txt" 2>&1 || { fail=1; stamp "launch split of $sc failed"; }
done
stamp "launch split done"
}
[ "${DATASET_T:-0}" -gt 0 ] && {
stamp "dataset throughput (benchmarks/dataset.py, timeout ${DATASET_T} s)"
timeout "$DATASET_T" python3 benchmarks/dataset.py --out "$OUT/dataset" > "$OUT/dataset.txt" 2>&1
rc=$?; [ $rc -eq 0 ] || fail=1
stamp "dataset benchmark exit $rc ($(grep -m1 -o '[0-9.e+]* camera-seconds[^*]*' "$OUT/dataset/dataset.md" 2>/dev/null))"
}
[ "${GOAL_T:-0}" -gt 0 ] && {
TIMEFORMAT='wall %R s, user %U s, sys %S s'
gt0=$(date +%s)
for lux in 5 1; do
  left=$(( GOAL_T - ($(date +%s) - gt0) ))
  [ "$left" -gt 5 ] || { stamp "goal run at $lux lux: no time left"; break; }
  stamp "goal: run rotating_disk, full sensor, 0.2 s, $lux lux (timeout $left s)"
  g=$(mktemp -d)/goal
  { time timeout "$left" python3 -m render2spike run rotating_disk --set camera.profile=vidar-default \
      --duration 0.2 --lux "$lux" --out "$g" --quiet; echo "exit $?"; cat "$g/summary.md"; } > "$OUT/goal_${lux}lux.txt" 2>&1
  grep -qx "exit 0" "$OUT/goal_${lux}lux.txt" || fail=1
  stamp "goal at $lux lux: $(grep -E '^wall|^exit' "$OUT/goal_${lux}lux.txt" | tr '\n' ' ')"
done
left=$(( GOAL_T - ($(date +%s) - gt0) ))
[ "$left" -gt 30 ] && { timeout "$left" python3 benchmarks/static_reuse.py --rounds 1 --out "$OUT/reuse" \
  > "$OUT/reuse.txt" 2>&1; stamp "static reuse benchmark exit $?"; }
}
[ "${SPIKE_T:-0}" -gt 0 ] && {
st0=$(date +%s)
mkdir -p "$OUT/spike"
python3 -c "from sensor.models.torch_models import cuda_works; import torch; print('torch', torch.__version__, \
  'cuda', torch.version.cuda); assert cuda_works(), 'torch finds no working CUDA device'" > "$OUT/spike/torch_env.txt" 2>&1 \
  || { stamp "torch sees no working CUDA device (see spike/torch_env.txt): the CUDA tests would only skip"; fail=1; }
stamp "spike stage: torch implementation's CUDA tests (timeout $(( SPIKE_T / 3 )) s)"
RENDER2SPIKE_TEST_WORKERS=0 RENDER2SPIKE_SPIKE_DEVICE=cuda timeout $(( SPIKE_T / 3 )) python3 -m pytest tests/sensor/test_torch_models.py -m cuda -q \
  -p no:cacheprovider -rfEs --durations=10 > "$OUT/spike/pytest_torch_cuda.txt" 2>&1
rc=$?; [ $rc -eq 0 ] || fail=1
stamp "spike-stage CUDA tests exit $rc ($(tail -1 "$OUT/spike/pytest_torch_cuda.txt"))"
left=$(( SPIKE_T - ($(date +%s) - st0) ))
if [ "$left" -gt 20 ]; then
  stamp "spike stage benchmark: torch on cuda against numba at 1-16 threads (timeout $left s)"
  timeout "$left" python3 benchmarks/spike_stage.py --device cuda --out "$OUT/spike/spike_stage.md" \
    ${SPIKE_ARGS:---threads 1 2 4 8 16 --size 250x400 --intervals 2000} > "$OUT/spike/spike_stage.txt" 2>&1
  rc=$?; [ $rc -eq 0 ] || fail=1
  stamp "spike stage benchmark exit $rc"
else
  stamp "spike stage benchmark: no time left"; fail=1
fi
}
[ "${BLOCK_T:-0}" -gt 0 ] && {
bt0=$(date +%s)
for size in window full; do
  left=$(( BLOCK_T - ($(date +%s) - bt0) ))
  [ "$left" -gt 10 ] || { stamp "keyframe blocks, $size: no time left"; break; }
  stamp "keyframe blocks (benchmarks/keyframe_blocks.py, $size, timeout $left s)"
  timeout "$left" python3 benchmarks/keyframe_blocks.py --scene room_pan $([ $size = full ] && echo --full) \
    --out "$OUT/blocks/$size" >> "$OUT/blocks.txt" 2>&1
  rc=$?; [ $rc -eq 0 ] || fail=1
  stamp "keyframe blocks, $size: exit $rc"
done
}
[ -n "${REPRO_SPP:-}" ] && {
stamp "two runs of the same render (benchmarks/repro_check.py, spp ${REPRO_SPP}, default launch)"
timeout 200 python3 benchmarks/repro_check.py --spp $REPRO_SPP --out "$OUT/repro" > "$OUT/repro.txt" 2>&1
rc=$?; [ $rc -eq 0 ] || fail=1
stamp "repro check exit $rc"
}
cat "$OUT/bench/render_gpu.md" 2>/dev/null | tail -30
cat "$OUT/steps.txt"
exit $fail
