#!/usr/bin/env bash
# The highlight job on a fitted real scene with an annotation field, and its contact sheet, in one command:
#
#     scripts/real_highlight.sh SCENE OUT [CONTACT.png]
#
# SCENE must already have its language field (`fourlegs language SCENE --encoder masks --masks ...`).
# Writes OUT/ (highlight.mp4, plan.json, report.json, ...), the contact sheet (default
# OUT/contact.png) and prints the job's timings (wall and CPU seconds per stage, per frame).
set -euo pipefail
scene=${1:?usage: scripts/real_highlight.sh SCENE OUT [CONTACT.png]}
out=${2:?usage: scripts/real_highlight.sh SCENE OUT [CONTACT.png]}
contact=${3:-$out/contact.png}
here=$(cd "$(dirname "$0")" && pwd)
fourlegs highlight "$scene" "a person" --preset broadcast --resolution 640x360 -o "$out"
python "$here/contact_sheet.py" "$out/highlight.mp4" "$out/plan.json" "$contact"
python - "$out/report.json" <<'PY'
import json, sys
r = json.load(open(sys.argv[1]))
n = r["render"]["frames_total"]
print(f"frames {n} at {r['resolution'][0]}x{r['resolution'][1]}")
for stage, wall in r["timings_s"].items():
    print(f"  {stage:18s} wall {wall:8.1f} s   cpu {r['cpu_timings_s'].get(stage, float('nan')):8.1f} s")
print(f"  render per frame   wall {r['render']['seconds_per_frame']:.3f} s   cpu {r['render']['cpu_seconds_per_frame']:.3f} s")
print("  messages:", *r["messages"], sep="\n    ")
PY
