"""README documents every node parameter exactly as the nodes declare it."""
import os

from conftest import require_ros

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_readme_parameter_tables_match_the_code():
    require_ros()
    from ae_tactile.ros.param_docs import markdown
    readme = open(os.path.join(ROOT, "README.md"), encoding="utf-8").read()
    assert markdown() in readme, "README parameters are stale: run tools/update_param_docs.sh"


def test_every_declared_parameter_has_a_description_and_unit_in_its_name_where_physical():
    require_ros()
    from ae_tactile.ros.param_docs import slip_config_descriptions
    from ae_tactile.ros.driver_node import DRIVER_PARAMS
    from ae_tactile.ros.grip_reflex_node import REFLEX_PARAMS
    from ae_tactile.ros.localizer_node import LOCALIZER_PARAMS
    from ae_tactile.ros.sim_fingertip_node import SIM_PARAMS
    from ae_tactile.ros.slip_node import NODE_PARAMS, slip_config_params
    for p in DRIVER_PARAMS + SIM_PARAMS + LOCALIZER_PARAMS + NODE_PARAMS + REFLEX_PARAMS:
        assert len(p.description) > 10, p.name
    desc = slip_config_descriptions()
    assert all(p.name in desc for p in slip_config_params()), set(p.name for p in slip_config_params()) - set(desc)
