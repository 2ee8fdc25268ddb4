#!/usr/bin/env bash
# GPU figures in one prepared call of the `device` tool (a lent NVIDIA H100/H200; see
# docs/performance.md, "Playback benchmarks, and a run for a lent GPU"). The device machine has
# no Rust toolchain and no network, and is lent for minutes of device time, starts included:
# everything is built and packed here, and one command there runs every measurement.
#
#   tools/device-bench.sh pack [DEMO.msth STAGE.msth [STAGE2.msth]]  # here: build, pack into .device/
#   DEVICE_BENCH_BASE=COMMIT tools/device-bench.sh pack ...  # also that commit's bench_gpu_play
#   tools/device-bench.sh run                           # there (or here, on lavapipe, as a check)
#
# `pack` builds the release binaries that measure (`bench_gpu_play`, `msth`), strips them, copies
# the two models (a fast-preset model of the built-in scene and a balanced-preset stage model;
# without arguments it makes them: `msth demo` and `msth train ... --preset balanced`, about 10
# minutes on 2 cores; STAGE2, optional, is the stage model's checkpoint exported again with other
# export settings, e.g. a newer default, timed right after STAGE) and downloads the Vulkan loader
# packages into .gl/. Both folders are kept
# out of git through .git/info/exclude. Then, on the GPU machine, with .device/ and .gl/ carried
# over:
#
#   bash tools/device-bench.sh run
#
# `run` writes report.txt under $OUT (or .device/out when $OUT is unset): the adapter, then per
# model a moving camera's playback from the play-time volume against the exact field (`msth play
# --gpu --volume`, with JSON reports beside report.txt), then per model and per samples-per-ray
# setting `bench_gpu_play` at 1352x1014 (full frames of a fixed
# and a moving camera, incremental frames, the GPU frame against the CPU renderer's; the stage
# model also with 1 and 2 samples per invocation, 128 MiB batches, comparing parameters, and
# f32 hash tables), one pass-by-pass profile, and the training step on the GPU against the CPU
# (`msth bench step --device gpu`). Every command has its own time limit, so a slow one cannot
# eat the rest.
# DEVICE_BENCH_SIZE (default 1352x1014), DEVICE_BENCH_FRAMES (24), DEVICE_BENCH_SAMPLES
# ("model fast faster"), DEVICE_BENCH_LANES ("1 2": the samples per invocation of the extra stage
# runs), DEVICE_BENCH_SCRATCH_MIB ("128 4000": the batch scratch of the extra stage runs),
# DEVICE_BENCH_STEP (1: the step benchmark) and DEVICE_BENCH_BUDGET (480: seconds after which
# no command starts) change what runs; on lavapipe use e.g. DEVICE_BENCH_SIZE=128x96
# DEVICE_BENCH_FRAMES=2 DEVICE_BENCH_STEP=0.
set -euo pipefail

root=$(cd "$(dirname "$0")/.." && pwd)
pack_dir="$root/.device"
# Models made by `pack` (training folders with checkpoints: they do not travel).
work_dir="$root/target/device-work"

die() {
    echo "device-bench: $*" >&2
    exit 1
}

exclude() {
    local f="$root/.git/info/exclude"
    mkdir -p "$(dirname "$f")"
    touch "$f"
    grep -qxF "$1" "$f" || echo "$1" >>"$f"
}

