#!/usr/bin/env bash
# The prepared GPU check, run on a lent machine with an NVIDIA GPU (docs/guides/gpu.md), in at most
# 8 minutes, nothing downloaded: unpacks the EGL / GL loaders that travelled in .gl/, installs the
# wheels that travelled in .whl/ (scripts/gpu_carry.sh makes both here), makes this checkout
# importable as the package `prt`, then runs studies/gpu_check.py, which writes
# docs/benchmarks/gpu.json and gpu.md; both, and the log, are copied to $OUT (what comes back).
# Extra arguments go to studies/gpu_check.py (e.g. --reduced --json /tmp/trial/gpu.json).
set -uo pipefail
cd "$(dirname "$0")/.."
out=${OUT:-/tmp/prt-gpu-check}
mkdir -p "$out"
if compgen -G ".gl/*.deb" >/dev/null; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
fi
vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json  # where the lent machines' driver keeps it
if [ -z "${__EGL_VENDOR_LIBRARY_FILENAMES:-}" ] && [ -f "$vendor" ]; then
  export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
fi
python=${PYTHON:-python3}
site=/tmp/prt-site
if compgen -G ".whl/*.whl" >/dev/null; then
  "$python" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" .whl/*.whl || exit 1
fi
pkg=/tmp/prt-pkg
mkdir -p "$pkg"
ln -sfn "$PWD" "$pkg/prt"  # the repository root is the package prt
export PYTHONPATH="$pkg:$site${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
nvidia-smi --query-gpu=name,driver_version,clocks.sm --format=csv,noheader 2>&1 | tee "$out/gpu_check.log"
timeout 470 "$python" studies/gpu_check.py "$@" 2>&1 | tee -a "$out/gpu_check.log"
rc=${PIPESTATUS[0]}
for f in docs/benchmarks/gpu.json docs/benchmarks/gpu.md; do
  [ -f "$f" ] && cp "$f" "$out/"
done
exit "$rc"
