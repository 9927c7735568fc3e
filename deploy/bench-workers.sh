#!/usr/bin/env bash
# Throughput of simulate jobs with 1 and 2 `otofit worker --threads 1` on one throwaway
# PostgreSQL (Debian's postgresql 15; run as root, the server runs as `postgres`).
# Build first (cargo build); prints wall time, rows/s and jobs per worker for each.
set -euo pipefail
BIN=${OTOFIT_BIN:-${CARGO_TARGET_DIR:-$HOME/.cache/otofit/target}/debug/otofit}
T=${TMPDIR:-/tmp}/otofit-bench-workers; D=$T/pg; PORT=${PGPORT:-55432}
rm -rf $T; mkdir -p $D; chown postgres:postgres $D
su postgres -c "/usr/lib/postgresql/15/bin/initdb -D $D/data -U postgres --auth=trust --no-sync >/dev/null"
su postgres -c "/usr/lib/postgresql/15/bin/pg_ctl -D $D/data -o '-p $PORT -k $D -c listen_addresses=127.0.0.1' -l $D/log start >/dev/null"
trap 'su postgres -c "/usr/lib/postgresql/15/bin/pg_ctl -D $D/data stop -m fast" >/dev/null' EXIT
sleep 1
for W in 1 2; do
  DB=w$W
  su postgres -c "psql -h 127.0.0.1 -p $PORT -U postgres -qc 'CREATE DATABASE $DB'" 
  URL=postgres://postgres@127.0.0.1:$PORT/$DB
  DATA=$T/data-$W
  PORT_HTTP=$((18080+W))
  $BIN serve --database $URL --data-dir $DATA --workers 0 --addr 127.0.0.1:$PORT_HTTP > $T/serve-$W.log 2>&1 &
  SP=$!
  sleep 2
  for k in 1 2 3 4; do
    curl -s -X POST -H 'content-type: application/json' -d "{\"kind\":\"simulate\",\"params\":{\"n\":10000,\"seed\":$k}}" http://127.0.0.1:$PORT_HTTP/jobs > /dev/null
  done
  PIDS=""
  t0=$(date +%s.%N)
  for i in $(seq 1 $W); do
    $BIN worker --database $URL --data-dir $DATA --threads 1 > $T/worker-$W-$i.log 2>&1 &
    PIDS="$PIDS $!"
  done
  while [ "$(curl -s "http://127.0.0.1:$PORT_HTTP/jobs?state=succeeded" | python3 -c 'import json,sys; print(len(json.load(sys.stdin)["jobs"]))')" != 4 ]; do sleep 0.2; done
  t1=$(date +%s.%N)
  echo "workers=$W seconds=$(python3 -c "print(round($t1-$t0,2))") rows_per_s=$(python3 -c "print(round(40000/($t1-$t0)))")"
  psql_out=$(su postgres -c "psql -h 127.0.0.1 -p $PORT -U postgres -d $DB -Atc \"SELECT worker, count(*), max(attempts) FROM jobs GROUP BY worker\"")
  echo "  by worker: $psql_out" | tr '\n' ' '; echo
  curl -s http://127.0.0.1:$PORT_HTTP/metrics | grep -E '^otofit_jobs\{kind="simulate"' | tr '\n' ' '; echo
  kill $PIDS $SP; wait $PIDS $SP 2>/dev/null || true
done
