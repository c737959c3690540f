"""RobotSpec / ArmSpec: validation against the URDF, and the layout the robot implies."""

import re
import shutil

import pydantic
import pytest

from anchordp3.schemas.robot import ASSETS_DIR, ArmSpec, RobotSpec, default_robot

SHIPPED_URDF = ASSETS_DIR / "dual_arm.urdf"


def _spec_dict() -> dict:
    """The default robot as plain data, to be edited and re-validated."""
    return default_robot().model_dump()


def _invalid(d: dict, match: str) -> pydantic.ValidationError:
    with pytest.raises(pydantic.ValidationError, match=match) as info:
        RobotSpec.model_validate(d)
    return info.value


def test_default_robot_validates_with_six_dof_and_a_32_dim_layout():
    spec = default_robot()
    assert spec.urdf_path == SHIPPED_URDF
    assert spec.urdf_path.is_file()
    assert spec.dof == 6
    assert spec.layout.dof == 6
    assert spec.layout.dim == 32
    assert spec.arm("left") is spec.left and spec.arm("right") is spec.right
    # round-trips through plain data
    assert RobotSpec.model_validate(spec.model_dump()) == spec


def test_gripper_normalisation_maps_open_to_1_and_closed_to_0():
    arm = default_robot().left
    assert arm.gripper_to_joint(1.0) == pytest.approx(arm.gripper_open)
    assert arm.gripper_to_joint(0.0) == pytest.approx(arm.gripper_closed)
    for g in (0.0, 0.3, 1.0):
        assert arm.joint_to_gripper(arm.gripper_to_joint(g)) == pytest.approx(g)


def test_joint_not_in_urdf_is_rejected_naming_the_joint():
    d = _spec_dict()
    d["right"]["joints"][2] = "right_elbow_typo"
    _invalid(d, r"right: joint 'right_elbow_typo' is not in dual_arm\.urdf")


def test_gripper_joint_not_in_urdf_is_rejected():
    d = _spec_dict()
    d["left"]["gripper_joints"] = ["left_finger_middle"]
    _invalid(d, r"left: joint 'left_finger_middle' is not in dual_arm\.urdf")


def test_fixed_joint_as_arm_joint_is_rejected():
    d = _spec_dict()
    d["left"]["joints"][5] = "left_ee_joint"
    _invalid(d, r"left: joint 'left_ee_joint' is fixed")


def test_ee_link_not_in_urdf_is_rejected_naming_the_link():
    d = _spec_dict()
    d["left"]["ee_link"] = "left_tcp"
    _invalid(d, r"left\.ee_link: link 'left_tcp' is not in dual_arm\.urdf")


def test_missing_urdf_file_is_rejected_naming_the_path(tmp_path):
    missing = tmp_path / "nowhere" / "robot.urdf"
    d = _spec_dict()
    d["urdf"] = str(missing)
    _invalid(d, "urdf: file not found: " + re.escape(str(missing)))


def test_missing_bare_urdf_name_is_looked_up_in_assets_and_rejected():
    d = _spec_dict()
    d["urdf"] = "no_such_robot.urdf"
    _invalid(d, "urdf: file not found: .*no_such_robot\\.urdf")


def test_urdf_that_is_not_xml_is_rejected(tmp_path):
    bad = tmp_path / "bad.urdf"
    bad.write_text("<robot><link name='a'></robot")
    d = _spec_dict()
    d["urdf"] = str(bad)
    _invalid(d, "is not valid XML")


def test_home_qpos_of_wrong_length_is_rejected():
    d = _spec_dict()
    d["left"]["home_qpos"] = [0.0] * 5
    _invalid(d, "home_qpos has 5 values for 6 joints")
    with pytest.raises(pydantic.ValidationError, match="home_qpos has 7 values for 6 joints"):
        ArmSpec.model_validate({**_spec_dict()["right"], "home_qpos": [0.0] * 7})


def test_equal_gripper_open_and_closed_is_rejected():
    d = _spec_dict()
    d["right"]["gripper_open"] = d["right"]["gripper_closed"] = 0.02
    _invalid(d, "gripper_open and gripper_closed must differ")


def test_empty_gripper_joints_is_rejected():
    d = _spec_dict()
    d["left"]["gripper_joints"] = []
    _invalid(d, "gripper_joints: at least one finger joint")


def test_arms_with_different_joint_counts_are_rejected():
    d = _spec_dict()
    d["left"]["joints"] = d["left"]["joints"][:5]
    d["left"]["home_qpos"] = d["left"]["home_qpos"][:5]
    _invalid(d, "left and right arms must have the same number of joints")


def test_unknown_fields_are_rejected():
    d = _spec_dict()
    d["left"]["wrist_camera"] = "yes"
    with pytest.raises(pydantic.ValidationError, match="wrist_camera"):
        RobotSpec.model_validate(d)
    with pytest.raises(pydantic.ValidationError, match="base_height"):
        RobotSpec.model_validate({**_spec_dict(), "base_height": 0.1})


def test_fewer_joints_per_arm_give_a_smaller_layout():
    d = _spec_dict()
    for side in ("left", "right"):
        d[side]["joints"] = d[side]["joints"][:5]
        d[side]["home_qpos"] = d[side]["home_qpos"][:5]
    spec = RobotSpec.model_validate(d)
    assert spec.dof == 5
    assert spec.layout.dim == 2 * 6 + 18


def _renamed_urdf(tmp_path):
    """The shipped URDF with every arm joint renamed (left_joint3 → L_axis_3) and the ee links
    renamed (left_ee → L_tcp)."""
    text = SHIPPED_URDF.read_text()
    for side, short in (("left", "L"), ("right", "R")):
        for i in range(1, 7):
            text = text.replace(f'joint name="{side}_joint{i}"', f'joint name="{short}_axis_{i}"')
        text = text.replace(f'link name="{side}_ee"', f'link name="{short}_tcp"')
        text = text.replace(f'link="{side}_ee"', f'link="{short}_tcp"')
    path = tmp_path / "renamed_dual_arm.urdf"
    path.write_text(text)
    return path


def test_custom_urdf_is_accepted_when_the_spec_names_its_joints(tmp_path):
    path = _renamed_urdf(tmp_path)
    d = _spec_dict()
    d["urdf"] = str(path)
    for side, short in (("left", "L"), ("right", "R")):
        d[side]["joints"] = [f"{short}_axis_{i}" for i in range(1, 7)]
        d[side]["ee_link"] = f"{short}_tcp"
    spec = RobotSpec.model_validate(d)
    assert spec.urdf_path == path
    assert spec.dof == 6 and spec.layout.dim == 32


def test_custom_urdf_rejects_the_default_joint_names(tmp_path):
    path = _renamed_urdf(tmp_path)
    d = _spec_dict()
    d["urdf"] = str(path)
    _invalid(d, r"left: joint 'left_joint1' is not in renamed_dual_arm\.urdf")


def test_shipped_urdf_copied_elsewhere_is_accepted_unchanged(tmp_path):
    path = tmp_path / "copy.urdf"
    shutil.copy(SHIPPED_URDF, path)
    d = _spec_dict()
    d["urdf"] = str(path)
    assert RobotSpec.model_validate(d).urdf_path == path
