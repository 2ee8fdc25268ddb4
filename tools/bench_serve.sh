#!/usr/bin/env bash
# Load benchmark of `msth serve` beside nginx serving the same file on the same host, in the same
# run: wrk (2 threads, 32 connections by default) against each in turn, for whole-file GETs and
# for 64 KiB Range GETs at random 64 KiB-aligned offsets. Prints requests per second, latency
# percentiles and the server's CPU time per request (user + system, from /proc: on a busy host
# it moves less than the rates do) side by side, the ratio msth/nginx, and the resident memory
# of `msth serve` before and after (with --soak, after that many seconds of mixed load).
#
#   tools/bench_serve.sh [--msth PATH] [--base PATH] [--size BYTES] [--duration SECS]
#                        [--rounds N] [--threads N] [--connections N] [--soak SECS] [--keep DIR]
#
#   --msth PATH        the msth binary (default: $CARGO_TARGET_DIR or target, release/msth)
#   --base PATH        another msth binary (an older build) measured in the same rounds
#   --size BYTES       the served file's size (default 1048576: 1 MiB of random bytes; the
#                      server never parses what it serves)
#   --duration SECS    each wrk run (default 10)
#   --rounds N         rounds of the four runs, alternating the servers (default 3); the table
#                      shows each figure's median over the rounds
#   --soak SECS        then load msth serve this long (whole-file and Range GETs alternating in
#                      60 s runs) and print its memory before and after (default 0: none)
#   --keep DIR         leave the served file, configs and logs in DIR
#
# Needs nginx and wrk (`apt-get install nginx-light wrk`, or nginx); both run as the calling
# user on loopback ports, nginx with its own temporary prefix (its access log on, as msth serve
# logs each request; both logs go to files). Nothing here decides pass or fail: it measures.
set -euo pipefail
cd "$(dirname "$0")/.."

msth="${CARGO_TARGET_DIR:-target}/release/msth"
base=""
size=1048576
duration=10
rounds=3
threads=2
connections=32
soak=0
keep=""
while [ $# -gt 0 ]; do
  case "$1" in
    --msth) msth="$2"; shift ;;
    --base) base="$2"; shift ;;
    --size) size="$2"; shift ;;
    --duration) duration="$2"; shift ;;
    --rounds) rounds="$2"; shift ;;
    --threads) threads="$2"; shift ;;
    --connections) connections="$2"; shift ;;
    --soak) soak="$2"; shift ;;
    --keep) keep="$2"; shift ;;
    *) echo "bench_serve.sh: unknown option $1 (see the header of tools/bench_serve.sh)" >&2; exit 2 ;;
  esac
  shift
done
for tool in wrk nginx; do
  command -v "$tool" >/dev/null 2>&1 || [ -x "/usr/sbin/$tool" ] || { echo "bench_serve.sh: $tool is not installed" >&2; exit 2; }
done
nginx_bin=$(command -v nginx || echo /usr/sbin/nginx)
[ -x "$msth" ] || { echo "bench_serve.sh: no msth binary at $msth (cargo build --release, or --msth PATH)" >&2; exit 2; }

if [ -n "$keep" ]; then mkdir -p "$keep"; dir=$(cd "$keep" && pwd); else dir=$(mktemp -d); fi
pids=()
cleanup() {
  for p in "${pids[@]}"; do kill "$p" 2>/dev/null || true; done
  [ -f "$dir/nginx/nginx.pid" ] && kill "$(cat "$dir/nginx/nginx.pid")" 2>/dev/null || true
  [ -n "$keep" ] || rm -rf "$dir"
}
trap cleanup EXIT

mkdir -p "$dir/models" "$dir/nginx/logs" "$dir/nginx/tmp"
head -c "$size" /dev/urandom > "$dir/models/bench.msth"
# nginx's workers run as another user when started by root: let them read the file.
chmod a+rx "$dir" "$dir/models" && chmod a+r "$dir/models/bench.msth"

