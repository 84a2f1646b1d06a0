# run 1 of the frozen launch on a GPU (2026-11-26 14:34, H100), code of f2c49be (frozen launch opt-in) with
# the gpu_check.sh switches of the next commit; the device tool's call, from the repository root:
TESTS="tests/render/test_frozen_launch.py tests/render/test_photometry.py tests/render/test_motion_render.py tests/render/test_reproducible.py" \
DEMO_LAUNCHES="film frozen" FROZEN_T=180 \
FROZEN_ARGS="--rounds 1 --frames 16 --warm 4 --pipeline --points lambertian_plane:window:16 rotating_disk:window:16 room_pan:window:16 rotating_disk:full:4 rotating_disk:full:64" \
bash benchmarks/gpu_check.sh $OUT 120 0 50
