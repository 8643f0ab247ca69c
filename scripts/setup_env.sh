#!/usr/bin/env bash
# Create or update the project's Python environment (idempotent; ~1-2 min the first time,
# under a second when requirements.txt and setup.py are unchanged).
#   VENV: where the virtualenv lives (default: <repo>/.venv)
# Prints the path of the venv's bin directory on the last line.
set -euo pipefail
repo=$(cd "$(dirname "$0")/.." && pwd)
venv=${VENV:-$repo/.venv}
py=${PYTHON:-python3}
stamp=$venv/.semfeat_stamp
want=$(cat "$repo/requirements.txt" "$repo/requirements-nodeps.txt" "$repo/setup.py" "$repo/setup.cfg" | sha256sum | cut -c1-16)

if [ -f "$stamp" ] && [ "$(cat "$stamp")" = "$want" ] && [ -x "$venv/bin/python" ]; then
  VENV=$venv "$repo/scripts/build_tf2_msgs.sh"  # tests only: /tf over DDS (no wheel)
  echo "$venv/bin"
  exit 0
fi
"$py" -c 'import sys; assert sys.version_info[:2] in ((3, 11), (3, 12)), sys.version' \
  || { echo "semfeat_ros needs Python 3.11 or 3.12 (set PYTHON=...)" >&2; exit 1; }
echo "setting up $venv (first run takes a minute or two) ..." >&2
[ -x "$venv/bin/python" ] || "$py" -m venv "$venv"
# torch==2.13.0 is pinned in requirements.txt: its CPU wheel for Python 3.11 is on local disk
# (find-links). For another Python the CPU build comes from PyTorch's CPU index (PyPI's torch
# pulls the CUDA libraries).
index=()
"$venv/bin/python" -c 'import sys; sys.exit(sys.version_info[:2] != (3, 11))' \
  || index=(--extra-index-url https://download.pytorch.org/whl/cpu)
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check "${index[@]}" \
  -r "$repo/requirements.txt" 2> >(grep -v "^WARNING: Location" >&2)
# Their declared dependencies are traps (a CUDA torchvision, opencv-python over the headless
# build, gdown, poselib): what they need is in requirements.txt.
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
  -r "$repo/requirements-nodeps.txt" 2> >(grep -v "^WARNING: Location" >&2)
"$venv/bin/python" -m pip install --quiet --disable-pip-version-check --no-deps \
  --no-build-isolation -e "$repo" 2> >(grep -v "^WARNING: Location" >&2)
# The venv holds package.xml files of the ROS wheels: keep colcon from crawling into it.
touch "$venv/COLCON_IGNORE"
echo "$want" > "$stamp"
VENV=$venv "$repo/scripts/build_tf2_msgs.sh"  # tests only: /tf over DDS (no wheel)
echo "$venv/bin"
