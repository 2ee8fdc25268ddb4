#!/usr/bin/env bash
# The project's test command (CI runs it through .ci/run): installs what the tests need, then
# checks formatting and lints and runs every test with every outside need required, so that
# nothing is skipped silently. Ends with one line: `tests: N passed, N failed, N skipped`.
#
#   1. system packages, with apt-get (as root, or through sudo), only those missing: curl,
#      chromium, ffmpeg, mesa-vulkan-drivers + libvulkan1 (lavapipe, the GPU tests' Vulkan
#      driver where no GPU exists), colmap, fonts-dejavu-core (plot text), xvfb and the X
#      libraries winit loads at run time (the window tests of `msth view`); nodejs and npm only
#      when `node` or `npm` is missing (npm is held back on some Debian releases);
#   2. the web player's npm packages: `npm ci --prefix web` (when web/node_modules is missing
#      or older than web/package-lock.json);
#   3. `cargo fmt --all -- --check`, `cargo clippy --workspace --all-targets --release -- -D
#      warnings`;
#   4. `cargo test --workspace --release --no-fail-fast` with MSTH_REQUIRE_ALL=1: a test whose
#      need (GPU adapter, browser, ffmpeg, colmap, curl, font, shared data) is missing fails
#      instead of being reported as ignored (testkit/src/lib.rs). Without ../shared/data
#      beside the repository, MSTH_REQUIRE_DATA=0: those tests show as ignored; so do the
#      SIMD kernel tests on a CPU without AVX2 or AVX-512 (MSTH_REQUIRE_AVX2=0,
#      MSTH_REQUIRE_AVX512=0), and the tmpfs full-disk test where a tmpfs cannot be mounted
#      (MSTH_REQUIRE_TMPFS=0).
#
# Usage: tools/test.sh [--no-install] [--no-lint] [-- ARGS for cargo test]
#   --no-install   skip steps 1-2 (no root; what is missing then fails the run)
#   --no-lint      skip step 3
# The requirement variables can be overridden, e.g. MSTH_REQUIRE_GPU=0 tools/test.sh.
set -euo pipefail
cd "$(dirname "$0")/.."

install=1
lint=1
while [ $# -gt 0 ]; do
  case "$1" in
    --no-install) install=0 ;;
    --no-lint) lint=0 ;;
    --) shift; break ;;
    *) echo "tools/test.sh: unknown option $1 (see the header of tools/test.sh)" >&2; exit 2 ;;
  esac
  shift
done

export CARGO_TERM_COLOR=${CARGO_TERM_COLOR:-never}

if [ "$install" = 1 ]; then
  echo "== system packages"
  sudo=""
  if [ "$(id -u)" != 0 ]; then sudo="sudo"; fi
  missing=()
  for pkg in curl chromium ffmpeg mesa-vulkan-drivers libvulkan1 colmap fonts-dejavu-core \
    xvfb libxkbcommon-x11-0 libxcursor1 libxi6 libxrandr2 libx11-xcb1; do
    if ! dpkg-query -W -f='${Status}' "$pkg" 2>/dev/null | grep -q "install ok installed"; then
      missing+=("$pkg")
    fi
  done
  if ! command -v node >/dev/null 2>&1 || ! command -v npm >/dev/null 2>&1; then
    missing+=(nodejs npm)
  fi
  if [ ${#missing[@]} -gt 0 ]; then
    if command -v apt-get >/dev/null 2>&1; then
      echo "installing: ${missing[*]}"
      $sudo apt-get update -qq
      DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -qq "${missing[@]}"
    else
      echo "no apt-get here: install ${missing[*]} yourself (the tests that need them will fail)"
    fi
  else
    echo "all present"
  fi
  echo "== npm packages of the web player"
  if [ ! -d web/node_modules ] || [ web/package-lock.json -nt web/node_modules ]; then
    npm ci --prefix web --no-audit --no-fund
  else
    echo "web/node_modules is up to date"
  fi
fi

# Every need required: a missing one fails its tests instead of skipping them.
export MSTH_REQUIRE_ALL=${MSTH_REQUIRE_ALL:-1}
# AVX2 and AVX-512 are the CPU's, not something step 1 can install: without them the comparisons
# of the SIMD kernels with the scalar ones (core/tests/grid_simd.rs, core/tests/mlp_simd.rs) show
# as ignored.
export MSTH_REQUIRE_AVX2=${MSTH_REQUIRE_AVX2:-0}
export MSTH_REQUIRE_AVX512=${MSTH_REQUIRE_AVX512:-0}
# Mounting a small tmpfs (the full-disk test of cli/tests/crash_safety.rs) needs root with
# CAP_SYS_ADMIN, which containers often lack: without it that test shows as ignored (the same
# test through a file size limit runs everywhere).
export MSTH_REQUIRE_TMPFS=${MSTH_REQUIRE_TMPFS:-0}
if [ ! -d ../shared/data ] && [ -z "${MSTH_REQUIRE_DATA:-}" ]; then
  echo "note: no ../shared/data beside the repository: the tests that read it will show as ignored"
  export MSTH_REQUIRE_DATA=0
fi

if [ "$lint" = 1 ]; then
  echo "== fmt"
  cargo fmt --all -- --check
  echo "== clippy"
  cargo clippy --workspace --all-targets --release -- -D warnings
fi

echo "== tests"
log=$(mktemp)
trap 'rm -f "$log"' EXIT
set +e
cargo test --workspace --release --no-fail-fast "$@" 2>&1 | tee "$log"
status=${PIPESTATUS[0]}
set -e
echo "== summary"
# What was skipped for a missing need, then one line for the whole run (cargo prints one
# `test result:` line per test binary).
grep -E '^test .* \.\.\. ignored \(no ' "$log" || true
awk '/^test result:/ { p += $4; f += $6; i += $8 } END { printf "tests: %d passed, %d failed, %d skipped\n", p, f, i }' "$log"
exit "$status"
