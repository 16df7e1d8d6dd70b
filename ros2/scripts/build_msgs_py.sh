#!/bin/bash
# Builds an rclpy-usable Python package of semlook_msgs (ros2/semlook_msgs) without colcon or
# cmake: `rosidl generate` from the PyPI wheels of ROS 2 kilted, then plain gcc/g++. Usage:
#   build_msgs_py.sh VENV OUT     (VENV: a venv with ros-kilted-rclpy[fastrtps] and catkin_pkg)
# Then run Python with PYTHONPATH=OUT/python and LD_LIBRARY_PATH=OUT/lib (the typesupport library
# is loaded by name). About 5 s.
set -euo pipefail
V=${1:?usage: build_msgs_py.sh VENV OUT}
PKG=semlook_msgs
MSGS=$(cd "$(dirname "$0")/.." && pwd)
OUT=${2:?usage: build_msgs_py.sh VENV OUT}
GEN=$OUT/gen
mkdir -p "$OUT"; OUT=$(cd "$OUT" && pwd); GEN=$OUT/gen; rm -rf "$GEN" "$OUT/lib" "$OUT/python" "$OUT/include"; mkdir -p "$OUT/lib" "$OUT/python/$PKG" "$OUT/include/$PKG"
export AMENT_PREFIX_PATH=$V
# all generators (c, cpp, py + typesupports); -t/-ts strict mode trips on duplicate entry points
"$V/bin/rosidl" generate -o "$GEN" -I "$V/share" $PKG "$MSGS/$PKG:msg/PlaceMatch.msg" "$MSGS/$PKG:msg/LoopClosure.msg" 2>&1 | grep -v "duplicate entry\|input file\|output file" || true
# headers into include/<pkg>/msg/...
for d in c fastrtps_c introspection_c; do
  (cd "$GEN/$d" && find msg -name '*.h' -exec cp --parents {} "$OUT/include/$PKG/" \;)
done
INC="-I$OUT/include -I$V/include $(for d in $V/include/*/; do printf -- '-I%s ' "$d"; done) -I$($V/bin/python -c "import sysconfig;print(sysconfig.get_paths()['include'])")"
L="-L$V/lib -L$OUT/lib -Wl,-rpath,$V/lib -Wl,-rpath,$OUT/lib"
CF="-fPIC -O1 -w"
# 1. C structs/functions/type description
gcc $CF -shared $INC $GEN/c/msg/detail/*.c -o $OUT/lib/lib${PKG}__rosidl_generator_c.so $L \
  -lstd_msgs__rosidl_generator_c -lbuiltin_interfaces__rosidl_generator_c -lrosidl_runtime_c -lrcutils
# 2. C typesupport dispatcher
g++ $CF -shared $INC $GEN/c/msg/*.cpp -o $OUT/lib/lib${PKG}__rosidl_typesupport_c.so $L \
  -l${PKG}__rosidl_generator_c -lrosidl_typesupport_c -lrosidl_runtime_c
# 3. introspection C typesupport
gcc $CF -shared $INC $GEN/introspection_c/msg/detail/*.c -o $OUT/lib/lib${PKG}__rosidl_typesupport_introspection_c.so $L \
  -l${PKG}__rosidl_generator_c -lstd_msgs__rosidl_typesupport_introspection_c -lrosidl_typesupport_introspection_c -lrosidl_runtime_c
# 4. fastrtps C typesupport (the one rmw_fastrtps uses)
g++ $CF -shared $INC $GEN/fastrtps_c/msg/detail/*.cpp -o $OUT/lib/lib${PKG}__rosidl_typesupport_fastrtps_c.so $L \
  -l${PKG}__rosidl_generator_c -lstd_msgs__rosidl_typesupport_fastrtps_c -lbuiltin_interfaces__rosidl_typesupport_fastrtps_c \
  -lrosidl_typesupport_fastrtps_c -lrosidl_typesupport_fastrtps_cpp -lfastcdr -lrosidl_runtime_c -lrmw
# 5. python C conversion lib
gcc $CF -shared $INC -I$($V/bin/python -c "import numpy; print(numpy.get_include())") $GEN/py/msg/*_s.c -o $OUT/lib/lib${PKG}__rosidl_generator_py.so $L \
  -l${PKG}__rosidl_generator_c -lstd_msgs__rosidl_generator_py -lstd_msgs__rosidl_generator_c -lbuiltin_interfaces__rosidl_generator_py -lrosidl_runtime_c
# 6. python extension modules, one per typesupport
SUF=$($V/bin/python -c 'import sysconfig;print(sysconfig.get_config_var("EXT_SUFFIX"))')
for ts in rosidl_typesupport_c rosidl_typesupport_fastrtps_c rosidl_typesupport_introspection_c; do
  lib=${PKG}__$ts; [ $ts = rosidl_typesupport_c ] && lib=${PKG}__rosidl_typesupport_c
  gcc $CF -shared $INC $GEN/py/_${PKG}_s.ep.$ts.c -o $OUT/python/$PKG/${PKG}_s__$ts$SUF $L \
    -l${PKG}__rosidl_generator_py -l$lib -l${PKG}__rosidl_generator_c -lrosidl_runtime_c
done
cp -r $GEN/py/msg $OUT/python/$PKG/msg
touch $OUT/python/$PKG/__init__.py
echo "built $PKG into $OUT"
