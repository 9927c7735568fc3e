#!/usr/bin/env bash
# One simulate job of N rows (default 40,000) on 1 and then 2 `otofit worker --threads 1`
# sharing a throwaway PostgreSQL (run as root; the server runs as `postgres`): the wall
# time from posting to `succeeded`, and the dataset compared byte for byte with
# `otofit simulate` of the same seed. Build first (cargo build). CHUNK=ROWS sets the
# serve's and workers' --chunk-rows (default theirs, 10,000).
set -euo pipefail
BIN=${OTOFIT_BIN:-${CARGO_TARGET_DIR:-$HOME/.cache/otofit/target}/debug/otofit}
PGBIN=$(ls -d /usr/lib/postgresql/*/bin | tail -1)
N=${N:-40000}
CHUNK_ARG=${CHUNK:+--chunk-rows $CHUNK}
T=${TMPDIR:-/tmp}/otofit-bench-one-job; PORT=${PGPORT:-55433}
rm -rf "$T"; mkdir -p "$T/pg"; chmod 777 "$T"; chown postgres "$T/pg"
su postgres -c "$PGBIN/initdb -D $T/pg -U postgres --auth=trust --no-sync -E UTF8 >/dev/null"
su postgres -c "$PGBIN/pg_ctl -D $T/pg -o '-p $PORT -k $T -c listen_addresses=127.0.0.1' -l $T/pg.log start >/dev/null"
trap 'su postgres -c "$PGBIN/pg_ctl -D $T/pg stop -m fast" >/dev/null' EXIT
sleep 1
"$BIN" simulate --n "$N" --seed 7 --noise-scale 1 --out "$T/cli" >/dev/null 2>&1
for W in 1 2; do
  su postgres -c "$PGBIN/psql -h 127.0.0.1 -p $PORT -U postgres -qc 'CREATE DATABASE w$W'"
  URL=postgres://postgres@127.0.0.1:$PORT/w$W; DATA=$T/data-$W; HTTP=127.0.0.1:$((18280 + W))
  "$BIN" serve --addr "$HTTP" --data-dir "$DATA" --database "$URL" --workers 0 $CHUNK_ARG >"$T/serve-$W.log" 2>&1 &
  PIDS="$!"
  sleep 2
  for i in $(seq "$W"); do
    "$BIN" worker --data-dir "$DATA" --database "$URL" --threads 1 $CHUNK_ARG >"$T/worker-$W-$i.log" 2>&1 &
    PIDS="$PIDS $!"
  done
  sleep 2
  t0=$(date +%s.%N)
  id=$(curl -s -X POST "$HTTP/jobs" -H 'content-type: application/json' \
    -d "{\"kind\":\"simulate\",\"params\":{\"n\":$N,\"seed\":7,\"noise_scale\":1}}" |
    sed -n 's/.*"id": *"\([^"]*\)".*/\1/p')
  # A poll must not take CPU from the workers it times: until the dataset's last file
  # is in place (or the job has failed), bash builtins alone look every 10 ms (a read
  # that times out on a pipe nobody writes); then the API, until it says the job ended.
  exec 9<> <(:)
  polls=0
  until [ -e "$DATA/datasets/$id/meta.json" ]; do
    read -rt 0.01 -u 9 _ || true
    polls=$((polls + 1))
    # About once a second the API, in case the job failed.
    if [ $((polls % 100)) = 0 ] && curl -s "$HTTP/jobs/$id" | grep -q '"state": *"failed"'; then break; fi
  done
  while true; do
    state=$(curl -s "$HTTP/jobs/$id" | grep -o '"state": *"[a-z_]*"' | grep -o '[a-z_]*"$' | tr -d '"')
    [ "$state" = succeeded ] || [ "$state" = failed ] && break
    read -rt 0.01 -u 9 _ || true
  done
  t1=$(date +%s.%N)
  echo "$W worker(s): $N rows, $state, $(python3 -c "print(round($t1 - $t0, 2))") s"
  ds=$(ls -d "$DATA"/datasets/* | head -1)
  for f in theta.csv x.csv; do
    if cmp -s "$ds/$f" "$T/cli/$f"; then echo "  $f: the same bytes as otofit simulate"; else echo "  $f DIFFERS"; fi
  done
  kill $PIDS; wait $PIDS 2>/dev/null || true
done
