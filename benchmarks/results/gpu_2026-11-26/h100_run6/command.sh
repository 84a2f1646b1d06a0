O=$OUT; export PYTHONUNBUFFERED=1; L() { echo "[$(date +%T) load $(cut -d' ' -f1-3 /proc/loadavg)] $*" | tee -a $O/steps.txt; }
L install; mkdir -p /tmp/r2s_site && tar -xJf .whl/site.tar.xz -C /tmp/r2s_site && echo /tmp/r2s_site > "$(python3 -c 'import site; print(site.getsitepackages()[0])')/r2s_carried.pth"
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . > $O/install.txt 2>&1
[ -d /usr/local/nvidia/lib64 ] && export LD_LIBRARY_PATH=/usr/local/nvidia/lib64:${LD_LIBRARY_PATH:-}
{ nvidia-smi -L; lscpu | grep "Model name"; nproc; } > $O/env.txt 2>&1
for a in "cuda_ad_spectral rotating_disk" "cuda_ad_spectral lambertian_plane" "llvm_ad_spectral rotating_disk" "llvm_ad_spectral lambertian_plane"; do set -- $a; L "launch $1 $2"; timeout 50 python3 benchmarks/render_launch.py --variant $1 --scene $2 --spp 16 256 --frames 40 --out $O/r/launch >> $O/launch.txt 2>&1 || L "launch $1 $2 failed: $?"; done
for sc in rotating_disk lambertian_plane; do L "freeze cuda $sc"; timeout 60 python3 benchmarks/render_launch.py --variant cuda_ad_spectral --scene $sc --spp 16 --frames 10 --freeze --freeze-timeout-s 35 --out $O/r/freeze >> $O/freeze.txt 2>&1 || L "freeze $sc failed: $?"; done
L repro; timeout 60 python3 benchmarks/repro_check.py --variant cuda_ad_spectral --spp 256 --duration 0.01 --out $O/r/repro > $O/repro.txt 2>&1 || L "repro failed: $?"
L end; cd $O && tar czf r.tgz r && rm -rf r; cat $O/launch.txt $O/freeze.txt $O/repro.txt | cut -c1-600; cat $O/steps.txt
