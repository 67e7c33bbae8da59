# SPDX-License-Identifier: Apache-2.0
"""A scene event placed at or after the end of the scene is a clear error at load (it
would render nothing, without a word), at the top level and in a composite's parts."""

import pytest

from ae_tactile.sim.scene import SceneError, load_scene


@pytest.mark.parametrize(
    "generator, params, key",
    [
        ("single_touch", {"time_s": 2.0}, "params.time_s"),
        ("touch_hold_release", {"time_s": 0.5}, "params.time_s"),
        ("three_pins", {"times_s": [1e-3, 0.6]}, "params.times_s"),
        ("paper_positions", {"start_s": 0.5}, "params.start_s"),
    ],
)
def test_an_event_after_the_end_of_the_scene_is_refused_naming_it(generator, params, key):
    spec = {"generator": generator, "duration_s": 0.5, "params": params}
    with pytest.raises(SceneError, match=rf"{key}: .* at or after the end of the scene"):
        load_scene(spec)


def test_a_composite_part_or_its_event_after_the_end_is_refused():
    part = {"generator": "single_touch", "params": {"time_s": 0.01}}
    late_part = {
        "generator": "composite",
        "duration_s": 0.1,
        "params": {"parts": [dict(part, at_s=0.0), dict(part, at_s=0.2)]},
    }
    with pytest.raises(SceneError, match=r"params.parts\[1\].at_s: 0.2 s"):
        load_scene(late_part)
    late_event = {
        "generator": "composite",
        "duration_s": 0.1,
        "params": {"parts": [dict(part, at_s=0.05, params={"time_s": 0.06})]},
    }
    with pytest.raises(SceneError, match=r"params.parts\[0\].params.time_s: 0.06 s"):
        load_scene(late_event)


def test_events_inside_the_scene_and_defaults_load():
    load_scene({"generator": "single_touch", "duration_s": 0.5, "params": {"time_s": 0.4}})
    load_scene({"generator": "single_touch", "duration_s": 0.01})  # the default time
