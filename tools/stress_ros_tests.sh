#!/usr/bin/env bash
# SPDX-License-Identifier: Apache-2.0
# Flakiness check: run the ROS tests N times in a row (default 20) while another process
# keeps one core busy; stop at the first failure. Usage: tools/stress_ros_tests.sh [N] [TESTS...]
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
N="${1:-20}"; shift || true
TESTS=("$@")
[ ${#TESTS[@]} -gt 0 ] || TESTS=(test/test_system.py test/test_driver_node.py test/test_ros_params.py
                                  test/test_ros_messages.py test/test_bag_replay.py)
"$ROOT/tools/setup.sh"
# shellcheck disable=SC1091
source "$ROOT/tools/env.sh"
cd "$ROOT"; mkdir -p log
python3 -c 'while True: pass' &          # the other core, kept busy
BUSY=$!
trap 'kill $BUSY 2>/dev/null || true' EXIT
echo "busy loop pid $BUSY; load: $(cut -d' ' -f1-3 /proc/loadavg)"
for i in $(seq 1 "$N"); do
  start=$(date +%s)
  # a failed run's temporary files (launch logs, ROS logs) stay in log/stress_tmp
  if AE_TACTILE_REQUIRE_ROS=1 pytest -q -p no:cacheprovider --basetemp="$ROOT/log/stress_tmp" \
      "${TESTS[@]}" >"log/stress_run_$i.txt" 2>&1; then
    echo "run $i/$N passed ($(( $(date +%s) - start )) s): $(tail -1 "log/stress_run_$i.txt")"
  else
    echo "run $i/$N FAILED: see log/stress_run_$i.txt and log/stress_tmp"
    tail -5 "log/stress_run_$i.txt"; exit 1
  fi
done
echo "$N runs in a row passed with one core kept busy"
