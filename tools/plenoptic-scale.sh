#!/usr/bin/env bash
# Trains from a synthetic dataset of Plenoptic Video scale, to check that data larger than RAM
# trains in bounded memory through the frame cache. Nothing is committed or kept: the videos,
# the cache and the run live in a temporary folder that is deleted at the end.
#
# What it does:
#   1. makes CAMS videos camNN.mp4 (default 19) of FRAMES frames (300) at WxH (1352x1014) with
#      ffmpeg's lavfi `testsrc2` source (hue-shifted per camera), H.264 ultrafast;
#   2. writes poses_bounds.npy for a forward-facing arc of cameras (pure Python, no numpy);
#   3. runs `msth train DIR --format dynerf --cache CACHE --no-eval --iters ITERS` under
#      `/usr/bin/time -v` and prints the cache build (load) time, the cache size, the training
#      speed and the peak resident set size.
#
# Usage: tools/plenoptic-scale.sh            (full scale: ~23 GiB cache, needs ~25 GiB of disk)
#        CAMS=3 FRAMES=30 W=320 H=240 ITERS=20 tools/plenoptic-scale.sh   (a quick check)
# Environment: MSTH (the msth binary, default target/release/msth), WORK (a scratch folder on a
# disk with room, default a new folder under /tmp), PRESET (fast), BATCH (the preset's).
set -euo pipefail

CAMS=${CAMS:-19}
FRAMES=${FRAMES:-300}
W=${W:-1352}
H=${H:-1014}
ITERS=${ITERS:-300}
PRESET=${PRESET:-fast}
MSTH=${MSTH:-target/release/msth}
WORK=${WORK:-$(mktemp -d /tmp/msth-plenoptic.XXXXXX)}
trap 'rm -rf "$WORK"' EXIT

for tool in ffmpeg python3 /usr/bin/time; do
  command -v "$tool" >/dev/null || { echo "needs $tool" >&2; exit 1; }
done
[ -x "$MSTH" ] || { echo "no msth binary at $MSTH (cargo build --release -p msth-cli)" >&2; exit 1; }

data="$WORK/data"
mkdir -p "$data"
echo "== making $CAMS videos of $FRAMES frames at ${W}x${H} in $data"
t0=$(date +%s)
for ((c = 0; c < CAMS; c++)); do
  name=$(printf 'cam%02d' "$c")
  ffmpeg -v error -nostdin -f lavfi -i "testsrc2=size=${W}x${H}:rate=30" \
    -vf "hue=h=$((c * 360 / CAMS))" -frames:v "$FRAMES" \
    -c:v libx264 -preset ultrafast -crf 23 -pix_fmt yuv420p "$data/$name.mp4"
done
echo "videos: $(du -sh "$data" | cut -f1) in $(( $(date +%s) - t0 )) s"

echo "== poses_bounds.npy (forward-facing arc)"
python3 - "$data/poses_bounds.npy" "$CAMS" "$W" "$H" <<'PY'
import math, struct, sys
path, n, w, h = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
focal = 0.9 * w
rows = []
for i in range(n):
    a = (i / max(n - 1, 1) - 0.5) * math.radians(60)
    # OpenGL camera: looks down -Z towards the origin from distance 4 on an arc in the XZ plane.
    c = (4 * math.sin(a), 0.3 * math.sin(3 * a), 4 * math.cos(a))
    back = (math.sin(a), 0.0, math.cos(a))
    up = (0.0, 1.0, 0.0)
    right = (up[1] * back[2] - up[2] * back[1], up[2] * back[0] - up[0] * back[2],
             up[0] * back[1] - up[1] * back[0])
    y = (back[1] * right[2] - back[2] * right[1], back[2] * right[0] - back[0] * right[2],
         back[0] * right[1] - back[1] * right[0])
    down = tuple(-v for v in y)
    hwf = (h, w, focal)
    row = []
    for r in range(3):  # LLFF columns: down, right, backwards, centre, hwf
        row += [down[r], right[r], back[r], c[r], hwf[r]]
    rows.append(row + [1.5, 20.0])
header = "{'descr': '<f8', 'fortran_order': False, 'shape': (%d, 17), }" % n
header += " " * ((64 - (10 + len(header) + 1) % 64) % 64) + "\n"
with open(path, "wb") as f:
    f.write(b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header.encode())
    for row in rows:
        f.write(struct.pack("<17d", *row))
PY

echo "== training $ITERS steps ($PRESET preset) through the frame cache"
log="$WORK/train.log"
set +e
/usr/bin/time -v "$MSTH" train "$data" --format dynerf --out "$WORK/out" --cache "$WORK/cache" \
  --preset "$PRESET" --iters "$ITERS" --no-eval ${BATCH:+--batch-rays "$BATCH"} >"$log" 2>&1
rc=$?
set -e
grep -E "^(dataset|model|trained)" "$log" || true
if [ $rc -ne 0 ]; then tail -20 "$log"; echo "training failed ($rc)" >&2; exit $rc; fi
echo "cache: $(ls -l "$WORK"/cache/*.frames | awk '{printf "%s bytes (%.2f GiB)", $5, $5 / 2^30}')"
grep -E "Maximum resident set size|Elapsed \(wall clock\)" "$log"
echo "== removing $WORK"
