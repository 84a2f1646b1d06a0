# run 2 (2026-11-26 14:48, H100, a fresh machine): the code of the commit that made launch=auto the default
# (frozen on LLVM and CUDA variants); all render tests run with that default on cuda_ad_spectral
TESTS="tests/render" DEMO_LAUNCHES="frozen film" REPRO_SPP="64 256 1024" FROZEN_T=120 \
FROZEN_ARGS="--rounds 1 --frames 16 --warm 4 --points lambertian_plane:window:16 rotating_disk:window:16 room_pan:window:16 rotating_disk:window:256 rotating_disk:full:4 rotating_disk:full:64" \
bash benchmarks/gpu_check.sh /tmp/o 200 0 50; rc=$?; cp /tmp/o/steps.txt $OUT/; tar -czf $OUT/run.tgz -C /tmp o; exit $rc
# (the run's folder came back as one archive: the device returns at most 8 files; unpacked here)
