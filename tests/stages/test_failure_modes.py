"""Failure modes that explain themselves: an episode that ran out of steps is classified from the
trace of its decisions (motion, gripper commands, object lift)."""

from __future__ import annotations

from anchordp3.stages.evaluate import DecisionTrace, diagnose

OPEN, CLOSED, BOTH_CLOSED, OTHER_CLOSED = (1.0, 1.0), (0.0, 1.0), (0.0, 0.0), (1.0, 0.0)


def d(motion: float, grippers: tuple[float, float], lift: float) -> DecisionTrace:
    return DecisionTrace(motion, grippers, lift)


def test_decisions_that_no_longer_move_the_robot_are_a_stall():
    trace = [d(0.4, OPEN, 0.0), d(0.001, OPEN, 0.0), d(0.0, OPEN, 0.0), d(0.002, OPEN, 0.0)]
    assert diagnose(trace, "step_limit") == "stalled"


def test_a_closed_gripper_that_lifted_nothing_missed_its_grasp():
    trace = [d(0.4, OPEN, 0.0), d(0.2, OPEN, 0.0), d(0.05, CLOSED, 0.0), d(0.3, CLOSED, 0.001)]
    assert diagnose(trace, "step_limit") == "grasp_missed"


def test_an_object_that_fell_while_the_gripper_stayed_closed_was_dropped():
    trace = [d(0.4, OPEN, 0.0), d(0.05, CLOSED, 0.0), d(0.3, CLOSED, 0.08), d(0.3, CLOSED, 0.0)]
    assert diagnose(trace, "step_limit") == "object_dropped"


def test_an_object_carried_then_released_off_target_was_placed_wrong():
    trace = [d(0.4, OPEN, 0.0), d(0.05, CLOSED, 0.0), d(0.3, CLOSED, 0.08), d(0.05, OPEN, 0.0), d(0.3, OPEN, 0.0)]
    assert diagnose(trace, "max_decisions") == "placed_wrong"


def test_a_release_by_one_arm_while_the_other_grasps_is_a_placement_not_a_drop():
    trace = [d(0.4, OPEN, 0.0), d(0.05, CLOSED, 0.0), d(0.3, CLOSED, 0.08), d(0.05, BOTH_CLOSED, 0.08),
             d(0.3, OTHER_CLOSED, 0.0), d(0.3, OTHER_CLOSED, 0.0)]
    assert diagnose(trace, "step_limit") == "placed_wrong"
    trace = [d(0.4, OPEN, 0.0), d(0.05, BOTH_CLOSED, 0.0), d(0.3, BOTH_CLOSED, 0.08), d(0.3, BOTH_CLOSED, 0.0)]
    assert diagnose(trace, "step_limit") == "object_dropped"


def test_an_object_lowered_below_the_lift_line_then_let_go_was_placed():
    """The place's descent (one anchor) brings the object down before the gripper opens."""
    trace = [d(0.4, OPEN, 0.0), d(0.05, CLOSED, 0.0), d(0.3, CLOSED, 0.08), d(0.1, CLOSED, 0.01),
             d(0.05, OPEN, 0.01), d(0.3, OPEN, 0.0)]
    assert diagnose(trace, "step_limit") == "placed_wrong"
    dropped_then_opened_late = trace[:4] + [d(0.3, CLOSED, 0.0)] * 3 + [d(0.3, OPEN, 0.0)]
    assert diagnose(dropped_then_opened_late, "step_limit") == "object_dropped"


def test_a_moving_episode_that_never_closed_a_gripper_just_ran_out():
    trace = [d(0.4, OPEN, 0.0), d(0.3, OPEN, 0.0), d(0.2, OPEN, 0.0)]
    assert diagnose(trace, "step_limit") == "step_limit"
    assert diagnose([d(0.3, CLOSED, 0.09)], "max_decisions") == "max_decisions"  # still holding it
