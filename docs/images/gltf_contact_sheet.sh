#!/bin/sh
# Regenerates docs/images/gltf_box_animated.png from the two BoxAnimated datasets:
#   msth synth --gltf ../shared/data/gltf/BoxAnimated/BoxAnimated.gltf --layout stage --out out/gltf_stage
#   msth synth --gltf ../shared/data/gltf/BoxAnimated/BoxAnimated.gltf --layout object --out out/gltf_object
#   sh docs/images/gltf_contact_sheet.sh out/gltf_stage out/gltf_object
# Top row: stage cameras cam01, cam00 (held out), cam05, cam08 at frames 0, 10, 18, 29.
# Bottom row: object-layout training images 0, 30, 60, 90 composited on white.
set -e
S=${1:-out/gltf_stage}
O=${2:-out/gltf_object}
ffmpeg -hide_banner -loglevel error -y \
  -i "$S/cam01/0000.png" -i "$S/cam00/0010.png" -i "$S/cam05/0018.png" -i "$S/cam08/0029.png" \
  -i "$O/train/r_000.png" -i "$O/train/r_030.png" -i "$O/train/r_060.png" -i "$O/train/r_090.png" \
  -f lavfi -i "color=white:s=800x150" \
  -filter_complex "[0][1][2][3]hstack=4[top];\
[4]scale=150:150[a];[5]scale=150:150[b];[6]scale=150:150[c];[7]scale=150:150[d];\
[8][a]overlay=25:0[w1];[w1][b]overlay=225:0[w2];[w2][c]overlay=425:0[w3];[w3][d]overlay=625:0,format=rgb24[bottom];\
[top][bottom]vstack=2" \
  -frames:v 1 docs/images/gltf_box_animated.png
