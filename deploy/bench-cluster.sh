#!/usr/bin/env bash
# The cluster check on one machine: PostgreSQL (Debian's 15, run as `postgres`),
# one `serve --workers 0` and 3 `worker --threads 1`; a 200,000-row simulate job; one
# worker is `kill -9`ed once a few chunks are done. Prints the chunks each worker
# finished, the job's attempts, the wall time, and the SHA-256 of theta.csv and x.csv
# beside those of the same job run by one SQLite `serve` (the zero-configuration
# default). Build first (cargo build).
set -euo pipefail
BIN=${OTOFIT_BIN:-${CARGO_TARGET_DIR:-$HOME/.cache/otofit/target}/debug/otofit}
N=${ROWS:-200000}; SEED=${SEED:-7}; LEASE=${LEASE:-10}
T=${TMPDIR:-/tmp}/otofit-bench-cluster; D=$T/pg; PORT=${PGPORT:-55433}; HTTP=127.0.0.1:18091
PG=$(ls -d /usr/lib/postgresql/*/bin | tail -1)
rm -rf $T; mkdir -p $D; chown postgres:postgres $D
su postgres -c "$PG/initdb -D $D/data -U postgres --auth=trust --no-sync >/dev/null"
su postgres -c "$PG/pg_ctl -D $D/data -o '-p $PORT -k $D -c listen_addresses=127.0.0.1' -l $D/log start >/dev/null"
PIDS=""
trap 'kill $PIDS 2>/dev/null || true; su postgres -c "$PG/pg_ctl -D $D/data stop -m fast" >/dev/null' EXIT
sleep 1
URL=postgres://postgres@127.0.0.1:$PORT/postgres
BODY="{\"kind\":\"simulate\",\"params\":{\"n\":$N,\"seed\":$SEED}}"
psql_() { su postgres -c "psql -h 127.0.0.1 -p $PORT -U postgres -Atc \"$1\""; }
state() { curl -s "http://$1/jobs/$2" | python3 -c 'import json,sys; print(json.load(sys.stdin)["state"])'; }

$BIN serve --database $URL --data-dir $T/data --workers 0 --addr $HTTP > $T/serve.log 2>&1 &
PIDS="$PIDS $!"; sleep 2
ID=$(curl -s -X POST -H 'content-type: application/json' -d "$BODY" http://$HTTP/jobs | python3 -c 'import json,sys; print(json.load(sys.stdin)["id"])')
t0=$(date +%s.%N)
W=()
for i in 1 2 3; do
  $BIN worker --database $URL --data-dir $T/data --threads 1 --lease-seconds $LEASE > $T/worker-$i.log 2>&1 &
  W+=($!); PIDS="$PIDS $!"
done
until [ "$(psql_ "SELECT count(*) FROM job_chunks WHERE state='done'")" -ge 4 ]; do sleep 0.2; done
kill -9 "${W[1]}"
echo "killed worker 2 (pid ${W[1]}) at $(python3 -c "print(round($(date +%s.%N)-$t0,1))") s with $(psql_ "SELECT count(*) FROM job_chunks WHERE state='done'") chunks done"
until [ "$(state $HTTP $ID)" = succeeded ]; do sleep 0.5; done
t1=$(date +%s.%N)
echo "cluster: $N rows in $(python3 -c "print(round($t1-$t0,1))") s; attempts $(psql_ "SELECT attempts FROM jobs WHERE id='$ID'")"
echo "chunks done by worker (worker|chunks|max chunk attempts):"
psql_ "SELECT worker, count(*), max(attempts) FROM job_chunks WHERE job_id='$ID' GROUP BY worker ORDER BY worker"
echo "killed worker's pid: ${W[1]}"
CL=$(cd $T/data/datasets/$ID && sha256sum theta.csv x.csv)

# The same job on the default: one process, SQLite, embedded workers.
$BIN serve --data-dir $T/single --addr 127.0.0.1:18092 > $T/single.log 2>&1 &
SP=$!; PIDS="$PIDS $SP"; sleep 2
ID2=$(curl -s -X POST -H 'content-type: application/json' -d "$BODY" http://127.0.0.1:18092/jobs | python3 -c 'import json,sys; print(json.load(sys.stdin)["id"])')
until [ "$(state 127.0.0.1:18092 $ID2)" = succeeded ]; do sleep 0.5; done
SI=$(cd $T/single/datasets/$ID2 && sha256sum theta.csv x.csv)
echo "cluster:        $(echo "$CL" | awk '{print $2": "$1}' | tr '\n' ' ')"
echo "single process: $(echo "$SI" | awk '{print $2": "$1}' | tr '\n' ' ')"
echo "rows: cluster $(($(wc -l < $T/data/datasets/$ID/theta.csv) - 1)), single $(($(wc -l < $T/single/datasets/$ID2/theta.csv) - 1))"
[ "$CL" = "$SI" ] && echo "identical" || { echo "DIFFERENT"; exit 1; }
