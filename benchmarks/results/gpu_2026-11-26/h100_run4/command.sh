O=$OUT; export PYTHONUNBUFFERED=1; TESTS=tests/render BENCH_ARGS="--scenes lambertian_plane --sizes window --spp 256" bash benchmarks/gpu_check.sh $O 140 30 0; rc=$?
[ -d /usr/local/nvidia/lib64 ] && export LD_LIBRARY_PATH=/usr/local/nvidia/lib64:${LD_LIBRARY_PATH:-}
L() { echo "[$(date +%T) load $(cut -d' ' -f1-3 /proc/loadavg)] $*" | tee -a $O/steps.txt; }
L launch; for v in cuda_ad_spectral llvm_ad_spectral; do for sc in rotating_disk lambertian_plane; do timeout 60 python3 benchmarks/render_launch.py --variant $v --scene $sc --spp 16 256 --frames 40 --freeze --out $O/launch >> $O/launch.txt 2>&1 || L "launch $v $sc failed"; done; done
L repro; timeout 90 python3 benchmarks/repro_check.py --variant cuda_ad_spectral --spp 64 256 1024 --duration 0.01 --out $O/repro > $O/repro.txt 2>&1 || L "repro failed"
L roompan; timeout 80 python3 benchmarks/render_gpu.py --variants llvm_ad_spectral --scenes room_pan --sizes full --spp 256 --frames 4 --point-timeout-s 75 --cpu-ref benchmarks/results/gpu_2026-11-26/cpu_2core/render_gpu.json --out $O/bench_roompan > $O/bench_roompan.txt 2>&1 || L "roompan failed"
L demo; d=$(mktemp -d)/demo; { TIMEFORMAT="wall %R s user %U s"; time timeout 45 python3 -m render2spike run scenes/rotating_disk.yaml --out $d; echo "exit $?"; cat $d/summary.md; } > $O/demo.txt 2>&1
L end; tail -3 $O/launch.txt $O/repro.txt $O/bench_roompan.txt; cat $O/steps.txt; exit $rc
