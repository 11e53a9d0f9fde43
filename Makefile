# A newcomer's two commands: `make demo` and `make test`. Both build .venv from nothing
# (ROS 2 Jazzy rclpy and messages from PyPI wheels, tf2_msgs built from its definition; no ROS
# install) and reuse it once complete.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
READY := $(VENV)/.ready

.PHONY: venv demo test lint bench clean

venv: $(READY)

# The marker is written last, so an interrupted set-up is redone from scratch next time.
$(READY): requirements.txt setup.py setup.cfg package.xml $(wildcard interfaces/*/*.txt interfaces/*/*.xml interfaces/*/msg/*.msg interfaces/*.sh)
	rm -rf $(VENV)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet -r requirements.txt
	bash interfaces/build_into_venv.sh $(VENV)
	$(BIN)/pip install --quiet --no-deps --no-build-isolation -e .
	$(BIN)/python -c "import rclpy, sensor_msgs.msg, tf2_msgs.msg, rosbags, mcap_ros2, scipy; print('venv ready')"
	touch $(READY)

demo: $(READY)
	$(BIN)/sensing_demo

# Two pytest-xdist workers, each on a DDS domain of its own (test/conftest.py), a test file to a
# worker (module fixtures are built once): most tests wait on processes and DDS, not the CPU.
test: $(READY)
	$(BIN)/ruff check .
	ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST $(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15

lint: $(READY)
	$(BIN)/ruff check .

bench: $(READY)
	$(BIN)/sensing_bench

clean:
	rm -rf $(VENV) build install log .pytest_cache
