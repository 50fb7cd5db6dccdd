#!/usr/bin/env bash
# The CUDA check (issue #34) in one command, for a lent GPU machine without network:
#
#   bash scripts/device_check.sh                          # on the GPU machine: --size full --device auto
#   bash scripts/device_check.sh --size toy --device cpu  # the CPU dry run (what tests/test_device_check.py runs)
#
# 1. installs the carried wheels (.whl/*.whl) with pip --no-index --no-deps: gsplat into a folder of its
#    own, the rest (plyfile, ...) into another; the project itself runs from this checkout (PYTHONPATH);
# 2. starts gsplat's CUDA build in the background, under its own cap (GSPLAT_BUILD_CAP, default 300 s);
# 3. runs `python -m fourlegs_bench.device` (= `fourlegs bench device`) with the remaining arguments:
#    every step in its own process under its own cap, the report rewritten after every step.
#
# Writes into $OUT (a new temporary folder when OUT is unset): device_report.json, device_report.md,
# device_contact.png, cuda_tests.txt, gsplat_build.txt and device_log.txt (this script's output).
# Prepare beforehand (on a machine with network): the wheels and the capture subset, see
# docs/device_check.md. Environment: PYTHON (default python3), GSPLAT_BUILD_CAP, MAX_JOBS.
set -uo pipefail
cd "$(dirname "$0")/.."
STARTED=$(date +%s)
PY=${PYTHON:-python3}
if [ -z "${OUT:-}" ]; then
    OUT=$(mktemp -d "${TMPDIR:-/tmp}/fourlegs-device-out.XXXXXX")
    echo "OUT is unset: the report goes to $OUT"
fi
mkdir -p "$OUT"
WORK=$(mktemp -d "${TMPDIR:-/tmp}/fourlegs-device-work.XXXXXX")
SITE=$WORK/site
GSPLAT_SITE=$WORK/site_gsplat
mkdir -p "$SITE" "$GSPLAT_SITE"
exec > >(tee -a "$OUT/device_log.txt") 2>&1
TEE_PID=$!

# the interpreter's own bin folder first: torch's extension builder runs `ninja` (from the ninja wheel) by name
export PATH="$("$PY" -c 'import os, sys; print(os.path.dirname(sys.executable))'):$PATH"
export PYTHONUNBUFFERED=1
export TQDM_MININTERVAL=${TQDM_MININTERVAL:-10}
# a fixed folder: a rerun on the same machine reuses the compiled gsplat extension
export TORCH_EXTENSIONS_DIR=${TORCH_EXTENSIONS_DIR:-${TMPDIR:-/tmp}/fourlegs-torch-extensions}
export PYTHONPATH="$SITE:$PWD${PYTHONPATH:+:$PYTHONPATH}"
echo "[device_check] $(date '+%F %T') in $PWD with $($PY --version 2>&1), work $WORK"

shopt -s nullglob
wheels=(.whl/*.whl)
gsplat_wheels=(.whl/gsplat-*.whl)
other_wheels=()
for w in "${wheels[@]}"; do
    case "$(basename "$w")" in gsplat-*) ;; *) other_wheels+=("$w") ;; esac
done
pip_install() {  # TARGET WHEEL...
    local target=$1
    shift
    timeout 120 "$PY" -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
        --target "$target" "$@" || echo "[device_check] pip install into $target FAILED: $*"
}
if [ ${#wheels[@]} -eq 0 ]; then
    echo "[device_check] no .whl/*.whl: nothing to install (missing packages show in the env step)"
fi
[ ${#other_wheels[@]} -gt 0 ] && pip_install "$SITE" "${other_wheels[@]}"
[ ${#gsplat_wheels[@]} -gt 0 ] && pip_install "$GSPLAT_SITE" "${gsplat_wheels[@]}"
ln -sfn "$PWD/addon" "$SITE/fourlegs_addon"     # the package name the add-on installs as
echo "[device_check] wheels installed after $(( $(date +%s) - STARTED )) s"

MAX_JOBS=${MAX_JOBS:-16} "$PY" -m fourlegs_bench.device_gsplat build --site "$GSPLAT_SITE" \
    --status "$WORK/gsplat_build.json" --log "$WORK/gsplat_build.txt" --cap "${GSPLAT_BUILD_CAP:-300}" &
BUILD_PID=$!

"$PY" -m fourlegs_bench.device --out "$OUT" --work "$WORK" --started "$STARTED" \
    --gsplat-site "$GSPLAT_SITE" --gsplat-status "$WORK/gsplat_build.json" --gsplat-log "$WORK/gsplat_build.txt" "$@"
RC=$?

if kill -0 "$BUILD_PID" 2>/dev/null; then
    echo "[device_check] stopping the gsplat build (still running)"
    kill -TERM "$BUILD_PID" 2>/dev/null
fi
wait "$BUILD_PID" 2>/dev/null
[ -f "$WORK/gsplat_build.txt" ] && tail -c 1048576 "$WORK/gsplat_build.txt" > "$OUT/.gsplat_build.txt.part" \
    && mv "$OUT/.gsplat_build.txt.part" "$OUT/gsplat_build.txt"
echo "[device_check] exit status $RC after $(( $(date +%s) - STARTED )) s; report in $OUT"
exec 1>&- 2>&-
wait "$TEE_PID" 2>/dev/null   # the log is complete before the caller collects $OUT
exit $RC
