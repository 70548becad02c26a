#!/bin/bash
# Run a benchmark command as round-robin real-time tasks (Linux, root), so that other
# programs on a shared machine cannot take the CPU from it while its own processes (the
# caller, the fork server, the workers: they inherit the policy) still share the cores in
# turn as under the normal scheduler:
#
#   scripts/realtime.sh env PYTHONPATH=. python scripts/bench_throughput.py ...
#
# It sets two kernel knobs for the run: round-robin slices of 4 ms (the default 100 ms
# starves a caller behind two busy workers) and no real-time throttling (the default,
# 95% of each second, stalled the runs ~50 ms every second); the throttling is restored
# at exit. A real-time process that never sleeps holds its core until it exits: use it
# for runs that end. Figures measured so are labelled "real-time" in docs/throughput.md.
set -euo pipefail
if [ "$#" -eq 0 ]; then
  echo "usage: scripts/realtime.sh COMMAND [ARG...]" >&2
  exit 2
fi
old_runtime=$(cat /proc/sys/kernel/sched_rt_runtime_us)
old_slice=$(cat /proc/sys/kernel/sched_rr_timeslice_ms)
restore() {
  echo "$old_runtime" > /proc/sys/kernel/sched_rt_runtime_us
  echo "$old_slice" > /proc/sys/kernel/sched_rr_timeslice_ms
}
trap restore EXIT
echo 4 > /proc/sys/kernel/sched_rr_timeslice_ms
echo -1 > /proc/sys/kernel/sched_rt_runtime_us
chrt -r 10 "$@"
