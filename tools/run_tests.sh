#!/usr/bin/env bash
# The test suite as `make test` (and so CI) runs it, once.
#
# With the ROS 2 launch tooling (a sourced system ROS 2, or the wheels tools/bootstrap.sh installs
# from ../shared/ros-tooling): `colcon build` indexes gsrmr in install/, and `colcon test` runs the
# whole suite — launch_testing files included — with that install sourced, as on a ROS workspace.
# Without it (a user's fresh clone with no ../shared): plain pytest; the launch tests skip with a reason.
# PYTEST_ARGS (whitespace-separated) go to pytest either way.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
# shellcheck disable=SC1091
source "$VENV/bin/activate"
read -r -a pytest_args <<< "${PYTEST_ARGS:-}"
# test/conftest.py's hard deadline writes every thread's stack here when a test hangs past it (then exits 1)
export GSRMR_HANG_DUMP="$PWD/log/pytest_hang_dump.txt"
rm -f "$GSRMR_HANG_DUMP"
print_hang_dump() {
  if [ -f "$GSRMR_HANG_DUMP" ] && grep -q "^Timeout (" "$GSRMR_HANG_DUMP"; then
    echo "run_tests: a test hung past the hard deadline; its threads' Python stacks:" >&2
    cat "$GSRMR_HANG_DUMP" >&2
    return 1
  fi
}

if command -v colcon >/dev/null && python -c "import launch_testing, launch_ros, ros2cli" 2>/dev/null; then
  echo "run_tests: colcon build + colcon test (ROS_DOMAIN_ID=${ROS_DOMAIN_ID:-0})"
  colcon --log-base log build --base-paths . --packages-select gsrmr --symlink-install \
    --event-handlers console_cohesion- status- summary- terminal_title- >/dev/null \
    || { cat log/latest_build/gsrmr/stdout_stderr.log >&2; exit 1; }
  set +u
  # shellcheck disable=SC1091
  source install/setup.bash
  set -u
  args=(--base-paths . --packages-select gsrmr --event-handlers console_direct+ status- summary- terminal_title-
        --return-code-on-test-failure)
  if [ ${#pytest_args[@]} -gt 0 ]; then
    args+=(--pytest-args "${pytest_args[@]}")
  fi
  status=0
  colcon --log-base log test "${args[@]}" || status=$?
  colcon --log-base log test-result --verbose --test-result-base build/gsrmr || status=$?
  print_hang_dump || status=1
  exit $status
fi
echo "run_tests: no ROS 2 launch tooling (no system ROS 2, no ../shared/ros-tooling): plain pytest"
status=0
python -m pytest "${pytest_args[@]}" || status=$?
print_hang_dump || status=1
exit $status