pack() {
    [ -d "$root/.git" ] || die "pack runs in the repository's checkout"
    exclude "/.device/"
    exclude "/.gl/"
    mkdir -p "$pack_dir/bin" "$pack_dir/models"
    echo "== building (release)"
    (cd "$root" && cargo build --release -p msth-cli --bin msth &&
        cargo build --release -p msth-player --example bench_gpu_play)
    for b in msth examples/bench_gpu_play; do
        cp "$root/target/release/$b" "$pack_dir/bin/"
        strip "$pack_dir/bin/$(basename "$b")"
    done
    # A baseline in the same run: DEVICE_BENCH_BASE=COMMIT builds that commit's bench_gpu_play
    # (in a temporary worktree, its own target folder) as bench_gpu_play_base.
    rm -f "$pack_dir/bin/bench_gpu_play_base"
    if [ -n "${DEVICE_BENCH_BASE:-}" ]; then
        local base_tree
        base_tree=$(mktemp -d)
        echo "== building the baseline: $DEVICE_BENCH_BASE"
        git -C "$root" worktree add --detach "$base_tree" "$DEVICE_BENCH_BASE" >/dev/null
        (cd "$base_tree" && CARGO_TARGET_DIR="$root/target/device-base" \
            cargo build --release -p msth-player --example bench_gpu_play) || {
            git -C "$root" worktree remove --force "$base_tree"
            die "the baseline $DEVICE_BENCH_BASE did not build"
        }
        git -C "$root" worktree remove --force "$base_tree"
        cp "$root/target/device-base/release/examples/bench_gpu_play" "$pack_dir/bin/bench_gpu_play_base"
        strip "$pack_dir/bin/bench_gpu_play_base"
        git -C "$root" rev-parse --short "$DEVICE_BENCH_BASE" >"$pack_dir/bin/base-commit"
    fi
    local demo="${1:-}" stage="${2:-}" stage2="${3:-}"
    local msth="$root/target/release/msth"
    if [ -z "$demo" ]; then
        demo="$work_dir/demo/scene.msth"
        if [ ! -f "$demo" ]; then
            echo "== making the demo model (msth demo, about 2.5 minutes)"
            "$msth" demo --out "$work_dir/demo"
        fi
    fi
    if [ -z "$stage" ]; then
        stage="$work_dir/stage/stage.msth"
        if [ ! -f "$stage" ]; then
            local data="$root/../shared/data/box_animated_stage"
            [ -d "$data" ] || die "no stage model given and no $data to train one from"
            echo "== training a balanced stage model (7 minutes)"
            "$msth" train "$data" --out "$work_dir/stage" --preset balanced --time-limit 420
            "$msth" export "$work_dir/stage/model.ckpt" -o "$stage"
        fi
    fi
    [ -f "$demo" ] || die "no file $demo"
    [ -f "$stage" ] || die "no file $stage"
    cp "$demo" "$pack_dir/models/demo.msth"
    cp "$stage" "$pack_dir/models/stage.msth"
    rm -f "$pack_dir/models/stage2.msth"
    if [ -n "$stage2" ]; then
        [ -f "$stage2" ] || die "no file $stage2"
        cp "$stage2" "$pack_dir/models/stage2.msth"
    fi
    echo "== Vulkan loader packages into .gl/"
    mkdir -p "$root/.gl" /tmp/amd64/partial
    local o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
    apt-get "${o[@]}" update >/dev/null
    # The Vulkan loader and the GLVND libraries the NVIDIA driver's ICD (libGLX_nvidia) loads:
    # with the loader alone the ICD fails ("Could not get 'vkCreateInstance'"), seen on an H200
    # machine on 2026-11-29.
    (cd "$root/.gl" && apt-get "${o[@]}" download libvulkan1 libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2 >/dev/null)
    local size
    size=$(du -sm "$pack_dir" "$root/.gl" | awk '{s += $1} END {print s}')
    echo "packed: $(ls "$pack_dir/bin" "$pack_dir/models" | tr '\n' ' ')(${size} MiB with .gl; the limit is 64 MiB with the tracked tree)"
    echo 'now: run(command="bash tools/device-bench.sh run", carry=[".device", ".gl"], timeout_s=540)'
}

