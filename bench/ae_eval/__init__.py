# SPDX-License-Identifier: Apache-2.0
"""Evaluation of ae_tactile on its simulator: trial generators, scoring, Cramér-Rao bounds
and synthesis helpers. Used by the benchmarks (bench/) and the tests (test/); neither
`pip install .` nor the ROS install ships it, and the product never imports it.
"""
