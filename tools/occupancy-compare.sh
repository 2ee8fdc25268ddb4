#!/usr/bin/env bash
# The occupancy grid written by `msth export` against the density-only grid, on one checkpoint
# (docs/playback.md, "The occupancy grid"): exports both, renders a
# held-out camera at every frame with each (full frames on the CPU), and prints the held-out
# PSNR of both against the dataset's frames, the worst frame of one against the other, and
# the CPU full-frame rate of both at that camera (two rounds, alternated).
#
#   tools/occupancy-compare.sh CHECKPOINT CAMERA GT_DIR FRAMES [OUT_DIR]
#
# CAMERA is the file's camera index of the held-out camera (`msth render CKPT --list-cameras`);
# GT_DIR holds its frames as 0000.png, 0001.png, ... (a DyNeRF layout's camNN/ folder).
# Needs `msth` on PATH (or MSTH=path) and ffmpeg; SIZE (default 200x150) sets the timed frames' size.
set -euo pipefail
if [ "$#" -lt 4 ]; then
    echo "usage: $0 CHECKPOINT CAMERA GT_DIR FRAMES [OUT_DIR]" >&2
    exit 2
fi
msth=${MSTH:-msth}
ckpt=$1 cam=$2 gt=$3 frames=$4
out=${5:-$(mktemp -d)}
mkdir -p "$out"
"$msth" export "$ckpt" -o "$out/density.msth" --occupancy-from density | grep "occupancy grid"
"$msth" export "$ckpt" -o "$out/carved.msth" | grep "occupancy grid"
for v in density carved; do
    "$msth" play "$out/$v.msth" --path "$cam" --frames "$frames" --no-incremental --cpu \
        -o "$out/$v" --no-video --quiet
done
psnr() {
    ffmpeg -v info -i "$1" -i "$2" -lavfi "[0:v]format=rgb24[a];[1:v]format=rgb24[b];[a][b]psnr" \
        -f null - 2>&1 | grep -o "average:[0-9.a-z]*" | cut -d: -f2
}
: > "$out/psnr.txt"
for k in $(seq 0 $((frames - 1))); do
    f=$(printf "frame_%05d.png" "$k")
    g=$(printf "%s/%04d.png" "$gt" "$k")
    echo "$k $(psnr "$out/density/$f" "$g") $(psnr "$out/carved/$f" "$g") $(psnr "$out/carved/$f" "$out/density/$f")" >> "$out/psnr.txt"
done
awk '{d += $2; s += $3; if ($4 != "inf" && (w == "" || $4 < w)) w = $4}
     END {printf "held-out PSNR over %d frames: density grid %.4f dB, carved %.4f dB; carved against density, worst frame %s dB\n", NR, d / NR, s / NR, (w == "" ? "inf" : w)}' "$out/psnr.txt"
for round in 1 2; do
    for v in density carved; do
        echo -n "round $round, $v: "
        "$msth" --threads 1 bench play "$out/$v.msth" --cpu --size "${SIZE:-200x150}" --frames 6 --path "$cam" | grep "full (baseline)"
    done
done
