#!/usr/bin/env bash
# The package as a ROS user builds it: a scratch colcon workspace holding the tracked
# files, `colcon build` (copy and --symlink-install), `colcon test` on a subset that
# runs under pytest in the colcon install, and a source tree left as it was.
# Uses the venv's Python and colcon (VENV, default .venv); `make test` runs it.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
venv=$(cd "$repo" && cd "${VENV:-.venv}" && pwd)
export PATH="$venv/bin:$PATH"
ws=$(mktemp -d)
trap 'rm -rf "$ws"' EXIT
mkdir -p "$ws/src/smpl_depth_ros"
git -C "$repo" ls-files -z | tar -C "$repo" --null -T - -cf - | tar -C "$ws/src/smpl_depth_ros" -xf -
cd "$ws"
(cd src && find . -type f | sort) > before.txt
colcon --log-base log build --build-base build_copy --install-base install_copy \
    --event-handlers console_direct- > build_copy.log 2>&1 || { cat build_copy.log; exit 1; }
colcon --log-base log build --symlink-install --event-handlers console_direct- \
    > build_link.log 2>&1 || { cat build_link.log; exit 1; }
# --symlink-install really links: the installed package points into the sources
link=$(python - <<'PY'
import glob, os
hits = glob.glob('install/smpl_depth_ros/lib/python3*/site-packages/smpl*depth*ros*.egg-link')
print(open(hits[0]).readline().strip() if hits else '')
PY
)
if [ -z "$link" ] || [ ! -L "$link/smpl_depth_ros" ]; then
    echo "colcon build --symlink-install did not link the sources (egg-link: '$link')"
    cat build_link.log; exit 1
fi
(cd src && find . -type f | sort) > after.txt
if ! diff -q before.txt after.txt > /dev/null; then
    echo 'colcon build wrote into the source tree:'; diff before.txt after.txt; exit 1
fi
colcon --log-base log test --packages-select smpl_depth_ros --event-handlers console_direct- \
    --pytest-args -q -k 'package_layout or (test_sensors and thresholds)' > test.log 2>&1 \
    || { cat test.log; exit 1; }
colcon test-result --test-result-base build --all > result.txt || { cat test.log result.txt; exit 1; }
grep -q 'Summary: [1-9][0-9]* tests, 0 errors, 0 failures' result.txt || { cat result.txt; exit 1; }
echo "colcon workspace: $(tail -1 result.txt) (build, --symlink-install, colcon test)"
