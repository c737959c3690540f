"""Telling the call that killed an actor from the calls queued behind it, whatever order Ray
reports their failures in."""

from anchordp3.pipeline.runner import ActorCalls


def _queue(*refs):
    calls = ActorCalls()
    for r in refs:
        calls.submitted("rollout/0", r)
    return calls


def test_the_executing_call_is_blamed_when_its_failure_arrives_first():
    calls = _queue("crash", "queued")
    assert calls.actor_died("rollout/0", "crash")
    calls.finished("rollout/0", "crash")
    assert not calls.actor_died("rollout/0", "queued")  # now oldest, but it never ran
    calls.finished("rollout/0", "queued")


def test_a_queued_call_is_not_blamed_when_its_failure_arrives_first():
    calls = _queue("crash", "queued")
    assert not calls.actor_died("rollout/0", "queued")
    calls.finished("rollout/0", "queued")
    assert calls.actor_died("rollout/0", "crash")


def test_calls_submitted_after_the_restart_are_judged_afresh():
    calls = _queue("crash", "queued")
    assert calls.actor_died("rollout/0", "crash")
    calls.finished("rollout/0", "crash")
    calls.submitted("rollout/0", "retry")
    assert not calls.actor_died("rollout/0", "queued")
    calls.finished("rollout/0", "queued")
    assert calls.actor_died("rollout/0", "retry")  # the retry ran on the restarted actor and killed it again
