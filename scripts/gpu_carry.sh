#!/usr/bin/env bash
# Prepares, on a machine with network access, what the GPU check needs on a lent NVIDIA machine
# that reaches nothing (docs/guides/gpu.md): .whl/ holds the wheels its Python 3.12 image lacks
# (moderngl and its EGL loader glcontext; jsonschema and its dependencies, which the manifest
# checks use), .gl/ the EGL / OpenGL loader packages (libglvnd) its image may lack.  Both folders
# are ignored by git and travel with the device tool's `carry: [".gl", ".whl"]`; together
# about 3 MB.  scripts/gpu_check.sh installs them there.
set -euo pipefail
cd "$(dirname "$0")/.."
python=${PYTHON:-python3}
mkdir -p .whl
# Versions: the ones the project's own .venv runs (pinned so the check runs what the tests ran).
wheels=(moderngl==5.13.0 glcontext==3.1.0 jsonschema==4.26.0 jsonschema-specifications==2025.9.1 referencing==0.37.0 rpds-py==2026.9.1)
"$python" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_27_x86_64 --platform manylinux_2_17_x86_64 \
  --platform manylinux2014_x86_64 --platform manylinux_2_5_x86_64 --platform manylinux1_x86_64 --platform any \
  -d .whl "${wheels[@]}"
mkdir -p .gl /tmp/prt-gl-lists/partial
o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/prt-gl-lists)
apt-get "${o[@]}" update -qq
(cd .gl && apt-get "${o[@]}" download libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 >/dev/null)
du -sh .whl .gl
