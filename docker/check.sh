#!/usr/bin/env bash
# A maintainer's check of the image against a real Docker engine (issue 51). Linux, as root,
# from the repository root, after `docker build -t relightcli .`:
#   docker/check.sh [IMAGE]        (IMAGE: relightcli)
# CHECK_USER: the ordinary user who owns the folders (created when missing; relight-check).
# It checks: the README's command word for word with out/ owned by that user and with out/
# missing, `docker stop` at several moments, `relight info` under --cpus=1, a 6-photo batch
# under --cpus=1 --memory=1g, --read-only and --user runs writing nothing to ~ and printing no
# warning, and the image size. Exit status 0 when every check passes; takes a few minutes.
set -uo pipefail
IMAGE=${1:-relightcli}
CHECK_USER=${CHECK_USER:-relight-check}
REPO=$(cd "$(dirname "$0")/.." && pwd)
MAX_IMAGE_BYTES=800000000
failures=0
report=()

pass() { report+=("ok    $1"); echo "ok    $1"; }
fail() { report+=("FAIL  $1"); echo "FAIL  $1"; failures=$((failures + 1)); }

[ "$(id -u)" = 0 ] || { echo "run as root (it creates $CHECK_USER and chowns folders to it)"; exit 2; }
id -u "$CHECK_USER" >/dev/null 2>&1 || useradd --create-home "$CHECK_USER"
uid=$(id -u "$CHECK_USER")
gid=$(id -g "$CHECK_USER")
work=$(mktemp -d)
chmod 755 "$work"
trap 'docker rm -f relight-check-stop relight-check-batch >/dev/null 2>&1; rm -rf "$work"' EXIT

# A job folder as a user keeps it: in/ with the example photo, its mask and a sky
new_job() {  # new_job NAME PHOTOS
    local dir="$work/$1" i
    mkdir -p "$dir/in"
    for i in $(seq 1 "$2"); do
        cp "$REPO/examples/skier.jpg" "$dir/in/skier$i.jpg"
        cp "$REPO/examples/skier_mask.png" "$dir/in/skier${i}_mask.png"
    done
    cp "$REPO/examples/noon_grass.hdr" "$dir/in/sky.hdr"
    chown -R "$uid:$gid" "$dir"
    echo "$dir"
}

owners_of_outputs() { find "$1/out" -type f -printf '%U:%G\n' | sort -u | tr '\n' ' '; }
now_ms() { date +%s%3N; }

# 1. The README's command, word for word, as an ordinary user would run it
for case in owned missing; do
    dir=$(new_job "readme-$case" 1)
    if [ "$case" = owned ]; then install -d -o "$uid" -g "$gid" "$dir/out"; fi  # else Docker creates it, as root
    (cd "$dir" && docker run --rm -v "$PWD/in:/in" -v "$PWD/out:/out" "$IMAGE" /in --hdr /in/sky.hdr -o /out) \
        > "$dir/log" 2>&1
    code=$?
    owners=$(owners_of_outputs "$dir")
    if [ "$code" = 0 ] && [ -f "$dir/out/skier1.png" ] && [ "$owners" = "$uid:$gid " ]; then
        pass "README command, out/ $case: exit 0, outputs owned by $CHECK_USER ($owners)"
    else
        fail "README command, out/ $case: exit $code, outputs owned by '$owners' ($(tail -1 "$dir/log"))"
    fi
done

# 2. docker stop at several moments: start-up, loading the networks, inside the batch
for delay in 0.15 1 3 8; do
    dir=$(new_job "stop$delay" 3)
    install -d -o "$uid" -g "$gid" "$dir/out"
    docker run -d --name relight-check-stop -v "$dir/in:/in" -v "$dir/out:/out" "$IMAGE" \
        /in --hdr /in/sky.hdr -o /out --workers 1 >/dev/null
    sleep "$delay"
    start=$(now_ms)
    docker stop relight-check-stop >/dev/null
    took=$(($(now_ms) - start))
    code=$(docker inspect -f '{{.State.ExitCode}}' relight-check-stop)
    logs=$(docker logs relight-check-stop 2>&1)
    docker rm relight-check-stop >/dev/null
    hidden=$(find "$dir/out" -name '.*' | wc -l)
    if [ "$code" = 143 ] && [ "$took" -lt 1500 ] && [ "$hidden" = 0 ] && ! grep -q Traceback <<<"$logs"; then
        pass "docker stop after ${delay} s: exit 143 in $took ms, no temporary file ($(tail -1 <<<"$logs"))"
    else
        fail "docker stop after ${delay} s: exit $code in $took ms, $hidden temporary file(s): $(tail -3 <<<"$logs")"
    fi
done

# 3. --cpus=1: one thread, one worker
info=$(docker run --rm --cpus=1 "$IMAGE" info --json)
threads=$(python3 -c 'import json, sys; r = json.load(sys.stdin); print(r["threads"], r["workers"], r["cores"])' <<<"$info")
if [ "${threads%% *}" = 1 ]; then pass "--cpus=1: threads, workers, cores = $threads"; else fail "--cpus=1: threads, workers, cores = $threads"; fi

# 4. A 6-photo batch under --cpus=1 --memory=1g
dir=$(new_job batch 6)
install -d -o "$uid" -g "$gid" "$dir/out"
start=$(now_ms)
docker run --name relight-check-batch --cpus=1 --memory=1g -v "$dir/in:/in" -v "$dir/out:/out" "$IMAGE" \
    /in --hdr /in/sky.hdr -o /out > "$dir/log" 2>&1
code=$?
oom=$(docker inspect -f '{{.State.OOMKilled}}' relight-check-batch)
docker rm relight-check-batch >/dev/null
written=$(find "$dir/out" -name 'skier?.png' | wc -l)
if [ "$code" = 0 ] && [ "$written" = 6 ] && [ "$oom" = false ]; then
    pass "6 photos under --cpus=1 --memory=1g: exit 0, 6 written in $((($(now_ms) - start) / 1000)) s"
else
    fail "6 photos under --cpus=1 --memory=1g: exit $code, $written written, OOM killed: $oom ($(tail -2 "$dir/log"))"
fi

# 5. Nothing written to ~ and no warning: a read-only root, and a --user without a home
for flags in "--read-only" "--user $uid:$gid"; do
    # shellcheck disable=SC2086  # the flags are two words on purpose
    err=$(docker run --rm $flags "$IMAGE" info 2>&1 >/dev/null)
    if [ -z "$err" ]; then pass "info $flags: nothing on stderr"; else fail "info $flags: $err"; fi
done

# 6. The image size
size=$(docker image inspect -f '{{.Size}}' "$IMAGE")
if [ "$size" -le "$MAX_IMAGE_BYTES" ]; then pass "image size $((size / 1000000)) MB"; else fail "image size $((size / 1000000)) MB > $((MAX_IMAGE_BYTES / 1000000)) MB"; fi

echo
printf '%s\n' "${report[@]}"
exit $((failures > 0))
