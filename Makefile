# Two commands on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# The CPU wheel of torch lies on this machine's disk; installing it first keeps pip
# from pulling a multi-GB CUDA build for the `torch` requirement.
TORCH_SPEC ?= torch==2.13.0

.PHONY: all install demo test test-all test-ros1 lint format bench clean

all: test

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet "$(TORCH_SPEC)"
	$(BIN)/python -m pip install --quiet -e ".[dev,viz,fleet]"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(BIN)/mogs demo

test: $(STAMP)
	$(BIN)/ruff check mogs_node bridges tests bench
	$(BIN)/ruff format --check mogs_node bridges tests bench
	$(BIN)/python -m pytest -q -p no:cacheprovider

test-all: $(STAMP)
	$(BIN)/python -m pytest -q -m "" -p no:cacheprovider

# The ROS 1 bridge's slow tests against a real roscore (`make test` runs the others): the
# whole pipeline (mono8, rgb8, jpeg) and the other encodings; .ci/run runs them where ROS 1 is
# installed (README "On a ROS 1 robot").
test-ros1: $(STAMP)
	$(BIN)/python -m pytest -q -m slow -p no:cacheprovider tests/bridges/test_bridges_ros1.py \
		tests/bridges/test_bridges_ros1_pipeline.py

lint: $(STAMP)
	$(BIN)/ruff check mogs_node bridges tests bench
	$(BIN)/ruff format --check mogs_node bridges tests bench

format: $(STAMP)
	$(BIN)/ruff format mogs_node bridges tests bench
	$(BIN)/ruff check --fix mogs_node bridges tests bench

clean:
	rm -rf $(VENV) build *.egg-info
