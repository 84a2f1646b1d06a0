#!/usr/bin/env bash
# Build .whl/site.tar.xz: the render stage's Python packages for a GPU machine that reaches no package index
# (Python 3.12, x86-64 manylinux), trimmed to fit a 64 MiB transfer beside the checkout (about 36 MB).
# Run here, where pip reaches the registries; benchmarks/gpu_check.sh unpacks it there, behind the packages
# that machine already has (a .pth entry: its own attrs, typing-extensions... win).
# Kept: Mitsuba's cuda_ad_spectral, llvm_ad_spectral and scalar_spectral variants (the ones render2spike
# picks from) and every plugin (a user's XML scene may name any). Dropped: the other variants (rgb, mono,
# polarized), headers and type stubs. Versions are pinned: those the GPU check has run on an H100.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$(pwd)
PY=${PY:-3.12}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
python3 -m pip download -q --no-deps --only-binary=:all: --python-version "$PY" --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 -d "$work/whl" \
  mitsuba==3.9.1 drjit==1.5.0 OpenEXR==3.5.3 jsonschema==4.26.0 jsonschema-specifications==2025.9.1 \
  referencing==0.37.0 rpds-py==2026.9.1 trimesh==5.2.0 attrs==26.1.0 typing-extensions==4.16.0
mkdir "$work/site"
for w in "$work"/whl/*.whl; do (cd "$work/site" && unzip -q -o "$w"); done
cd "$work/site/mitsuba"
rm -f ./*polarized*.so ./*_mono*.so cuda_ad_rgb*.so llvm_ad_rgb*.so scalar_rgb*.so
rm -rf include mitsuba_stubs cmake pkgconfig
cd "$work/site"
rm -rf drjit/include drjit/cmake
find . -name "*.pyi" -delete
cd "$ROOT"
mkdir -p .whl
grep -qx "/.whl/" .git/info/exclude 2>/dev/null || { mkdir -p .git/info; echo "/.whl/" >> .git/info/exclude; }
tar -cJf .whl/site.tar.xz.part -C "$work/site" . && mv .whl/site.tar.xz.part .whl/site.tar.xz
ls -la .whl/site.tar.xz
