#!/usr/bin/env bash
# Planner solves per second per drone, from the onboards' logs of a demo run (issue 19, item 3).
# Every onboard logs `planner solves=N` (a running count) every 10 s; this prints, for each
# 10 s window before the drone is told to land, the mean and the lowest rate over the drones.
#   usage: deploy/solve-rates.sh /tmp/tacos-demo<PID>
set -euo pipefail
dir=${1:?usage: $0 LOG_DIR (the demo prints it; /tmp/tacos-demo<PID>)}
shopt -s nullglob
logs=("$dir"/tacos-onboard-*.log)
if [ ${#logs[@]} -eq 0 ]; then
    echo "no tacos-onboard-*.log in $dir" >&2
    exit 1
fi
for log in "${logs[@]}"; do
    # Strip the colour codes, keep the running count of each `planner` line up to the drone's
    # first landing (a landed drone stops planning, so the window holding its touch-down would
    # read as a slow planner), print the rates.
    sed 's/\x1b\[[0-9;]*m//g' "$log" \
        | sed '/action=land()/q' \
        | grep ' planner solves=' \
        | sed 's/.* planner solves=\([0-9]*\) .*/\1/' \
        | awk 'NR > 1 { printf "%.1f ", ($1 - prev) / 10 } { prev = $1 } END { print "" }'
done | awk '
    { for (i = 1; i <= NF; i++) { sum[i] += $i; if (!(i in low) || $i < low[i]) low[i] = $i; n[i]++; if (i > w) w = i } }
    END {
        printf "%d drones; solves per second per drone in 10 s windows from the first log line\n", NR
        for (i = 1; i <= w; i++) printf "window %2d (%3d-%3d s): mean %5.2f  lowest %5.1f  (%d drones)\n", i, (i - 1) * 10, i * 10, sum[i] / n[i], low[i], n[i]
    }'
