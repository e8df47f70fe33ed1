#!/usr/bin/env bash
# rfm workspace environment.
#
#   source ros_ws/env.sh          # this shell gets the venv, ROS 2 Jazzy and the rfm workspace
#   ros_ws/env.sh CMD [ARGS...]   # run one command in that environment
#
# ROS comes from /opt/ros/jazzy when it exists (a regular apt install), otherwise from the
# PyPI wheels in .venv. Set RFM_USE_WHEELS=1 to force the wheels. `make setup` must have
# run once (it creates .venv and builds ros_ws/install).

_rfm_ws_dir="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
RFM_ROOT="$(dirname "$_rfm_ws_dir")"
RFM_VENV="${RFM_VENV:-$RFM_ROOT/.venv}"
if [ -f /opt/ros/jazzy/setup.bash ] && [ -z "${RFM_USE_WHEELS:-}" ]; then
  RFM_ROS_MODE=system
else
  RFM_ROS_MODE=wheels
fi
export RFM_ROOT RFM_VENV RFM_ROS_MODE

_rfm_nounset=0
case $- in *u*) _rfm_nounset=1; set +u ;; esac

if [ "$RFM_ROS_MODE" = system ]; then
  # shellcheck disable=SC1091
  . /opt/ros/jazzy/setup.bash
fi
if [ -f "$RFM_VENV/bin/activate" ]; then
  # shellcheck disable=SC1091
  VIRTUAL_ENV_DISABLE_PROMPT=1 . "$RFM_VENV/bin/activate"
fi
if [ "$RFM_ROS_MODE" = wheels ]; then
  # The wheels install an ament prefix into the venv itself.
  case ":${AMENT_PREFIX_PATH:-}:" in
    *":$RFM_VENV:"*) ;;
    *) export AMENT_PREFIX_PATH="$RFM_VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}" ;;
  esac
  case ":${CMAKE_PREFIX_PATH:-}:" in
    *":$RFM_VENV:"*) ;;
    *) export CMAKE_PREFIX_PATH="$RFM_VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}" ;;
  esac
fi
if [ -f "$_rfm_ws_dir/install/local_setup.bash" ]; then
  # shellcheck disable=SC1091
  . "$_rfm_ws_dir/install/local_setup.bash"
  # the `rfm` command line
  case ":$PATH:" in
    *":$_rfm_ws_dir/install/rfm_bringup/lib/rfm_bringup:"*) ;;
    *) export PATH="$_rfm_ws_dir/install/rfm_bringup/lib/rfm_bringup:$PATH" ;;
  esac
fi

# Fast DDS with room for camera-sized messages (see ros_ws/fastdds.xml), unless configured
if [ -z "${FASTRTPS_DEFAULT_PROFILES_FILE:-}" ] && [ -z "${FASTDDS_DEFAULT_PROFILES_FILE:-}" ] \
   && [ "${RMW_IMPLEMENTATION:-rmw_fastrtps_cpp}" = rmw_fastrtps_cpp ]; then
  export FASTRTPS_DEFAULT_PROFILES_FILE="$_rfm_ws_dir/fastdds.xml"
fi

[ "$_rfm_nounset" = 1 ] && set -u
unset _rfm_nounset

# Executed rather than sourced: run the given command in this environment.
if [ "${BASH_SOURCE[0]}" = "$0" ]; then
  unset _rfm_ws_dir
  if [ $# -eq 0 ]; then
    echo "usage: source ros_ws/env.sh | ros_ws/env.sh CMD [ARGS...]" >&2
    exit 2
  fi
  exec "$@"
fi
unset _rfm_ws_dir
