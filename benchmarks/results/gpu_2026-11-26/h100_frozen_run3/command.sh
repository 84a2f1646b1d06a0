# run 3 (2026-11-26 15:07, H100, a fresh machine): the code with moving meshes as instances in the frozen launch
TESTS="tests/render/test_frozen_launch.py tests/render/test_motion_render.py" bash benchmarks/gpu_check.sh /tmp/o 150 0 0; rc=$?
[ -d /usr/local/nvidia/lib64 ] && export LD_LIBRARY_PATH=/usr/local/nvidia/lib64:${LD_LIBRARY_PATH:-}
timeout 60 python3 benchmarks/frozen_replay_check.py --out /tmp/o/replay > /tmp/o/replay.txt 2>&1
timeout 60 python3 benchmarks/frozen_replay_check.py --as-vertices --out /tmp/o/replay_vertices > /tmp/o/replay_vertices.txt 2>&1
timeout 40 python3 benchmarks/render_frozen.py --rounds 1 --frames 16 --warm 4 --points translating_object:window:16 --out /tmp/o/frozen_to > /tmp/o/frozen_to.txt 2>&1
tar czf $OUT/run.tgz -C /tmp o; cp /tmp/o/steps.txt $OUT/; exit $rc
