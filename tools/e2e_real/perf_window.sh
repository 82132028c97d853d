#!/usr/bin/env bash
# Profile Blender's own threads in a real window (Xvfb) while timing.py runs there:
# the run of tools/e2e_real/timing.sh's window part, under `perf record` from the host.
#
#   tools/e2e_real/perf_window.sh [OUT_DIR]          # the extension's renders
#   ENGINE=BLENDER_WORKBENCH tools/e2e_real/perf_window.sh out/perf-wb
#   KEEP_HOME=1 tools/e2e_real/perf_window.sh out/perf-warm   # Mesa's cache kept
#   DISPLAY_TYPE=AREA tools/e2e_real/perf_window.sh out/perf-area  # no render window
#
# Writes OUT_DIR/perf.data (CLOCK_MONOTONIC timestamps), OUT_DIR/window.log (the
# E2E_MARK lines of timing.py give each render's start and end on the same clock) and
# OUT_DIR/pid. Then, for example, the main thread (tid = pid) during the first render:
#
#   perf report -i OUT_DIR/perf.data --symfs "$ROOT" --tid PID --time S,E --sort dso,sym
#
# with S,E from `grep E2E_MARK OUT_DIR/window.log`. Needs root and a built dist/.
# Uses its own Xvfb display (RB_DISPLAY, default :97) and stops only that one.
set -euo pipefail
REPO=$(cd "$(dirname "$0")/../.." && pwd)
RB=${RB:-$(cd "$REPO/../shared/tools/realblender" 2>/dev/null && pwd || echo /work/shared/tools/realblender)}
OUT=$(realpath -m "${1:-$REPO/out/perf-window}")
ZIP=$REPO/$(cat "$REPO/dist/LINUX_ZIP")
BLEND=${BLEND:-$REPO/sample_blends/demo.blend}
export RB_SUITE=sid RB_HOME=$REPO/out/e2e-real/home-perf RB_DISPLAY=${RB_DISPLAY:-:97}
ROOT="${XDG_CACHE_HOME:-$HOME/.cache}/realblender/sid-root"
mkdir -p "$OUT"
# KEEP_HOME=1: keep the last run's home, so its caches (Mesa's shader cache in
# ~/.cache/mesa_shader_cache) are warm, as on a user's machine after the first session
if [ "${KEEP_HOME:-0}" != 1 ] || [ ! -d "$RB_HOME" ]; then
  rm -rf "$RB_HOME"
  "$RB/run.sh" --command extension install-file -r user_default -e "$ZIP" | tail -1
fi
engine=(); [ -n "${ENGINE:-}" ] && engine=(--engine "$ENGINE")
[ -n "${DISPLAY_TYPE:-}" ] && engine+=(--render-display "$DISPLAY_TYPE")
RB_ENV=${RB_ENV:-} "$RB/run.sh" -B "$OUT" "$BLEND" --python "$REPO/tools/e2e_real/timing.py" \
  -- --out "$OUT/timing-window.json" --renders "${RENDERS:-2}" "${engine[@]}" \
  > "$OUT/window.log" 2>&1 &
pid=$!
echo "$pid" > "$OUT/pid"
# run.sh execs chroot, env and blender in turn: wait until the pid is Blender's and it
# has loaded Mesa, so that perf names the chroot's libraries by their paths on the host
# (libraries loaded after perf attaches appear under their paths in the chroot, which
# the host does not have: their samples lose their symbols)
for _ in $(seq 300); do
  grep -q libgallium "/proc/$pid/maps" 2>/dev/null && break; sleep 0.05
done
perf record -F "${FREQ:-1999}" -g -k CLOCK_MONOTONIC -p "$pid" -o "$OUT/perf.data" \
  > "$OUT/perf-record.log" 2>&1 &
perf_pid=$!
wait "$pid" || true
sleep 1
kill -INT "$perf_pid" 2>/dev/null || true
wait "$perf_pid" || true
xvfb=$ROOT/run/rb-xvfb-${RB_DISPLAY#:}.pid
[ -e "$xvfb" ] && kill "$(cat "$xvfb")" 2>/dev/null && rm -f "$xvfb"
grep E2E_MARK "$OUT/window.log" || tail -20 "$OUT/window.log"
echo "blender pid $pid; perf data $OUT/perf.data; symfs $ROOT"
