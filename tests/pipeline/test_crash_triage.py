"""Blame after an actor dies: calls lost with it are retried free and alone, and only a crash
with a single call on the actor costs that item an attempt (no Ray needed)."""

from anchordp3.pipeline.runner import CrashTriage

ACTOR, OTHER = ("rollout", 0), ("rollout", 1)
A, B = ("rollout", "place_bell/000000"), ("rollout", "place_bell/000001")


def test_calls_lost_together_are_not_blamed_and_the_actor_waits_for_a_ping():
    t = CrashTriage()
    t.submitted(ACTOR, A)
    t.submitted(ACTOR, B)
    assert not t.lost(ACTOR, A) and not t.lost(ACTOR, B)  # A's reply died with the process B crashed
    t.finished(ACTOR, A, ok=False)
    t.finished(ACTOR, B, ok=False)
    assert not t.can_take(ACTOR, A, load=0, cap=2)  # down until it answers
    assert t.can_take(OTHER, ("rollout", "place_mouse/000000"), load=1, cap=2)
    t.up(ACTOR)
    assert t.can_take(ACTOR, A, load=0, cap=2)


def test_a_suspect_runs_alone_and_is_blamed_only_for_its_own_crash():
    t = CrashTriage()
    t.submitted(ACTOR, A)
    t.submitted(ACTOR, B)
    t.lost(ACTOR, A), t.lost(ACTOR, B)
    t.finished(ACTOR, A, ok=False), t.finished(ACTOR, B, ok=False)
    t.up(ACTOR)
    assert not t.can_take(ACTOR, A, load=1, cap=2)  # a suspect needs an idle actor
    t.submitted(ACTOR, A)
    assert not t.can_take(ACTOR, ("rollout", "place_mouse/000000"), load=1, cap=2)  # and keeps it to itself
    t.finished(ACTOR, A, ok=True)  # A was innocent
    assert t.can_take(ACTOR, A, load=1, cap=2)
    t.submitted(ACTOR, B)
    assert t.lost(ACTOR, B)  # B alone killed the actor: its fault
    t.finished(ACTOR, B, ok=False)
    t.up(ACTOR)
    assert not t.can_take(ACTOR, B, load=1, cap=2) and t.can_take(ACTOR, B, load=0, cap=2)
