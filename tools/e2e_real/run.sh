#!/usr/bin/env bash
# make e2e-real: the extension in real Blender builds (../shared/tools/realblender).
#
#   1. Blender 5.2 (Debian sid) and 4.3 (Debian trixie): install the built zip into a
#      fresh user folder, open the demo scene, check the rig, build the field, render
#      (tools/e2e_real/check_render.py) -> out/e2e-real/<suite>/summary.json, render.png.
#      4.3 cannot open files saved by Blender 5, so it builds its own demo.blend first.
#   2. Blender 5.2 in a real window (Xvfb): the sidebar with three cameras, a render, the
#      viewport's Rendered shading, a mask made and painted over its guide
#      (tools/e2e_real/gui_steps.py), then the mask tools (tools/e2e_real/mask_steps.py);
#      screenshots -> docs/images/ (SHOTS=... to change); then Esc pressed in each stage
#      of a render, timed (tools/e2e_real/cancel_steps.py).
#
# Needs root and the realblender chroots (made by its setup.sh when missing: ~90 s each).
# RB_SUITES="sid" to skip 4.3 (RB_SUITES=none: only the window run); E2E_GUI=0 to skip
# the window run; E2E_CLI=0 to skip tests/tools and the animation and farm tests with
# the real 5.2 as $BLENDER. Optional: not in make test.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/../.." && pwd)
RB=${RB:-$(cd "$REPO/../shared/tools/realblender" 2>/dev/null && pwd || echo /work/shared/tools/realblender)}
OUT=$REPO/out/e2e-real
SHOTS=${SHOTS:-$REPO/docs/images}
ZIP=$REPO/$(cat "$REPO/dist/LINUX_ZIP")
cd "$REPO"
mkdir -p "$OUT"

root_of() { echo "${XDG_CACHE_HOME:-$HOME/.cache}/realblender/$1-root"; }

for suite in ${RB_SUITES:-sid trixie}; do
  [ "$suite" = none ] && continue
  [ -x "$(root_of "$suite")/usr/bin/blender" ] || RB_SUITE=$suite "$RB/setup.sh"
  export RB_SUITE=$suite RB_HOME=$OUT/home-$suite
  rm -rf "$RB_HOME" "$OUT/$suite"
  "$RB/run.sh" --command extension install-file -r user_default -e "$ZIP" | tail -1
  blend=$REPO/sample_blends/demo.blend
  if [ "$suite" != sid ]; then
    "$RB/run.sh" -b --python-exit-code 1 --python "$REPO/sample_blends/make_samples.py" -- \
      --out "$OUT/samples-$suite" --only demo > "$OUT/samples-$suite.log" 2>&1
    blend=$OUT/samples-$suite/demo.blend
  fi
  echo "== $suite: install, check and render $blend"
  "$RB/run.sh" -b "$blend" --python-exit-code 1 --python "$REPO/tools/e2e_real/check_render.py" \
    -- --out "$OUT/$suite" > "$OUT/$suite.log" 2>&1 || { tail -30 "$OUT/$suite.log"; exit 1; }
  grep E2E_SUMMARY "$OUT/$suite.log"
done

if [ "${E2E_GUI:-1}" = 1 ]; then
  export RB_SUITE=sid RB_HOME=$OUT/home-sid RB_DISPLAY=${RB_DISPLAY:-:99}
  GUI_DISPLAY=$RB_DISPLAY  # the mask tools below use the same display
  mkdir -p "$SHOTS"
  # the newest zip, into the 5.2 user folder (its field cache stays)
  "$RB/run.sh" --command extension install-file -r user_default -e "$ZIP" | tail -1
  echo "== sid: the workflow in a window, screenshots in $SHOTS"
  rm -f "$OUT/painted.blend"
  RB_ENV="SHOT_DIR=$SHOTS E2E_LOG=$OUT/gui-log.json E2E_SAVE=$OUT/painted.blend" \
    "$RB/run.sh" "$REPO/sample_blends/demo.blend" --python "$REPO/tools/e2e_real/gui_steps.py" \
    > "$OUT/gui.log" 2>&1 || true
  "$RB/run.sh" --stop-xvfb
  # the painted mask survives saving and reopening (no Image > Save)
  unset RB_DISPLAY
  "$RB/run.sh" -b "$OUT/painted.blend" --python-exit-code 1 --python-expr "$(cat <<'PY'
