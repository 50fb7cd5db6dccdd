#!/usr/bin/env bash
# Install (CPU torch, the project with its dev + blender extras) and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet torch==2.13.0
python -m pip install --quiet -e ".[dev,blender,cluster,fit-features]"
export FOURLEGS_CACHE="${FOURLEGS_CACHE:-$PWD/.cache/fourlegs}"
# the extension's dependency wheels for linux-x64 (cp311 + cp313; ~190 MB, kept in the cache and not
# downloaded again), so the offline zip-install tests run; a release build fetches all four platforms
python -c "from fourlegs_addon import build; from fourlegs_engine.paths import cache_dir; \
build.fetch_wheels(cache_dir() / 'extension-wheels', platforms=['linux-x64'])" >/dev/null
set +e
# two worker processes, each test file kept in one of them (its module fixtures built once);
# FOURLEGS_TEST_WORKERS=0 runs in this process
python -m pytest -q -p no:cacheprovider --timeout=600 -n "${FOURLEGS_TEST_WORKERS:-2}" --dist loadfile "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "no tests were collected: failing" >&2
  exit 1
fi
# the Blender editors run (bpy 5.3, Python 3.13, no torch): native splats, EEVEE and Cycles
PY313="${PYTHON313:-$HOME/.pyenv/versions/3.13.0/bin/python}"
if [ -x "$PY313" ] && [ -z "${FOURLEGS_SKIP_313:-}" ]; then
  set +e
  scripts/test_blender_313.sh
  rc313=$?
  set -e
  [ "$rc" -eq 0 ] && rc=$rc313
else
  echo "skipped the bpy 5.3 / Python 3.13 job: no Python 3.13 at $PY313 (set PYTHON313)" >&2
fi
exit "$rc"
