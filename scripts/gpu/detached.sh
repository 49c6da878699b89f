#!/usr/bin/env bash
# Work longer than one remote command may run (a shell session or batch job with a time limit,
# e.g. 10 minutes) on a GPU host where a process that started its own session keeps running after
# that command ends, so
#   bash scripts/gpu/detached.sh start NAME CMD [ARG ...]   runs CMD detached (setsid), its output
#                                                          and exit status in /tmp/detached/NAME/,
#                                                          and $OUT pointed at /tmp/detached/NAME/out
#   bash scripts/gpu/detached.sh wait NAME SECONDS [DIR ...]  follows that output until CMD ends or
#                                                          SECONDS pass, then packs NAME's out folder
#                                                          and the files under 3 MB in each DIR (outside
#                                                          videos/) into $OUT/NAME.tar.gz (in 15 MiB
#                                                          parts NAME.tar.gz.part-NN when larger), the first
#                                                          episode of each videos/ folder (or the episode
#                                                          videos whose path matches VIDEOS, a find -path
#                                                          pattern) into
#                                                          $OUT/NAME-videos.tar.gz, both partial if
#                                                          CMD is still running (then with the last line
#                                                          of each log in the out folder)
# Commands that follow each other on the same host find the same process. `wait` exits 0
# when CMD ended with 0, 1 when it failed, 3 while it is still running.
set -uo pipefail
usage() { echo "usage: detached.sh start NAME CMD [ARG ...] | wait NAME SECONDS [DIR ...]" >&2; exit 2; }
[ $# -ge 2 ] || usage
mode=$1 name=$2; shift 2
# The name becomes a folder that `start` empties: a plain name only.
[[ "$name" =~ ^[A-Za-z0-9_][A-Za-z0-9._-]*$ ]] || { echo "detached: NAME must be letters, digits, '.', '_' or '-' (not starting with '.' or '-'), got '$name'" >&2; exit 2; }
dir=/tmp/detached/$name
case "$mode" in
  start)
    [ $# -ge 1 ] || usage
    if [ -f "$dir/pid" ] && [ ! -f "$dir/rc" ] && kill -0 "$(cat "$dir/pid")" 2>/dev/null; then
      echo "detached: $name is already running (pid $(cat "$dir/pid"))" >&2; exit 1
    fi
    rm -rf "$dir"; mkdir -p "$dir/out"
    OUT="$dir/out" setsid bash -c '"$@" > "'"$dir"'/log" 2>&1; echo $? > "'"$dir"'/rc"' detached "$@" < /dev/null > /dev/null 2>&1 &  # holds none of the caller's pipes
    echo $! > "$dir/pid"
    echo "detached: $name started (pid $!, output in $dir/log)"
    ;;
  wait)
    [ $# -ge 1 ] || usage
    seconds=$1; shift
    [ -d "$dir" ] || { echo "detached: nothing named $name was started on this machine" >&2; exit 1; }
    deadline=$(( $(date +%s) + seconds ))
    show() { # what the log gained since the last look
      local seen size; seen=$(cat "$dir/seen" 2>/dev/null || echo 0); size=$(stat -c %s "$dir/log")
      [ "$size" -gt "$seen" ] && tail -c +"$((seen + 1))" "$dir/log" | head -c "$((size - seen))"
      echo "$size" > "$dir/seen"
    }
    while [ ! -f "$dir/rc" ] && [ "$(date +%s)" -lt "$deadline" ]; do show; sleep 5; done
    show
    mkdir -p "${OUT:-/tmp/out}"
    cp "$dir/log" "${OUT:-/tmp/out}/$name.log"
    rm -rf "$dir/pack"; mkdir -p "$dir/pack"; cp -r "$dir/out" "$dir/pack/out"
    rm -rf "$dir/videos"; mkdir -p "$dir/videos"
    # The first episode of each videos/ folder (or those VIDEOS picks) goes in an archive of its
    # own, as many as fit in 14 MiB (where results are copied back with a limit on a file's
    # size, e.g. 16 MiB, the measurements must still come back).
    videos="${VIDEOS:-*/videos/*/episode_000.*}"
    video_bytes=0 video_left=0
    for d in "$@"; do
      [ -d "$d" ] || continue
      find "$d" -type f -size -3M -not -path '*/videos/*' -exec cp --parents {} "$dir/pack/" \;
      while IFS= read -r f; do
        size=$(stat -c %s "$f")
        if [ $((video_bytes + size)) -le $((14 << 20)) ]; then
          cp --parents "$f" "$dir/videos/"; video_bytes=$((video_bytes + size))
        else
          video_left=$((video_left + 1))
        fi
      done < <(find "$d" -type f -path '*/videos/*' -path "$videos" | sort)
    done
    [ "$video_left" -gt 0 ] && echo "detached: $video_left episode videos left out of $name-videos.tar.gz (over 14 MiB in all)"
    tar -czf "${OUT:-/tmp/out}/$name.tar.gz" -C "$dir/pack" .
    # Over 16 MiB a file may not come back (as above).
    if [ "$(stat -c %s "${OUT:-/tmp/out}/$name.tar.gz")" -gt $((15 << 20)) ]; then
      split -b 15M -d "${OUT:-/tmp/out}/$name.tar.gz" "${OUT:-/tmp/out}/$name.tar.gz.part-" && rm "${OUT:-/tmp/out}/$name.tar.gz"
      echo "detached: $name.tar.gz over 15 MiB, in parts: cat $name.tar.gz.part-* | tar -xz"
    fi
    tar -czf "${OUT:-/tmp/out}/$name-videos.tar.gz" -C "$dir/videos" .
    if [ -f "$dir/rc" ]; then
      rc=$(cat "$dir/rc"); echo "detached: $name ended with status $rc"
      [ "$rc" = 0 ] && exit 0 || exit 1
    fi
    # Where each log under the out folder stands, so that the next command can follow at once (a
    # host released when idle between commands ends the run with it).
    for f in "$dir"/out/*.log "$dir"/out/*/log; do
      [ -s "$f" ] && echo "detached: ${f#"$dir/out/"}: $(tr '\r' '\n' < "$f" | grep -v '^[[:space:]]*$' | tail -1 | cut -c1-160)"
    done
    echo "detached: $name still running after $seconds s"; exit 3
    ;;
  *) usage ;;
esac
