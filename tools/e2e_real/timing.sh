#!/usr/bin/env bash
# make e2e-timing: Compute Field and the render of sample_blends/demo.blend as saved, in
# a real Blender 5.2 window (Xvfb) and with `blender -b`, on the same machine
# (../shared/tools/realblender; needs root). Each run clears the field cache first.
# Writes out/e2e-real/timing-{window,background}.json and prints both, with the ratio
# of window to background for the build and the renders (RENDERS of them, default 4: the
# first starts the render workers), and the CPU seconds each render took in Blender's
# process and in its workers, which the machine's other load does not change. Then the
# same renders by Blender's Workbench (BASELINE=0 skips them): the window's own cost.
#
# Mesa's shader cache: the window's first render compiles the shaders that draw the
# Render Result (image editor, colour management), which under Xvfb's software OpenGL
# (llvmpipe) is LLVM work on Blender's main thread, about 1.2 CPU s for any engine
# when Mesa's on-disk cache is empty (docs/performance.md). A user's later sessions find
# those shaders in the cache, so by default (MESA_CACHE=warm) the cache is kept in
# $OUT/mesa-shader-cache across runs and each window run follows an unmeasured window
# session of the same engine (two when the cache is new; WARMUP=0 skips them).
# MESA_CACHE=cold empties it before each window run instead: what a first session on
# a new machine pays.
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
MESA_CACHE_DIR=$OUT/mesa-shader-cache
export RB_ENV="MESA_SHADER_CACHE_DIR=$MESA_CACHE_DIR ${RB_ENV:-}"
# window_run OUT_NAME [timing.py args...]: one measured window session, after the
# Mesa shader cache is made warm (an unmeasured session) or cold (emptied)
window_run() {
  local name=$1; shift
  if [ "${MESA_CACHE:-warm}" = cold ]; then
    rm -rf "$MESA_CACHE_DIR"
  elif [ "${WARMUP:-1}" = 1 ]; then
    # after one session from an empty cache, the next still compiled a third as much
    local n=1; [ -d "$MESA_CACHE_DIR" ] || n=2
    for _ in $(seq $n); do
      RB_DISPLAY=${RB_DISPLAY:-:99} "$RB/run.sh" "$BLEND" --python \
        "$REPO/tools/e2e_real/timing.py" -- --out "$OUT/warmup.json" --renders 1 "$@" \
        > "$OUT/warmup.log" 2>&1 || true
    done
  fi
  RB_DISPLAY=${RB_DISPLAY:-:99} "$RB/run.sh" "$BLEND" --python "$REPO/tools/e2e_real/timing.py" \
    -- --out "$OUT/$name.json" --renders "${RENDERS:-4}" "$@" > "$OUT/$name.log" 2>&1 || true
}
"$RB/run.sh" --command extension install-file -r user_default -e "$ZIP" | tail -1

echo "== background: $BLEND"
"$RB/run.sh" -b "$BLEND" --python-exit-code 1 --python "$REPO/tools/e2e_real/timing.py" \
  -- --out "$OUT/timing-background.json" --renders "${RENDERS:-4}" > "$OUT/timing-background.log" 2>&1 \
  || { tail -30 "$OUT/timing-background.log"; exit 1; }

echo "== window: $BLEND (Mesa's shader cache ${MESA_CACHE:-warm})"
window_run timing-window
# the same file rendered by Blender's own Workbench, window and -b: what opening the
# render window and drawing in it costs any engine here (BASELINE=0 skips it)
if [ "${BASELINE:-1}" = 1 ]; then
  "$RB/run.sh" -b "$BLEND" --python "$REPO/tools/e2e_real/timing.py" -- \
    --out "$OUT/timing-workbench-background.json" --renders "${RENDERS:-4}" \
    --engine BLENDER_WORKBENCH > "$OUT/timing-workbench-background.log" 2>&1 || true
  window_run timing-workbench-window --engine BLENDER_WORKBENCH
fi
# stop this display's Xvfb only (`run.sh --stop-xvfb` stops every one in the chroot)
xvfb_pid=$root/run/rb-xvfb-$(d=${RB_DISPLAY:-:99}; echo "${d#:}").pid
[ -e "$xvfb_pid" ] && kill "$(cat "$xvfb_pid")" 2>/dev/null && rm -f "$xvfb_pid" || true

python3 - "$OUT/timing-background.json" "$OUT/timing-window.json" <<'PY'
import json, os, sys
bg, win = (json.load(open(p)) for p in sys.argv[1:3])
for key in ("compute_seconds", "render_seconds", "later_render_median_seconds"):
    if key in win and key in bg:
        print(f"{key}: window {win[key]} s, background {bg[key]} s, "
              f"ratio {win[key] / bg[key]:.2f}")
for name, run in (("background", bg), ("window", win)):
    for i, r in enumerate(run.get("renders", []), 1):
        print(f"{name} render {i}: {r['seconds']} s; CPU s: Blender {r['blender_cpu_seconds']}, "
              f"workers {r['workers_cpu_seconds']}; "
              f"by thread {r.get('blender_threads_cpu_seconds')}")
print("load averages: background", bg["load_average"], "window", win["load_average"])
print("Mesa's shader cache in the window runs:", os.environ.get("MESA_CACHE", "warm"))
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
