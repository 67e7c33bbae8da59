# make demo : set up (as needed) and run the main job on the simulated fingertip
# make test : set up (as needed) and run the test suite (what CI runs)
.PHONY: demo test setup bench clean
SHELL := /bin/bash

demo:
	@tools/run.sh install/ae_tactile/lib/ae_tactile/message_demo

test:
	@AE_TACTILE_REQUIRE_ROS=1 tools/run.sh pytest -q -p no:cacheprovider test

setup:
	@tools/setup.sh

clean:
	rm -rf build install log .ae_venv_path
