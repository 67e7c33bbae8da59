# SPDX-License-Identifier: Apache-2.0
# make demo : set up (as needed) and run the main job on the simulated fingertip
# make test : set up (as needed) and run the test suite (what CI runs)
.PHONY: demo test setup bench bench-% clean
BENCH_REQ = tools/run.sh python -m pip install -q --disable-pip-version-check -r bench/requirements.txt
SHELL := /bin/bash

demo:
	@tools/run.sh install/ae_tactile/lib/ae_tactile/bringup --monitor --sliding-speed 0.02 \
		--summary-json log/demo_summary.json --report-png log/demo_summary.png

test:
	@AE_TACTILE_REQUIRE_ROS=1 tools/run.sh pytest -q -p no:cacheprovider -n 2 --dist loadfile \
		--durations=15 test   # two workers, a test file each (pytest-xdist); own ROS domains

# make bench: every benchmark; make bench-sim: bench/bench_sim.py alone (results in bench/results/)
bench:
	@$(BENCH_REQ)
	@set -e; for b in bench/bench_*.py; do \
		[ "$$b" = bench/bench_overlap.py ] && continue; \
		echo "== $$b"; tools/run.sh python $$b; done   # bench_localization runs the overlap sweep
	@tools/run.sh python bench/readme_figures.py --write

bench-%:
	@$(BENCH_REQ)
	@tools/run.sh python bench/bench_$*.py

setup:
	@tools/setup.sh

clean:
	rm -rf build install log .ae_venv_path
