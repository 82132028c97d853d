"""Count the `perf script` samples of one thread in a time window by shared library
and by function (the leaf frame), and by library anywhere on the stack; optionally as a
timeline (tools/e2e_real/perf_window.sh records them).

    perf script -i OUT/perf.data -F pid,tid,comm,time,ip,sym,dso > OUT/script.txt
    python3 perf_threads.py --tid PID --render 1 --log OUT/window.log < OUT/script.txt
    python3 perf_threads.py --tid PID --time 44183.54,44186.52 --bucket 0.1 < OUT/script.txt

``--render N --log`` takes the window from the ``E2E_MARK render_start N`` and
``render_end N`` lines timing.py prints (CLOCK_MONOTONIC, the clock perf records with
``-k CLOCK_MONOTONIC``). The main thread's tid is Blender's pid.
"""

import argparse
import collections
import os
import re
import sys

HEAD = re.compile(r"^\S.*?\s(\d+)/(\d+)\s+([\d.]+):")
FRAME = re.compile(r"^\s+([0-9a-f]+)\s+(.*)\s+\((.*)\)\s*$")


def samples(lines):
    """Yield (pid, tid, time, [(sym, dso), ...] leaf first) per sample."""
    head, frames = None, []
    for line in lines:
        m = HEAD.match(line)
        if m:
            if head:
                yield (*head, frames)
            head, frames = (int(m[1]), int(m[2]), float(m[3])), []
            continue
        f = FRAME.match(line)
        if f and head:
            sym = f[2].split("+0x")[0]
            frames.append((sym, os.path.basename(f[3])))
    if head:
        yield (*head, frames)


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--tid", type=int, required=True, help="thread id (main: the pid)")
    p.add_argument("--time", help="START,END in CLOCK_MONOTONIC seconds")
    p.add_argument("--render", type=int, help="render N's window, from --log")
    p.add_argument("--log", help="timing.py's output, with its E2E_MARK lines")
    p.add_argument("--top", type=int, default=25)
    p.add_argument(
        "--bucket",
        type=float,
        default=0.0,
        help="also print a timeline: samples per this many seconds, by library",
    )
    a = p.parse_args()
    if a.render:
        marks = {}
        with open(a.log) as f:
            for line in f:
                if line.startswith("E2E_MARK "):
                    *name, seconds = line.split()[1:]
                    marks[" ".join(name)] = seconds
        a.time = f"{marks[f'render_start {a.render}']},{marks[f'render_end {a.render}']}"
    t0, t1 = (float(x) for x in a.time.split(","))
    by_dso, by_sym, by_caller = (collections.Counter() for _ in range(3))
    n = 0
    timeline = collections.defaultdict(collections.Counter)
    for _pid, tid, t, frames in samples(sys.stdin):
        if tid != a.tid or not t0 <= t <= t1 or not frames:
            continue
        n += 1
        sym, dso = frames[0]
        by_dso[dso] += 1
        by_sym[f"{dso}: {sym}"] += 1
        if a.bucket:
            timeline[int((t - t0) / a.bucket)][dso] += 1
        # any frame in the stack from a library: inclusive counts
        seen = set()
        for _sym, d in frames:
            if d not in seen:
                by_caller[d] += 1
                seen.add(d)
    print(f"tid {a.tid}, {t0}..{t1}: {n} samples")
    for title, c in (
        ("self, by library", by_dso),
        ("self, by function", by_sym),
        ("library anywhere on the stack", by_caller),
    ):
        print(f"-- {title}")
        for k, v in c.most_common(a.top):
            print(f"{v:7d}  {k}")
    if a.bucket:
        print(f"-- timeline: samples per {a.bucket} s from {t0}, top libraries")
        for b in sorted(timeline):
            c = timeline[b]
            top = ", ".join(f"{k} {v}" for k, v in c.most_common(3))
            print(f"{b * a.bucket:6.2f}s {sum(c.values()):5d}  {top}")


if __name__ == "__main__":
    main()