free_port() { python3 -c 'import socket; s=socket.socket(); s.bind(("127.0.0.1",0)); print(s.getsockname()[1])'; }
msth_port=$(free_port)
base_port=$(free_port)
nginx_port=$(free_port)

cat > "$dir/nginx/nginx.conf" <<EOF
worker_processes auto;
pid $dir/nginx/nginx.pid;
error_log $dir/nginx/logs/error.log;
events { worker_connections 1024; }
http {
  access_log $dir/nginx/logs/access.log;
  client_body_temp_path $dir/nginx/tmp;
  proxy_temp_path $dir/nginx/tmp;
  fastcgi_temp_path $dir/nginx/tmp;
  uwsgi_temp_path $dir/nginx/tmp;
  scgi_temp_path $dir/nginx/tmp;
  sendfile on;
  tcp_nopush on;
  keepalive_requests 100000;
  default_type application/octet-stream;
  server {
    listen 127.0.0.1:$nginx_port;
    location /models/ { alias $dir/models/; }
  }
}
EOF
"$nginx_bin" -p "$dir/nginx" -c "$dir/nginx/nginx.conf"
"$msth" serve "$dir/models" --addr "127.0.0.1:$msth_port" > "$dir/msth.out" 2> "$dir/msth.log" &
msth_pid=$!
pids+=("$msth_pid")
servers="msth nginx"
if [ -n "$base" ]; then
  "$base" serve "$dir/models" --addr "127.0.0.1:$base_port" > "$dir/base.out" 2> "$dir/base.log" &
  base_pid=$!
  pids+=("$base_pid")
  servers="msth base nginx"
fi
for _ in $(seq 100); do
  curl -sf -o /dev/null "http://127.0.0.1:$msth_port/models/bench.msth" && curl -sf -o /dev/null "http://127.0.0.1:$nginx_port/models/bench.msth" && break
  sleep 0.1
done

cat > "$dir/range.lua" <<EOF
-- 64 KiB Range GETs at random 64 KiB-aligned offsets of the file.
local blocks = math.max(1, math.floor($size / 65536))
request = function()
  local off = math.random(0, blocks - 1) * 65536
  return wrk.format(nil, nil, { Range = "bytes=" .. off .. "-" .. (off + 65535) })
end
EOF

rss_kib() { awk '/VmRSS/ {print $2}' "/proc/$1/status"; }
# CPU clock ticks (user + system) of the processes given.
ticks() { local t=0 p; for p in "$@"; do t=$((t + $(awk '{print $14 + $15}' "/proc/$p/stat"))); done; echo "$t"; }
hz=$(getconf CLK_TCK)

# One wrk run against the server whose processes are PIDS: prints "RPS P50 P90 P99 CPU_US ERRORS"
# (latencies in ms, the server's CPU microseconds per request).
run_wrk() {
  local url="$1" script="$2"; shift 2
  local args=(-t"$threads" -c"$connections" -d"${duration}s" --latency)
  [ -n "$script" ] && args+=(-s "$script")
  local t0 t1
  t0=$(ticks "$@")
  wrk "${args[@]}" "$url" > "$dir/wrk.out"
  t1=$(ticks "$@")
  awk -v cpu=$((t1 - t0)) -v hz="$hz" '
    function ms(v) { if (v ~ /us$/) return v/1000; if (v ~ /ms$/) return v+0; if (v ~ /s$/) return v*1000; return v }
    /requests in/ { n = $1 }
    /Requests\/sec/ { rps = $2 }
    /^ +50%/ { p50 = ms($2) } /^ +90%/ { p90 = ms($2) } /^ +99%/ { p99 = ms($2) }
    /Non-2xx|Socket errors/ { err = err " " $0 }
    END { printf "%s %.3f %.3f %.3f %.1f%s\n", rps, p50, p90, p99, 1e6 * cpu / hz / n, (err == "" ? "" : " ERR:" err) }' "$dir/wrk.out"
}

