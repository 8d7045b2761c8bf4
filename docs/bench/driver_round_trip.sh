#!/usr/bin/env bash
# Run from the workspace root after `cargo build --release --workspace --examples`.
# Round trip per driver against hapticd (release) on loopback; demo-like press on the built-in lv.
set -u
B=${BIN_DIR:-target/release}
EX=${BIN_DIR:-target/release}/examples/emulator
OUT=${OUT:-target/bench/drivers}; mkdir -p $OUT
$B/hapticd --listen 127.0.0.1:0 > $OUT/d.out 2> $OUT/d.err &
DPID=$!
for i in $(seq 50); do grep -q "listening on" $OUT/d.out && break; sleep 0.1; done
URL="http://$(sed -n 's/listening on //p' $OUT/d.out)"
run() { # name, extra args...
  local name=$1; shift
  SID=$($B/hapticctl --server $URL start lv | tail -1)
  $B/haptic-bridge --server $URL --session $SID --rearm auto --json --hold-s 3 "$@" > $OUT/$name.json 2> $OUT/$name.err
  echo "$name: $(python3 -c "import json,sys; s=json.load(open('$OUT/$name.json')); print('rtt p50/p99/max', s['rtt_p50_us'], s['rtt_p99_us'], s['rtt_max_us'], 'us; forces', s['forces_received'], 'peak %.4f N'%s['peak_force_n'])")"
  $B/hapticctl --server $URL stats $SID --json > $OUT/$name.stats.json
  echo "   server p2f p50/p99: $(python3 -c "import json; s=json.load(open('$OUT/$name.stats.json')); print(s.get('pose_to_force_p50_us'), s.get('pose_to_force_p99_us'), 'step', s.get('step_p50_us'), s.get('step_p99_us'))")"
  $B/hapticctl --server $URL stop $SID > /dev/null
}
run sim --driver sim --script press
$EX hapticmaster 30 > $OUT/hm.out 2>&1 &
EPID=$!; sleep 0.5
HM=$(sed -n 's/hapticmaster emulator on //p' $OUT/hm.out)
run hapticmaster --driver hapticmaster --hm-addr $HM --offset-m 0,0,-0.455 --duration-s 5
kill $EPID 2>/dev/null; wait $EPID 2>/dev/null
SID=$($B/hapticctl --server $URL start lv | tail -1)
$EX serial-bridge $URL $SID > $OUT/serial.json 2> $OUT/serial.err
echo "serial: $(python3 -c "import json,sys; s=json.load(open('$OUT/serial.json')); print('rtt p50/p99/max', s['rtt_p50_us'], s['rtt_p99_us'], s['rtt_max_us'], 'us; forces', s['forces_received'], 'peak %.4f N'%s['peak_force_n'])")"
$B/hapticctl --server $URL stats $SID --json > $OUT/serial.stats.json
echo "   server p2f p50/p99: $(python3 -c "import json; s=json.load(open('$OUT/serial.stats.json')); print(s.get('pose_to_force_p50_us'), s.get('pose_to_force_p99_us'), 'step', s.get('step_p50_us'), s.get('step_p99_us'))")"
kill $DPID; wait $DPID 2>/dev/null
