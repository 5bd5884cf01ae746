#!/bin/sh
# Regenerates tests/fixtures/sick/lms111_sick_scan_xd_ranges.json: SICK's own LMDscandata parser
# (sick_scan_xd, generic/no-ROS build flags) run on the real LMS111 telegrams of
# tests/fixtures/sick/lms111_pcapng_excerpt.json. Dev tool, not run in CI; needs g++ and a
# Python with numpy. Builds outside the repository.
#
#   SICK_GIT_DIR=/path/to/sick_scan_xd.git tools/sick_driver_reference/regenerate.sh [COMMIT]
#
# SICK_GIT_DIR is a (bare) clone of https://github.com/SICKAG/sick_scan_xd; COMMIT defaults to
# HEAD. Only the parser and what it links against are compiled (see README in tests/fixtures).
set -eu
HERE=$(cd "$(dirname "$0")" && pwd)
REPO=$(cd "$HERE/../.." && pwd)
: "${SICK_GIT_DIR:?set SICK_GIT_DIR to a clone of SICKAG/sick_scan_xd}"
COMMIT=$(git --git-dir="$SICK_GIT_DIR" rev-parse "${1:-HEAD}")
WORK=${WORK:-/tmp/sickdrv/build-$COMMIT}
PYTHON=${PYTHON:-python3}
mkdir -p "$WORK/src" "$WORK/obj"
git --git-dir="$SICK_GIT_DIR" archive "$COMMIT" driver include roswrap LICENSE | tar -x -C "$WORK/src"
cd "$WORK/src"
# swap_endian lives in sick_scan_common.cpp, which pulls in the whole driver: take it verbatim.
{ echo '#include <sick_scan/sick_ros_wrapper.h>'
  sed -n '/^void swap_endian(unsigned char \*ptr, int numBytes)/,/^}/p' driver/src/sick_scan_common.cpp
} > "$WORK/swap_endian_from_driver.cpp"
FLAGS="-std=c++14 -O1 -D__ROS_VERSION=0 -DROSSIMU -Iinclude -Iinclude/sick_scan_xd_api
 -Iinclude/tinyxml -Iinclude/sick_scan -Iroswrap/src/include/launchparser -Iroswrap/src/msg_header
 -Iroswrap/src/include -Iroswrap/src/rossimu/melodic/include -Iroswrap/src/rossimu/kinetic/include
 -Iroswrap/src/cfgsimu -Iroswrap/src/toojpeg -Iroswrap/src/tools -Idriver/src"
for f in driver/src/sick_lmd_scandata_parser.cpp driver/src/sick_generic_parser.cpp \
         driver/src/abstract_parser.cpp driver/src/softwarePLL.cpp \
         roswrap/src/rossimu/kinetic/src/rossimu.cpp roswrap/src/rossimu/kinetic/src/duration.cpp \
         roswrap/src/cfgsimu/sick_scan/time_modi.cpp \
         "$WORK/swap_endian_from_driver.cpp" "$HERE/log_stubs.cpp" "$HERE/lmd_harness.cpp"; do
  # shellcheck disable=SC2086
  g++ $FLAGS -c "$f" -o "$WORK/obj/$(basename "$f" .cpp).o"
done
g++ "$WORK"/obj/*.o -o "$WORK/lmd_harness" -lpthread
CAPTURE="$REPO/tests/fixtures/sick/lms111_pcapng_excerpt.json"
"$PYTHON" "$HERE/telegrams.py" extract "$CAPTURE" | "$WORK/lmd_harness" sick_lms_1xx \
  | "$PYTHON" "$HERE/telegrams.py" fixture "$CAPTURE" "$COMMIT" \
  > "$REPO/tests/fixtures/sick/lms111_sick_scan_xd_ranges.json"
echo "wrote $REPO/tests/fixtures/sick/lms111_sick_scan_xd_ranges.json (sick_scan_xd $COMMIT)"
