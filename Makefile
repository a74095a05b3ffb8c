# Two commands do everything on a fresh machine: `make demo` and `make test`.
# Both run the idempotent bootstrap first (seconds when nothing changed).
SHELL := /bin/bash
.ONESHELL:
.SHELLFLAGS := -e -o pipefail -c
export ROS_AUTOMATIC_DISCOVERY_RANGE := LOCALHOST
# One BLAS thread per process: on 2 shared cores multithreaded OpenBLAS makes least squares 10-20x slower.
export OPENBLAS_NUM_THREADS ?= 1
ENV := . ./env.sh

.PHONY: bootstrap build test lint demo bench clean

bootstrap:
	scripts/bootstrap.sh

# The workspace build a ROS user runs, here with the repository as the workspace's only source.
build: bootstrap
	$(ENV)
	colcon --log-base log build --symlink-install --base-paths . hybrid_kinematics_interfaces

lint: bootstrap
	$(ENV)
	ruff check .
	ruff format --check .

test: bootstrap
	$(ENV)
	ruff check .
	python -m pytest -q -n auto --dist loadfile --no-loadscope-reorder

demo: bootstrap
	$(ENV)
	python scripts/demo.py

bench: bootstrap
	$(ENV)
	python -m bench.run_all $(if $(RERUN),--rerun)

clean:
	rm -rf build install log env.sh out
