#!/usr/bin/env bash
# Builds interface packages that have no wheel into a venv that holds the ROS 2 Jazzy wheels, with
# the rosidl generators and ament_cmake from PyPI, gcc and cmake.
# Usage: interfaces/build_into_venv.sh VENV [PACKAGE_FOLDER...]. Without folders: the packages in
# this folder (tf2_msgs); with them, those (e.g. the vendored composition_interfaces, which may be
# read-only: the build happens elsewhere). The venv is the install prefix (its lib/ holds the other
# message libraries, which the wheels' bootstrapper puts on LD_LIBRARY_PATH).
set -euo pipefail
venv=$(cd "$1" && pwd)
here=$(cd "$(dirname "$0")" && pwd)
python="$venv/bin/python"

# The message wheels' exported CMake files name the include folders of the machine that built them
# (/opt/python/cp311-cp311/...); point them at this venv's Python and numpy, or CMake refuses them.
py_include=$("$python" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
np_include=$("$python" -c "import numpy; print(numpy.get_include())")
for f in "$venv"/share/*/cmake/export_*__rosidl_generator_pyExport.cmake; do
  sed -i -e "s#/opt/python/cp311-cp311/lib/python3.11/site-packages/numpy/_core/include#$np_include#g" \
         -e "s#/opt/python/cp311-cp311/include/python3.11#$py_include#g" "$f"
done

shift
if [ "$#" -eq 0 ]; then set -- "$here/tf2_msgs"; fi
build=$(mktemp -d)
trap 'rm -rf "$build"' EXIT
for source in "$@"; do
  package=$(basename "$source")
  # The ament index is how rosidl finds the type support generators.
  AMENT_PREFIX_PATH="$venv" cmake -S "$source" -B "$build/$package" \
    -DCMAKE_PREFIX_PATH="$venv" -DCMAKE_INSTALL_PREFIX="$venv" -DPython3_EXECUTABLE="$python" \
    -DBUILD_TESTING=OFF -DCMAKE_BUILD_TYPE=Release > "$build/$package.log" 2>&1 \
    || { cat "$build/$package.log"; exit 1; }
  AMENT_PREFIX_PATH="$venv" cmake --build "$build/$package" --target install -j "$(nproc)" \
    >> "$build/$package.log" 2>&1 || { tail -n 60 "$build/$package.log"; exit 1; }
  echo "built $package into $venv"
done
