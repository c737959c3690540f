"""StateLayout: the one definition of the state / action vector."""

import numpy as np
import pytest

from anchordp3.schemas.state import ARMS, StateLayout


def _indices(layout: StateLayout) -> list[list[int]]:
    """Every index range of ``layout`` as explicit index lists, one per field."""
    groups = []
    for arm in ARMS:
        groups.append(list(range(*layout.qpos(arm).indices(layout.dim))))
        groups.append([layout.gripper(arm)])
        groups.append(list(range(*layout.ee_xyz(arm).indices(layout.dim))))
        groups.append(list(range(*layout.ee_rot6(arm).indices(layout.dim))))
    return groups


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q @ np.diag(np.sign(np.diag(r)))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def test_default_layout_is_32_dims_for_6_dof_arms():
    L = StateLayout()
    assert L.dof == 6
    assert L.dim == 32
    assert L.joint_dim == 14


@pytest.mark.parametrize("dof", [1, 5, 6, 7, 9])
def test_dim_is_two_arms_of_dof_plus_gripper_plus_18_ee_values(dof):
    L = StateLayout(dof)
    assert L.dim == 2 * (dof + 1) + 18
    assert L.joint_dim == 2 * (dof + 1)
    assert len(L.names()) == L.dim


@pytest.mark.parametrize("dof", [1, 6, 7])
def test_fields_are_disjoint_and_cover_every_index_exactly_once(dof):
    L = StateLayout(dof)
    groups = _indices(L)
    flat = [i for g in groups for i in g]
    assert sorted(flat) == list(range(L.dim))  # each index exactly once
    sizes = [len(g) for g in groups]
    assert sizes == [dof, 1, 3, 6] * 2


@pytest.mark.parametrize("dof", [1, 6, 7])
def test_joint_part_comes_first_and_spans_joint_dim(dof):
    L = StateLayout(dof)
    joint_idx = set()
    for arm in ARMS:
        joint_idx |= set(range(*L.qpos(arm).indices(L.dim))) | {L.gripper(arm)}
    assert joint_idx == set(range(L.joint_dim))


@pytest.mark.parametrize("dof", [6, 7])
def test_names_are_unique_and_follow_the_fields(dof):
    L = StateLayout(dof)
    names = L.names()
    assert len(set(names)) == len(names) == L.dim
    assert all(names)
    assert names[L.gripper("left")] == "left_gripper"
    assert names[L.gripper("right")] == "right_gripper"
    assert names[L.qpos("right")][0] == "right_q0"
    assert names[L.ee_xyz("left")] == ["left_ee_x", "left_ee_y", "left_ee_z"]
    assert names[L.ee_rot6("right")] == [f"right_ee_r{rc}" for rc in ("00", "01", "10", "11", "20", "21")]


def test_unknown_arm_is_rejected():
    with pytest.raises(ValueError, match="arm must be one of"):
        StateLayout().qpos("middle")


@pytest.mark.parametrize("dof", [6, 7])
def test_pack_round_trips_through_the_slices(dof):
    rng = np.random.default_rng(dof)
    L = StateLayout(dof)
    qpos = {a: rng.uniform(-3, 3, dof) for a in ARMS}
    grip = {a: float(rng.uniform()) for a in ARMS}
    ee = {}
    for a in ARMS:
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = _random_rotation(rng), rng.uniform(-1, 1, 3)
        ee[a] = m
    v = L.pack(qpos, grip, ee)
    assert v.shape == (L.dim,) and v.dtype == np.float64
    for a in ARMS:
        np.testing.assert_array_equal(v[L.qpos(a)], qpos[a])
        assert v[L.gripper(a)] == grip[a]
        np.testing.assert_array_equal(v[L.ee_xyz(a)], ee[a][:3, 3])
        # R[:3, :2] flattened row-major: (r00, r01, r10, r11, r20, r21)
        np.testing.assert_array_equal(v[L.ee_rot6(a)], ee[a][:3, :2].reshape(-1))
        np.testing.assert_array_equal(v[L.ee_rot6(a)].reshape(3, 2), ee[a][:3, :2])


def test_ee_matrix_recovers_random_rotation_and_position():
    rng = np.random.default_rng(0)
    L = StateLayout()
    for _ in range(20):
        ee = {}
        for a in ARMS:
            m = np.eye(4)
            m[:3, :3], m[:3, 3] = _random_rotation(rng), rng.uniform(-1, 1, 3)
            ee[a] = m
        v = L.pack({a: np.zeros(6) for a in ARMS}, {a: 1.0 for a in ARMS}, ee)
        for a in ARMS:
            np.testing.assert_allclose(L.ee_matrix(v, a), ee[a], atol=1e-12)


def test_ee_matrix_projects_a_slightly_off_manifold_rotation_to_a_proper_one():
    rng = np.random.default_rng(1)
    L = StateLayout()
    R = _random_rotation(rng)
    m = np.eye(4)
    m[:3, :3] = R
    v = L.pack({a: np.zeros(6) for a in ARMS}, {a: 0.0 for a in ARMS}, {a: m for a in ARMS})
    v[L.ee_rot6("left")] += rng.normal(scale=1e-3, size=6)  # a network's prediction is never exact
    out = L.ee_matrix(v, "left")[:3, :3]
    np.testing.assert_allclose(out.T @ out, np.eye(3), atol=1e-12)
    assert np.linalg.det(out) == pytest.approx(1.0, abs=1e-12)
    np.testing.assert_allclose(out, R, atol=1e-2)
