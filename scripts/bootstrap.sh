#!/usr/bin/env bash
# Installs what the project needs on a fresh Debian/Ubuntu machine, idempotently:
# Mesa's headless EGL (OpenGL without a display or GPU), a virtual environment in .venv, the
# CPU build of torch (first, so no dependency can pull the multi-GB CUDA wheels) and the
# package with its [train] and [dev] extras.  A second run with nothing changed takes a second.
set -euo pipefail
cd "$(dirname "$0")/.."

# qemu-user: tests/test_cpu_portability.py; chromium + chromium-driver: tests/test_web.py (the web page in a
# real browser, driven by selenium through Debian's chromedriver, built from the same source as the browser)
apt_packages=(libegl1 libegl-mesa0 libgl1-mesa-dri qemu-user chromium chromium-driver)
missing=()
for pkg in "${apt_packages[@]}"; do
  dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed" || missing+=("$pkg")
done
sudo_cmd=()
[ "$(id -u)" -ne 0 ] && sudo_cmd=(sudo)
updated=0
if [ ${#missing[@]} -gt 0 ]; then
  "${sudo_cmd[@]}" apt-get update -qq
  updated=1
fi
# libllvm19: Mitsuba's LLVM variant (prt-bench --reference mitsuba, tests/test_mitsuba_reference.py),
# where this release has it; without it Mitsuba runs its scalar variant, about 10x slower.
if ! dpkg-query -W -f='${Status}' libllvm19 2>/dev/null | grep -q "install ok installed"; then
  [ "$updated" = 1 ] || "${sudo_cmd[@]}" apt-get update -qq || true
  if apt-cache policy libllvm19 2>/dev/null | grep -q "Candidate: [0-9]"; then
    missing+=(libllvm19)
  else
    echo "bootstrap: libllvm19 is not in this release's packages; Mitsuba will run its scalar variant"
  fi
fi
if [ ${#missing[@]} -gt 0 ]; then
  echo "bootstrap: installing ${missing[*]} (apt)"
  DEBIAN_FRONTEND=noninteractive "${sudo_cmd[@]}" apt-get install -y -qq "${missing[@]}" >/dev/null
fi

python=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$python" -m venv .venv
stamp=.venv/.prt-installed
want=$(cat pyproject.toml scripts/bootstrap.sh | sha1sum | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null)" != "$want" ]; then
  echo "bootstrap: installing Python packages into .venv"
  # PRT_TORCH_INDEX lets a machine without a local CPU wheel name the CPU index of its mirror.
  .venv/bin/pip install -q ${PRT_TORCH_INDEX:+--index-url "$PRT_TORCH_INDEX"} "torch==2.13.0"
  .venv/bin/pip install -q -e ".[train,dev]"
  echo "$want" > "$stamp"
fi
