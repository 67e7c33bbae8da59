# SPDX-License-Identifier: Apache-2.0
"""README.md and the parameter files hold exactly what the nodes declare (one source)."""

import os

import yaml

from conftest import require_ros

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_readme_parameter_tables_match_the_code():
    require_ros()
    from ae_tactile.ros.param_docs import markdown

    readme = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    assert markdown() in readme, "README parameters are stale: run tools/update_param_docs.sh"


def test_parameter_files_are_generated_from_the_tables_with_one_section_per_node():
    require_ros()
    from ae_tactile.ros.param_docs import BODY_VALUES, parameter_file

    for body in BODY_VALUES:
        path = os.path.join(ROOT, "config", f"{body}.yaml")
        text = open(path, encoding="utf-8").read()
        assert text == parameter_file(body), f"{path} is stale: run tools/update_param_docs.sh"
        data = yaml.safe_load(text)
        assert "/**" not in data  # no section that sets every node at once
        assert set(data) == {
            "/**/driver",
            "/**/sim_fingertip",
            "/**/localizer",
            "/**/slip_detector",
            "/**/grip_reflex",
        }
        drv = data["/**/driver"]["ros__parameters"]
        assert drv["medium"] == body and drv["localization"]["method"] == "ml"
        # the localizer's and the slip detector's min_confidence are separate parameters now
        assert "min_confidence" in drv["localization"] and "min_confidence" in drv["slip"]


def test_every_parameter_is_described_with_unit_and_range():
    require_ros()
    from ae_tactile.ros.param_docs import SECTIONS, _table_of
    from ae_tactile.ros.params import describe

    for _, node, tables in SECTIONS:
        for prefix, t in tables:
            for p in _table_of(prefix, t):
                assert len(p.description) > 10 and "SlipConfig." not in p.description, (
                    node,
                    p.name,
                )
                text = describe(p)
                if (
                    isinstance(p.default, (int, float))
                    and not isinstance(p.default, bool)
                    and p.choices is None
                ):
                    assert "range:" in text, (node, p.name, text)


def test_full_parameter_table_is_generated_into_docs():
    require_ros()
    from ae_tactile.ros.param_docs import full_markdown

    text = open(os.path.join(ROOT, "docs", "parameters.md"), encoding="utf-8").read()
    assert text == full_markdown(), "docs/parameters.md is stale: run tools/update_param_docs.sh"


def test_readme_names_the_few_parameters_a_user_sets_and_the_rest_are_expert():
    require_ros()
    from ae_tactile.ros.param_docs import SECTIONS, _table_of, markdown
    from ae_tactile.ros.params import USER_PARAMS, describe, is_expert

    assert len(USER_PARAMS) <= 10
    text = markdown()
    names = set()
    for _, _, tables in SECTIONS:
        for prefix, t in tables:
            for p in _table_of(prefix, t):
                full = prefix + p.name
                names.add(full)
                assert describe(p, full).startswith("[expert] ") == is_expert(full), full
    for name, trade in USER_PARAMS.items():
        assert name in names, name  # a parameter some node declares
        assert f"`{name}`" in text and trade in text, name
