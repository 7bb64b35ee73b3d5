#!/usr/bin/env bash
# Split frames FIRST..LAST into chunks of CHUNK frames and run `godrays-jax batch --frames A-B` on each chunk,
# JOBS at a time: what a render-farm manager does with one task per chunk. Chunks write into one output
# folder; --resume makes a retried chunk skip the frames it already wrote.
#
# usage: fanout.sh PATTERN OUT_DIR FIRST LAST [CHUNK] [JOBS] [batch options ...]
#   CHUNK frames per task (default 10), JOBS tasks at a time (default 2)
# e.g.   fanout.sh 'shot/frame.####.exr' out/rays 1001 1100 25 4 --preset gpu_gems
set -euo pipefail
if (( $# < 4 )); then
  echo "usage: $0 PATTERN OUT_DIR FIRST LAST [CHUNK] [JOBS] [batch options ...]" >&2
  exit 2
fi
pattern=$1 out=$2 first=$3 last=$4 chunk=${5:-10} jobs=${6:-2}
shift $(( $# < 6 ? $# : 6 ))
for (( start = first; start <= last; start += chunk )); do
  end=$(( start + chunk - 1 < last ? start + chunk - 1 : last ))
  echo "$start-$end"
done | xargs -P "$jobs" -I RANGE godrays-jax batch "$pattern" -o "$out" --frames RANGE --resume -q "$@"
