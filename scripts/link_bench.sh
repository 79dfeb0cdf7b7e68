#!/usr/bin/env bash
# Browsing over a wide-area link (issue 32): a viewer host and a server host (network namespaces
# on a veth pair, root needed), the link limited to RATE by `tc tbf` on both ends and given
# RTT_MS of round trip by scripts/delay_relay.py in the viewer's namespace (this kernel has no
# netem). The MNI volume at 1.25 % is rendered (256², 16.6 ms frames, default oblique view) from
#   - a cache node with its own store (serve cache --db),
#   - a cache node over an S3 bucket (serve cache --store s3://…, SeaweedFS on the server host),
#   - range requests to a web server (nginx) serving the published .wspx,
#   - range requests to the bucket directly (s3://…),
# RUNS times each, printing per source, in ms after the request (the render command's start,
# client start-up included): opened, first image, converged; and the requests before the first
# packet (range sources) and the bytes received.
#   sudo bash scripts/link_bench.sh [OUT_DIR] [RATE] [RTT_MS] [RUNS]
set -euo pipefail
ROOT="$(cd "$(dirname "$0")/.." && pwd)"
OUT="${1:-$ROOT/out/link}"
RATE="${2:-30mbit}"
RTT="${3:-30}"
RUNS="${4:-3}"
BIN="${WAVESPLAT_BIN:-$ROOT/target/release/wavesplat}"   # another build to compare
VOL="$ROOT/../shared/data/mni152_t1_1mm.nii.gz"
[ -x "$BIN" ] || (cd "$ROOT" && cargo build --release -q)
mkdir -p "$OUT/www" "$OUT/weed"
[ -f "$OUT/mni.wsp" ] || "$BIN" compress "$VOL" --target-fraction 0.0125 -o "$OUT/mni.wsp" >/dev/null
"$BIN" publish "$OUT/mni.wsp" -o "$OUT/www/mni.wspx" >/dev/null
V=lbv$$; S=lbs$$
cleanup() {
  ip netns pids "$S" 2>/dev/null | xargs -r kill -9 2>/dev/null || true
  ip netns pids "$V" 2>/dev/null | xargs -r kill -9 2>/dev/null || true
  ip netns del "$V" 2>/dev/null || true
  ip netns del "$S" 2>/dev/null || true
}
trap cleanup EXIT
ip netns add "$V"; ip netns add "$S"
ip link add "${V}e" type veth peer name "${S}e"
ip link set "${V}e" netns "$V"; ip link set "${S}e" netns "$S"
ip -n "$V" addr add 10.210.0.1/24 dev "${V}e"; ip -n "$S" addr add 10.210.0.2/24 dev "${S}e"
for ns in "$V" "$S"; do ip -n "$ns" link set lo up; done
ip -n "$V" link set "${V}e" up; ip -n "$S" link set "${S}e" up
ip netns exec "$V" tc qdisc add dev "${V}e" root tbf rate "$RATE" burst 32kb latency 400ms
ip netns exec "$S" tc qdisc add dev "${S}e" root tbf rate "$RATE" burst 32kb latency 400ms
run_s() { ip netns exec "$S" "$@"; }
run_v() { ip netns exec "$V" "$@"; }
export AWS_ACCESS_KEY_ID=bench AWS_SECRET_ACCESS_KEY=bench-secret-key AWS_REGION=us-east-1 \
       AWS_ALLOW_HTTP=true
# Servers on the server host.
cat > "$OUT/nginx.conf" <<NGX
daemon off; worker_processes 1; pid $OUT/nginx.pid; error_log $OUT/nginx.err;
events { worker_connections 64; }
http { access_log off; server { listen 10.210.0.2:8080; root $OUT/www; } }
NGX
run_s nginx -c "$OUT/nginx.conf" -p "$OUT" &
rm -rf "$OUT/weed"; mkdir -p "$OUT/weed"
mkdir -p "$OUT/weed-tmp"   # its unix sockets, apart from any other SeaweedFS's
TMPDIR="$OUT/weed-tmp" run_s weed mini -dir="$OUT/weed" -bucket=archive -admin.ui=false -webdav=false >"$OUT/weed.log" 2>&1 &
for _ in $(seq 120); do
  run_s curl -s -o /dev/null http://127.0.0.1:8333/ && break; sleep 0.5
done
sleep 2
rm -rf "$OUT/node-db" "$OUT/bucket-node-db"
run_s "$BIN" serve cache --db "$OUT/node-db" --addr 0.0.0.0:50051 --insecure >/dev/null 2>"$OUT/node.log" &
AWS_ENDPOINT_URL=http://127.0.0.1:8333 run_s "$BIN" serve cache --db "$OUT/bucket-node-db" \
  --store s3://archive/wavesplat --addr 0.0.0.0:50052 --insecure >/dev/null 2>"$OUT/bucket-node.log" &
sleep 2
run_s "$BIN" cache ingest "$OUT/mni.wsp" --name mni --cache http://127.0.0.1:50051 >/dev/null
run_s "$BIN" cache ingest "$OUT/mni.wsp" --name mni --cache http://127.0.0.1:50052 >/dev/null
SHA=$(sha256sum "$OUT/mni.wsp" | cut -d' ' -f1)
# Relays on the viewer host: half the round trip each way.
HALF=$(python3 -c "print($RTT / 2)")
for p in 50051 50052 8080 8333; do
  run_v python3 "$ROOT/scripts/delay_relay.py" "$p" 10.210.0.2 "$p" "$HALF" >/dev/null &
done
sleep 1
echo "file: $(stat -c %s "$OUT/mni.wsp") bytes (.wspx $(stat -c %s "$OUT/www/mni.wspx")), link $RATE, ${RTT} ms round trip"
echo "| source | opened (ms) | first image (ms) | requests before the first packet | converged (ms) | bytes received |"
echo "|---|---|---|---|---|---|"
measure() {  # name, render source arguments...
  local name=$1; shift
  for i in $(seq "$RUNS"); do
    local log
    log=$(AWS_ENDPOINT_URL=http://127.0.0.1:8333 run_v "$BIN" render "$@" --size 256x256 \
          --frame-ms 16.6 --cpu -o "$OUT/$name.png" 2>/dev/null)
    local opened first total req bytes
    opened=$(echo "$log" | sed -n 's/^opened in \([0-9.]*\) ms.*/\1/p')
    first=$(echo "$log" | sed -n 's/.*first image \([0-9.]*\) ms.*/\1/p')
    total=$(echo "$log" | sed -n 's/.* done \([0-9.]*\) ms.*/\1/p')
    bytes=$(echo "$log" | sed -n 's/.* packets, \([0-9]*\) bytes received.*/\1/p')
    req=$(echo "$log" | sed -n 's/^range requests: [0-9]* (\([0-9]*\) before.*/\1/p')
    echo "| $name #$i | $opened | $first | ${req:--} | $total | $bytes |"
  done
}
measure "cache node (sled)" --cache http://127.0.0.1:50051 --volume mni
measure "cache node over the bucket" --cache http://127.0.0.1:50052 --volume mni
measure "range requests, nginx" http://127.0.0.1:8080/mni.wspx
measure "range requests, bucket" "s3://archive/wavesplat/volumes/$SHA.wspx"