import bpy, numpy as np, sys
m = bpy.context.scene.multiscale.cameras[1].mask
px = np.empty(m.size[0] * m.size[1] * 4, np.float32)
m.pixels.foreach_get(px)
white = int((px.reshape(-1, 4)[:, 0] > 0.5).sum())
print("E2E_REOPENED", m.name, "packed" if m.packed_file else "not packed", white, "white pixels")
sys.exit(0 if white > 0 and m.packed_file else 1)
PY
)" 2>&1 | grep E2E_REOPENED
  python3 - "$OUT/gui-log.json" <<'PY'
import json, sys
log = json.load(open(sys.argv[1]))
steps = [s["step"] for s in log["steps"]]
print("steps:", ", ".join(steps))
painted = [s for s in log["steps"] if s["step"] == "mask painted"]
ok = steps[-1] == "done" and painted and painted[0]["white_pixels"] > 0
sys.exit(0 if ok else 1)
PY
  # the mask tools in the same window: the guide under any mask, Mask from Selected, a
  # dragged soft shape, the overlay, the guide remade after the camera turns, New Mask
  # asking first (tools/e2e_real/mask_steps.py; screenshots mask_*.png)
  echo "== sid: the mask tools in a window, screenshots in $SHOTS"
  export RB_DISPLAY=$GUI_DISPLAY
  RB_ENV="SHOT_DIR=$SHOTS E2E_LOG=$OUT/mask-log.json" \
    "$RB/run.sh" "$REPO/sample_blends/demo.blend" --python "$REPO/tools/e2e_real/mask_steps.py" \
    > "$OUT/mask.log" 2>&1 || true
  "$RB/run.sh" --stop-xvfb
  unset RB_DISPLAY
  python3 - "$OUT/mask-log.json" <<'PY'
import json, sys
steps = [s["step"] for s in json.load(open(sys.argv[1]))["steps"]]
print("mask steps:", ", ".join(steps))
sys.exit(0 if steps and steps[-1] == "done" and "failed" not in steps else 1)
PY
  # Esc in the window stops a render in each stage within 2 s (the render job's
  # test_break; tools/e2e_real/cancel_steps.py: SCALAR_FIELD's stages, then AUTO's
  # IMAGE_BLEND at 1920x1080)
  echo "== sid: Esc in each stage of a render in a window"
  export RB_DISPLAY=$GUI_DISPLAY
  RB_ENV="E2E_LOG=$OUT/cancel-log.json" \
    "$RB/run.sh" "$REPO/sample_blends/demo.blend" --python "$REPO/tools/e2e_real/cancel_steps.py" \
    > "$OUT/cancel.log" 2>&1 || true
  "$RB/run.sh" --stop-xvfb
  unset RB_DISPLAY
  python3 - "$OUT/cancel-log.json" <<'PY'
import json, sys
steps = json.load(open(sys.argv[1]))["steps"]
for s in steps:
    if s["step"] in ("cancelled", "skipped", "failed"):
        info = {k: s[k] for k in ("key_to_end", "heard_to_end", "heard_in", "reason") if k in s}
        print("cancel:", s["step"], s.get("stage"), info)
names = [s["step"] for s in steps]
sys.exit(0 if names and names[-1] == "done" and "failed" not in names else 1)
PY
fi
if [ "${E2E_CLI:-1}" = 1 ]; then
  # Blender's command line as the tests rely on it (tests/tools: -s, -e, -j, -a, -F,
  # placeholders, no-overwrite), then keyframed cameras rendered with -a and three farm
  # workers sharing a cache folder, all with the real 5.2 as $BLENDER. The chroot sees
  # the repository only, so the tests' temporary files go under out/.
  export RB_SUITE=sid RB_HOME=$OUT/home-sid
  echo "== sid: the command line, animation and farm workers"
  rm -rf "$OUT/cli"
  BLENDER="$RB/run.sh" .venv/bin/python -m pytest -q -p no:cacheprovider \
    --basetemp="$OUT/cli" tests/tools/test_blender.py \
    tests/blender/test_animation.py::test_command_line_animation_reads_each_frames_cameras \
    tests/blender/test_farm.py > "$OUT/cli.log" 2>&1 || { tail -30 "$OUT/cli.log"; exit 1; }
  tail -1 "$OUT/cli.log"
fi
echo "e2e-real: all passed"