msth_url="http://127.0.0.1:$msth_port/models/bench.msth"
base_url="http://127.0.0.1:$base_port/models/bench.msth"
nginx_url="http://127.0.0.1:$nginx_port/models/bench.msth"
[ -z "$base" ] || for _ in $(seq 100); do curl -sf -o /dev/null "$base_url" && break; sleep 0.1; done
rss_before=$(rss_kib "$msth_pid")
echo "file: $size bytes; wrk -t$threads -c$connections -d${duration}s, $rounds rounds; $(nproc) cores, load average $(cut -d' ' -f1-3 /proc/loadavg)"
echo "msth serve: $("$msth" --version 2>/dev/null || echo "$msth"), RSS $((rss_before / 1024)) MiB at start; nginx: $("$nginx_bin" -v 2>&1 | sed 's/nginx version: //')"
results="$dir/results.txt"
: > "$results"
for r in $(seq "$rounds"); do
  for kind in whole range; do
    script=""; [ "$kind" = range ] && script="$dir/range.lua"
    for server in $servers; do
      case $server in
        msth) url=$msth_url; procs=("$msth_pid") ;;
        base) url=$base_url; procs=("$base_pid") ;;
        nginx) url=$nginx_url; mapfile -t procs < <(pgrep -P "$(cat "$dir/nginx/nginx.pid")") ;;
      esac
      line=$(run_wrk "$url" "$script" "${procs[@]}")
      echo "$kind $server $line" >> "$results"
      echo "  round $r: $kind $server: $line"
    done
  done
done

median() { sort -g | awk '{ v[NR] = $1 } END { if (NR % 2) print v[(NR + 1) / 2]; else print (v[NR / 2] + v[NR / 2 + 1]) / 2 }'; }
fig() { awk -v k="$1" -v s="$2" -v c="$3" '$1 == k && $2 == s { print $c }' "$results" | median; }
echo
printf '%-30s %12s %10s %10s %10s %12s\n' "" "requests/s" "p50 ms" "p90 ms" "p99 ms" "CPU us/req"
for kind in whole range; do
  label="whole file ($size B)"; [ "$kind" = range ] && label="64 KiB Range"
  for server in $servers; do
    printf '%-30s %12.0f %10.3f %10.3f %10.3f %12.1f\n' "$label, $server" "$(fig $kind $server 3)" "$(fig $kind $server 4)" "$(fig $kind $server 5)" "$(fig $kind $server 6)" "$(fig $kind $server 7)"
  done
  awk -v a="$(fig $kind msth 3)" -v b="$(fig $kind nginx 3)" -v l="$label" 'BEGIN { printf "%-30s %12.2fx nginx\n", l ", msth/nginx", a / b }'
  [ -z "$base" ] || awk -v a="$(fig $kind base 3)" -v b="$(fig $kind nginx 3)" -v l="$label" 'BEGIN { printf "%-30s %12.2fx nginx\n", l ", base/nginx", a / b }'
done
echo "msth serve RSS: $((rss_before / 1024)) MiB at start, $(( $(rss_kib "$msth_pid") / 1024 )) MiB after the runs"

if [ "$soak" -gt 0 ]; then
  start_rss=$(rss_kib "$msth_pid")
  end=$((SECONDS + soak))
  n=0
  while [ $SECONDS -lt "$end" ]; do
    left=$((end - SECONDS)); d=$((left < 60 ? left : 60)); [ "$d" -lt 1 ] && break
    script=""; [ $((n % 2)) = 1 ] && script="$dir/range.lua"
    wrk -t"$threads" -c"$connections" -d"${d}s" ${script:+-s "$script"} "$msth_url" > /dev/null
    n=$((n + 1))
    echo "  soak: $((SECONDS - end + soak)) s, RSS $(( $(rss_kib "$msth_pid") / 1024 )) MiB"
  done
  sleep 2
  echo "msth serve RSS over a ${soak} s soak: $((start_rss / 1024)) MiB before, $(( $(rss_kib "$msth_pid") / 1024 )) MiB after (KiB: $start_rss -> $(rss_kib "$msth_pid"))"
fi
