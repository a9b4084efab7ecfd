#!/usr/bin/env bash
# Wheels for a lent GPU machine, whose image has torch, numpy, OpenCV (without contrib) and rich but reaches no
# package index: gsplat 1.5.3 (the GPU figures' version; GSPLAT= another), pycolmap (the start of captures without
# points), tyro and tyro's two dependencies at the versions installed here, for CPython 3.12 on x86-64 Linux, into
# .whl/ (ignore it: echo /.whl/ >> .git/info/exclude).
# Carry .whl with the run; gpu_check.sh and gpu_env.sh install them. About 45 MiB of the 64 that travel.
set -eu
cd "$(dirname "$0")/.."
version() { python3 -c "import importlib.metadata as m; print(m.version('$1'))"; }
mkdir -p .whl
for spec in "gsplat==${GSPLAT:-1.5.3}" pycolmap tyro docstring-parser typeguard; do
    [[ $spec == *==* ]] || spec="$spec==$(version "$spec")"
    python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
        -d .whl "$spec"
done
du -sh .whl
