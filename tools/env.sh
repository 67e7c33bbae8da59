# SPDX-License-Identifier: Apache-2.0
# Source this (bash) after tools/setup.sh: activates the venv, ROS 2 launch (when set up
# from ../shared/ros2-launch) and the colcon install.
_ae_root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
_ae_venv="$(cat "$_ae_root/.ae_venv_path")"
# shellcheck disable=SC1091
source "$_ae_venv/bin/activate"
if [ -z "${ROS_DISTRO:-}" ]; then
  export CMAKE_PREFIX_PATH="$_ae_venv${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
  export AMENT_PREFIX_PATH="$_ae_venv${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
  export RMW_IMPLEMENTATION="${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}"
fi
_ae_nounset=0; case $- in *u*) _ae_nounset=1; set +u;; esac
if [ -z "${ROS_DISTRO:-}" ] && [ -f "$_ae_venv/ros2_launch/install/local_setup.bash" ]; then
  # shellcheck disable=SC1091
  source "$_ae_venv/ros2_launch/install/local_setup.bash"   # composition_interfaces
fi
# shellcheck disable=SC1091
source "$_ae_root/install/setup.bash"
[ "$_ae_nounset" = 1 ] && set -u
export AE_TACTILE_ROOT="$_ae_root"
unset _ae_root _ae_venv _ae_nounset
