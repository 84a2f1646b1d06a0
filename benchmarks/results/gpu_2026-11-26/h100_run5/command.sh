O=$OUT; export PYTHONUNBUFFERED=1; L() { echo "[$(date +%T) load $(cut -d' ' -f1-3 /proc/loadavg)] $*" | tee -a $O/steps.txt; }
L install; mkdir -p /tmp/r2s_site && tar -xJf .whl/site.tar.xz -C /tmp/r2s_site && echo /tmp/r2s_site > "$(python3 -c 'import site; print(site.getsitepackages()[0])')/r2s_carried.pth"
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . > $O/install.txt 2>&1
[ -d /usr/local/nvidia/lib64 ] && export LD_LIBRARY_PATH=/usr/local/nvidia/lib64:${LD_LIBRARY_PATH:-}
for a in "cuda_ad_spectral rotating_disk" "cuda_ad_spectral lambertian_plane" "llvm_ad_spectral rotating_disk" "llvm_ad_spectral lambertian_plane"; do set -- $a; L "launch $1 $2"; timeout 50 python3 benchmarks/render_launch.py --variant $1 --scene $2 --spp 16 256 --frames 40 --out $O/launch >> $O/launch.txt 2>&1 || L "launch $1 $2 failed: $?"; done
L "freeze cuda rotating_disk"; timeout 45 python3 benchmarks/render_launch.py --variant cuda_ad_spectral --scene rotating_disk --spp 16 --frames 10 --freeze --out $O/freeze >> $O/freeze.txt 2>&1 || L "freeze failed: $?"
L end; cd $O && tar czf launch_freeze.tgz launch freeze && rm -rf launch freeze; cat $O/launch.txt $O/freeze.txt | cut -c1-400; cat $O/steps.txt
