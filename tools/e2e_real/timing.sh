#!/usr/bin/env bash
# make e2e-timing: Compute Field and the render of sample_blends/demo.blend as saved, in
# a real Blender 5.2 window (Xvfb) and with `blender -b`, on the same machine
# (../shared/tools/realblender; needs root). Each run clears the field cache first.
# Writes out/e2e-real/timing-{window,background}.json and prints both, with the ratio
# of window to background for the build and the renders (RENDERS of them, default 4: the
# first starts the render workers), and the CPU seconds each render took in Blender's
# process and in its workers, which the machine's other load does not change. Then the
# same renders by Blender's Workbench (BASELINE=0 skips them): the window's own cost.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/../.." && pwd)
RB=${RB:-$(cd "$REPO/../shared/tools/realblender" 2>/dev/null && pwd || echo /work/shared/tools/realblender)}
OUT=$REPO/out/e2e-real
ZIP=$REPO/$(cat "$REPO/dist/LINUX_ZIP")
BLEND=${BLEND:-$REPO/sample_blends/demo.blend}
export RB_SUITE=sid RB_HOME=$OUT/home-timing
root="${XDG_CACHE_HOME:-$HOME/.cache}/realblender/sid-root"
[ -x "$root/usr/bin/blender" ] || "$RB/setup.sh"
mkdir -p "$OUT"
rm -rf "$RB_HOME"
"$RB/run.sh" --command extension install-file -r user_default -e "$ZIP" | tail -1

echo "== background: $BLEND"
"$RB/run.sh" -b "$BLEND" --python-exit-code 1 --python "$REPO/tools/e2e_real/timing.py" \
  -- --out "$OUT/timing-background.json" --renders "${RENDERS:-4}" > "$OUT/timing-background.log" 2>&1 \
  || { tail -30 "$OUT/timing-background.log"; exit 1; }

echo "== window: $BLEND"
RB_DISPLAY=${RB_DISPLAY:-:99} "$RB/run.sh" "$BLEND" --python "$REPO/tools/e2e_real/timing.py" \
  -- --out "$OUT/timing-window.json" --renders "${RENDERS:-4}" > "$OUT/timing-window.log" 2>&1 || true
# the same file rendered by Blender's own Workbench, window and -b: what opening the
# render window and drawing in it costs any engine here (BASELINE=0 skips it)
if [ "${BASELINE:-1}" = 1 ]; then
  for mode in background window; do
    flag=(); [ "$mode" = background ] && flag=(-b)
    RB_DISPLAY=${RB_DISPLAY:-:99} "$RB/run.sh" "${flag[@]}" "$BLEND" --python \
      "$REPO/tools/e2e_real/timing.py" -- --out "$OUT/timing-workbench-$mode.json" \
      --renders "${RENDERS:-4}" --engine BLENDER_WORKBENCH > "$OUT/timing-workbench-$mode.log" 2>&1 || true
  done
fi
RB_DISPLAY=${RB_DISPLAY:-:99} "$RB/run.sh" --stop-xvfb || true

python3 - "$OUT/timing-background.json" "$OUT/timing-window.json" <<'PY'
import json, sys
bg, win = (json.load(open(p)) for p in sys.argv[1:3])
for key in ("compute_seconds", "render_seconds", "later_render_median_seconds"):
    if key in win and key in bg:
        print(f"{key}: window {win[key]} s, background {bg[key]} s, "
              f"ratio {win[key] / bg[key]:.2f}")
for name, run in (("background", bg), ("window", win)):
    for i, r in enumerate(run.get("renders", []), 1):
        print(f"{name} render {i}: {r['seconds']} s; CPU s: Blender {r['blender_cpu_seconds']}, "
              f"workers {r['workers_cpu_seconds']}")
print("load averages: background", bg["load_average"], "window", win["load_average"])
try:
    wb = [json.load(open(p.replace("timing-", "timing-workbench-"))) for p in sys.argv[1:3]]
except OSError:
    wb = None
if wb:
    for key in ("render_seconds", "later_render_median_seconds"):
        print(f"Workbench {key}: window {wb[1][key]} s, background {wb[0][key]} s, "
              f"ratio {wb[1][key] / wb[0][key]:.2f}")
sys.exit(0 if "error" not in win else 1)
PY
