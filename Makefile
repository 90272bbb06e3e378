# Two entry points (see README): `make demo` and `make test`. Both build the venv first.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= out/demo
export PIP_DISABLE_PIP_VERSION_CHECK=1

.PHONY: demo test venv install clean

$(STAMP): requirements.txt
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip 2>&1 | grep -v '^WARNING: Location' || true
	$(BIN)/pip install -q -r requirements.txt 2>&1 | grep -v '^WARNING: Location' || true
	$(BIN)/python -c "import torch, rclpy, rosbags, anny, trimesh, embreex, depthai" 2>/dev/null
	# No tf2_msgs wheel exists: generate tf2_msgs/msg/TFMessage (for the node's /tf).
	$(BIN)/python -c "import tf2_msgs.msg" 2>/dev/null || bash resource/tf2_msgs/build.sh $(VENV)
	touch $(STAMP)

venv: $(STAMP)

# Non-editable install: also lays out share/ament_index, share/<pkg>, lib/<pkg> in the venv.
install: $(STAMP)
	$(BIN)/pip install -q --no-deps --no-build-isolation . 2>&1 | grep -v '^WARNING: Location' || true

demo: install
	$(BIN)/python -m smpl_depth_ros.tools.demo --out $(OUT)

# Lint (ruff.toml), then the colcon workspace check (colcon build, --symlink-install, colcon test on a
# subset), then the whole suite (pytest's summary is the last line).
test: install
	$(BIN)/ruff check smpl_depth_ros test resource/launchers setup.py
	VENV=$(VENV) bash test/colcon_workspace.sh
	$(BIN)/python -m pytest -q test

clean:
	rm -rf $(VENV) build *.egg-info out
