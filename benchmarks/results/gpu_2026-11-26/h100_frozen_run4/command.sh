# run 4 (2026-11-26 15:31, H100, a fresh machine): all render tests on the code of 5499e31
# (frozen default, moving meshes as instances from their t = 0 pose, review fixes)
TESTS="tests/render" bash benchmarks/gpu_check.sh /tmp/o 165 0 0; rc=$?; tar czf $OUT/run.tgz -C /tmp o; cp /tmp/o/steps.txt $OUT/; exit $rc
