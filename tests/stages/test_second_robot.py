"""A robot of one's own, from the run config: a changed copy of the shipped URDF (upper arms 4 cm
longer) runs the rollout, anchors, render and features stages, and its episodes are its own."""

import numpy as np
import yaml

from anchordp3.schemas.robot import ASSETS_DIR
from anchordp3.schemas.run import RunConfig
from anchordp3.stages.anchors import run_anchors
from anchordp3.stages.features import load_features, run_features
from anchordp3.stages.files import plan_file
from anchordp3.stages.render import load_frames, run_render
from anchordp3.stages.rollout import load_episode, rollout

LONGER = 0.04  # metres added to each upper arm (link2, between joint2 and joint3)


def longer_arms_urdf(path):
    """The shipped URDF with both upper arms ``LONGER`` longer: joint3 moves up, link2's cylinder grows."""
    text = (ASSETS_DIR / "dual_arm.urdf").read_text()
    assert text.count('<origin xyz="0 0 0.38" rpy="0 0 0"/><axis xyz="-1 0 0"/>') == 2  # each arm's joint3
    text = text.replace('<origin xyz="0 0 0.38" rpy="0 0 0"/><axis xyz="-1 0 0"/>',
                        f'<origin xyz="0 0 {0.38 + LONGER}" rpy="0 0 0"/><axis xyz="-1 0 0"/>')
    text = text.replace('<origin xyz="0 0 0.19" rpy="0 0 0"/><geometry><cylinder radius="0.04" length="0.38"/>',
                        f'<origin xyz="0 0 {(0.38 + LONGER) / 2}" rpy="0 0 0"/><geometry><cylinder radius="0.04" length="{0.38 + LONGER}"/>')
    path.write_text(text)
    return path


def config(tmp_path, robot: dict | None) -> RunConfig:
    """A small run config (64x48 cameras, 256 points), read from YAML as a user's would be."""
    data = {"tasks": ["place_mouse"], "seeds": "0", "preset": "clean", "cameras": {"width": 64, "height": 48},
            "features": {"n_points": 256}}
    if robot is not None:
        data["robot"] = robot
    path = tmp_path / ("own.yaml" if robot else "shipped.yaml")
    path.write_text(yaml.safe_dump(data))
    return RunConfig.model_validate(yaml.safe_load(path.read_text()))


def data_stages(cfg: RunConfig, d):
    """Rollout, anchors, render and features of the config's one episode; returns its record and arrays."""
    rec = rollout("place_mouse", 0, cfg.world(), cfg.preset, d / "rollout")
    assert rec.success, (rec.reason, rec.detail)
    run_anchors(rec, d / "rollout", d / "anchors", cfg.anchors)
    frames = run_render(rec, d / "rollout", d / "anchors" / plan_file(rec.task, rec.seed), d / "render", cfg.world(), cfg.render, cfg.anchors)
    feats = run_features(rec.task, rec.seed, d / "render" / frames, d / "features", cfg.features)
    return rec, load_episode(d / "rollout", rec), load_frames(d / "render" / frames), load_features(d / "features" / feats)


def test_a_second_robot_description_runs_the_data_stages(tmp_path):
    urdf = longer_arms_urdf(tmp_path / "longer_arms.urdf")
    own = config(tmp_path, {"urdf": str(urdf)})
    shipped = config(tmp_path, None)
    assert own.robot.urdf_path == urdf.resolve()
    # a different robot is a different world: every stage downstream of the rollout is redone
    assert own.stage_config("rollout") != shipped.stage_config("rollout")
    assert own.stage_config("render") != shipped.stage_config("render")

    rec, episode, frames, feats = data_stages(own, tmp_path / "own")
    _, ref_episode, _, _ = data_stages(shipped, tmp_path / "shipped")
    F = len(frames["t"])
    assert F > 0 and feats["points"].shape == (F, 256, 11)
    assert np.isfinite(feats["points"]).all() and feats["labels"].any()  # the mouse is seen
    # the same joint angles put the longer arm's hand elsewhere: the home state differs
    L = own.robot.layout
    home, ref_home = episode["states"][0], ref_episode["states"][0]
    np.testing.assert_allclose(home[L.qpos("left")], ref_home[L.qpos("left")], atol=1e-3)
    assert np.abs(L.ee_matrix(home, "left")[:3, 3] - L.ee_matrix(ref_home, "left")[:3, 3]).max() > LONGER / 2
