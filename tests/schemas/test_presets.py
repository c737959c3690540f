"""Randomization presets and the RandomizationConfig contract."""

import pydantic
import pytest

from anchordp3.schemas.randomization import PRESETS, RandomizationConfig, preset
from anchordp3.schemas.sim import WorldConfig


def test_clean_preset_randomizes_nothing_but_object_yaw():
    c = preset("clean")
    assert isinstance(c, RandomizationConfig)
    assert c.table_height_range == (0.0, 0.0)
    assert c.clutter_max == 0
    assert not c.random_lights and not c.textured_table and not c.textured_wall
    assert c.crazy_light_prob == 0.0
    assert c.object_pose_noise == 0.0
    assert c.camera_jitter_pos == 0.0 and c.camera_jitter_rot_deg == 0.0
    assert c.object_yaw_range_deg > 0


def test_randomized_preset_has_robotwin_like_ranges():
    r = preset("randomized")
    assert r.table_height_range == (-0.03, 0.0)
    assert r.clutter_max == 10
    assert r.random_lights
    assert r.textured_table and r.textured_wall
    assert 0 < r.crazy_light_prob < 0.1
    assert r.object_pose_noise > 0 and r.object_yaw_range_deg > preset("clean").object_yaw_range_deg
    assert r.camera_jitter_pos > 0 and r.camera_jitter_rot_deg > 0


def test_presets_are_the_registered_objects():
    assert set(PRESETS) >= {"clean", "randomized"}
    for name, cfg in PRESETS.items():
        assert preset(name) is cfg


def test_unknown_preset_raises_value_error_naming_the_known_presets():
    with pytest.raises(ValueError) as info:
        preset("messy")
    msg = str(info.value)
    assert "'messy'" in msg
    for name in PRESETS:
        assert name in msg


def test_extra_fields_are_rejected():
    with pytest.raises(pydantic.ValidationError, match="clutter_min"):
        RandomizationConfig(clutter_min=2)
    with pytest.raises(pydantic.ValidationError, match="table_colour"):
        RandomizationConfig.model_validate({**preset("randomized").model_dump(), "table_colour": "red"})


@pytest.mark.parametrize(
    "field, value",
    [("clutter_max", 11), ("clutter_max", -1), ("plain_texture_prob", 1.5), ("crazy_light_prob", -0.1),
     ("object_pose_noise", -0.01), ("object_yaw_range_deg", 181.0), ("camera_jitter_pos", -1.0)],
)
def test_out_of_range_values_are_rejected(field, value):
    with pytest.raises(pydantic.ValidationError, match=field):
        RandomizationConfig(**{field: value})


def test_presets_are_immutable():
    with pytest.raises(pydantic.ValidationError):
        preset("randomized").clutter_max = 3  # type: ignore[misc]
    assert preset("randomized").clutter_max == 10


def test_preset_plugs_into_world_config_and_round_trips():
    cfg = WorldConfig(randomization=preset("randomized"))
    assert cfg.randomization == preset("randomized")
    again = WorldConfig.model_validate(cfg.model_dump())
    assert again.randomization == preset("randomized")
    assert WorldConfig().randomization == RandomizationConfig()
