#!/usr/bin/env bash
# The Blender editors run: bpy 5.3 on Python 3.13, WITHOUT PyTorch (Blender's Python has none until the
# add-on's preferences install it). Covers the extension's build and offline install (its numba compiling
# against bpy 5.3's numpy 2.x, its plyfile and scipy), registration, the scene as Blender's own Gaussian
# splats (import, timeline, deletions), highlights rendered by EEVEE and Cycles with their relevancy mask,
# the PyTorch installer, the MP4 encoder process, keyframes, markers, the orbit rig and the compositor;
# what needs torch (query, the 4-LEGS render) is covered by the Python 3.11 / bpy 5.0 suite.
# Usage: scripts/test_blender_313.sh [pytest args]; PYTHON313 overrides the interpreter.
set -euo pipefail
cd "$(dirname "$0")/.."
PY="${PYTHON313:-$HOME/.pyenv/versions/3.13.0/bin/python}"
VENV=.venv313
if [ ! -x "$VENV/bin/python" ]; then
  "$PY" -m venv "$VENV"
fi
"$VENV/bin/python" -m pip install --quiet "bpy==5.3.0" pytest hypothesis pytest-timeout scipy tqdm safetensors \
  "plyfile>=1.0.3"
# the project without its dependencies (torch among them); numpy comes with bpy
"$VENV/bin/python" -m pip install --quiet --no-deps -e .
export FOURLEGS_CACHE="${FOURLEGS_CACHE:-$PWD/.cache/fourlegs}"
set +e
"$VENV/bin/python" - <<'PY'
import importlib.util, sys
assert importlib.util.find_spec("torch") is None, "this job runs without torch; remove it from .venv313"
print("python", sys.version.split()[0])
PY
"$VENV/bin/python" -m pytest -q -p no:cacheprovider --timeout=600 \
  tests/test_blender_no_torch.py tests/test_blender_highlight.py tests/test_blender_editing.py \
  tests/test_blender_native_splats.py tests/test_blender_messages.py tests/test_blender_retime_and_projects.py \
  -k "not relevancy_follows and not undo_after" "$@"
rc=$?
set -e
if [ "$rc" -eq 5 ]; then
  echo "no tests were collected: failing" >&2
  exit 1
fi
exit "$rc"
