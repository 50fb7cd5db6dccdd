#!/usr/bin/env bash
# Install (CPU torch, the project with its dev + blender extras) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet torch==2.13.0
python -m pip install --quiet -e ".[dev,blender,cluster]"
export FOURLEGS_CACHE="${FOURLEGS_CACHE:-$PWD/.cache/fourlegs}"
set +e
python -m pytest -q -p no:cacheprovider --timeout=600 "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "no tests were collected: failing" >&2
  exit 1
fi
exit "$rc"
