#!/usr/bin/env bash
# Times the CPU training step of several `msth` binaries side by side, interleaved, so that the
# ratios come from one run on one host (docs/performance.md).
#
#   tools/bench-step-compare.sh OLD_MSTH NEW_MSTH [MORE_MSTH...]
#
# Build an older commit's binary with e.g.
#   git worktree add /tmp/old 63a39ea && (cd /tmp/old && cargo build --release -p msth-cli)
# and pass /tmp/old/target/release/msth with target/release/msth.
set -euo pipefail
if [ "$#" -lt 2 ]; then
    echo "usage: $0 OLD_MSTH NEW_MSTH [MORE_MSTH...]" >&2
    exit 2
fi
for b in "$@"; do
    [ -x "$b" ] || { echo "$b: not an executable" >&2; exit 2; }
done
echo "host: $(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg)"
for round in 1 2; do
    for b in "$@"; do
        echo "== $b: demo, 1 thread (round $round)"
        "$b" --threads 1 bench step --only demo --reps 6 2>&1 | grep "demo (fast" || echo "(no demo line: see the output of this binary)"
    done
done
for b in "$@"; do
    echo "== $b: demo, all threads"
    "$b" bench step --only demo --reps 6 2>&1 | grep "demo (fast" || echo "(no demo line: see the output of this binary)"
done
for b in "$@"; do
    echo "== $b: paper, 1 thread"
    "$b" --threads 1 bench step --only paper --reps 2 2>&1 | grep "paper (" || echo "(no paper line)"
done