run() {
    local out="${OUT:-$pack_dir/out}"
    mkdir -p "$out"
    local report="$out/report.txt"
    local bin="$pack_dir/bin" models="$pack_dir/models"
    [ -x "$bin/bench_gpu_play" ] && [ -x "$bin/msth" ] || die "no packed binaries in $bin: run '$0 pack' first"
    # The loader and the GLVND libraries (a bare device machine may have the loader and still
    # lack what the NVIDIA ICD needs), then the NVIDIA driver's manifests.
    if compgen -G "$root/.gl/*.deb" >/dev/null; then
        for f in "$root"/.gl/*.deb; do dpkg -x "$f" /; done
        ldconfig
    fi
    if [ -f /usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json ] && [ -z "${VK_DRIVER_FILES:-}" ]; then
        export VK_DRIVER_FILES=/usr/local/nvidia/share/vulkan/icd.d/nvidia_icd.json
    fi
    if [ -f /usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json ] && [ -z "${__EGL_VENDOR_LIBRARY_FILENAMES:-}" ]; then
        export __EGL_VENDOR_LIBRARY_FILENAMES=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
    fi
    local size="${DEVICE_BENCH_SIZE:-1352x1014}" frames="${DEVICE_BENCH_FRAMES:-24}"
    local samples="${DEVICE_BENCH_SAMPLES:-model fast faster}"
    {
        echo "# device-bench $(date -u +%FT%TZ) on $(hostname)"
        echo "commit: $(git -C "$root" rev-parse --short HEAD 2>/dev/null || echo unknown)"
        nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader 2>/dev/null || echo "nvidia-smi: none"
        echo "cpus: $(nproc)"
    } | tee "$report"
    local budget="${DEVICE_BENCH_BUDGET:-480}"
    step() {
        local limit=$1
        shift
        echo | tee -a "$report"
        echo "\$ $*" | tee -a "$report"
        # Within the call's time: a command that would start too late is skipped, said so.
        if [ $((SECONDS + 30)) -gt "$budget" ]; then
            echo "(skipped: ${SECONDS} s of the ${budget} s budget spent)" | tee -a "$report"
            return 0
        fi
        # The last lines say why a command failed; the run goes on with the next one.
        timeout "$limit" "$@" 2>&1 | tee -a "$report" || echo "(exit $?)" | tee -a "$report"
    }
    play() {
        # play MODEL SAMPLES [VAR=VALUE...]: bench_gpu_play with those variables set
        # (BENCH=bench_gpu_play_base: the baseline's binary)
        local m="$models/$1.msth" s=$2
        shift 2
        [ -f "$m" ] || return 0
        local env_args=(env -u MSTH_BENCH_SAMPLES -u MSTH_BENCH_SCRATCH_MIB -u MSTH_BENCH_COMPARE_PARAMS -u MSTH_BENCH_TABLES -u MSTH_BENCH_LANES)
        [ "$s" = model ] || env_args+=(MSTH_BENCH_SAMPLES="$s")
        step 120 "${env_args[@]}" "$@" "$bin/${BENCH:-bench_gpu_play}" "$m" "$size" "$frames"
    }
    # Most wanted first, in case time runs out: a moving camera drawn from the play-time volume
    # (`msth play --gpu --volume`, the bake waited for) against the exact field, orbit frames at
    # the bench size, per model; the bake's time and the slices' per frame are in the reports.
    for m in stage demo; do
        [ -f "$models/$m.msth" ] || continue
        for mode in volume exact; do
            local extra=()
            [ "$mode" = volume ] && extra=(--volume --bake-first)
            step 150 "$bin/msth" play "$models/$m.msth" --gpu "${extra[@]}" --path orbit \
                --frames "$frames" --size "$size" --no-video --quiet --report "$out/play-$m-$mode.json"
        done
    done
    # Then the exact renderer's bench (a balanced stage model at 1352x1014) and the baseline's
    # binary on the same model, when `pack` built one.
    play stage model
    if [ -x "$bin/bench_gpu_play_base" ]; then
        echo "baseline: $(cat "$bin/base-commit" 2>/dev/null || echo unknown)" | tee -a "$report"
        BENCH=bench_gpu_play_base play stage model
    fi
    # The same checkpoint exported with other settings, when packed (`pack DEMO STAGE STAGE2`).
    play stage2 model
    # Samples per invocation of the per-sample passes: 4 is what software adapters want; a GPU
    # may run one or two per invocation faster (more invocations, fewer live registers).
    for l in ${DEVICE_BENCH_LANES:-1 2}; do play stage model MSTH_BENCH_LANES="$l"; done
    for s in $samples; do [ "$s" = model ] || play stage "$s"; done
    # Batch size: 128 MiB of scratch per batch (the default before 2026-11-30, and still on
    # integrated and software adapters) and 4000 MiB (two batches a 1352x1014 frame, within a
    # 4 GiB binding) against the discrete GPU's default of 1 GiB.
    for mib in ${DEVICE_BENCH_SCRATCH_MIB:-128 4000}; do
        play stage model MSTH_BENCH_SCRATCH_MIB="$mib"
    done
    # Every frame comparing its parameters with the device's copy (what the player did before
    # it passed versions): the incremental frames' difference is that comparison.
    play stage model MSTH_BENCH_COMPARE_PARAMS=1
    # f32 hash tables (the default for a quantised file is binary16): what half the bytes buy.
    play stage model MSTH_BENCH_TABLES=f32
    for s in $samples; do play demo "$s"; done
    [ -x "$bin/bench_gpu_play_base" ] && BENCH=bench_gpu_play_base play demo model
    # One full frame pass by pass, at the model's own samples (on the device's clock where it
    # has timestamp queries), with 4 and with 1 sample per invocation.
    if [ -f "$models/stage.msth" ]; then
        for l in 4 1; do
            step 120 env MSTH_BENCH_PROFILE=1 MSTH_BENCH_LANES=$l "$bin/bench_gpu_play" "$models/stage.msth" "$size" 2
        done
    fi
    if [ "${DEVICE_BENCH_STEP:-1}" = 1 ]; then
        step 150 "$bin/msth" bench step --device gpu --reps 5
    fi
    echo | tee -a "$report"
    echo "report: $report" | tee -a "$report"
}

case "${1:-}" in
pack)
    shift
    pack "$@"
    ;;
run) run ;;
*)
    echo "usage: $0 pack [DEMO.msth STAGE.msth [STAGE2.msth]] | run" >&2
    exit 2
    ;;
esac
