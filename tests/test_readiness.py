"""What a robot's decision point waits for in a lockstep run (services/protocol/readiness.py), as pure code: counts
announced on board and arrivals in, "may act now" / "still owed N" out. An arrival here is whatever the driver
counts as one: delivered, or held or dropped by its fault layer."""

from __future__ import annotations

from services.protocol.readiness import Readiness


def _first_on_board(r: Readiness, t: int, refused: int) -> None:
    """The robot's first on-board state, and its decision point asking: the count it announces is the base."""
    r.announce(t, refused)
    assert r.refusals_owed() == 0


def _ready(lockstep: bool = True, fleet: int = 100) -> Readiness:
    """A robot whose fleet broadcasts have all arrived, so only replies, refusals and requests are in question."""
    r = Readiness(lockstep)
    r.fleet(fleet)
    return r


# -- the fleet broadcast ---------------------------------------------------------------------------------------------
def test_the_tick_waits_for_its_own_fleet_broadcast_and_only_a_newer_one_resumes_it():
    r = Readiness(lockstep=True)
    assert not r.may_act(3, 0, False)
    assert r.fleet(2)
    assert not r.may_act(3, 0, False)  # an older broadcast is not this tick's
    assert r.fleet(3)
    assert r.may_act(3, 0, False)
    assert not r.fleet(3) and not r.fleet(1)  # a copy, or an older one arriving late, resumes nothing
    assert r.fleet_arrived == 3


def test_a_paced_robot_waits_for_its_fleet_broadcast_and_for_nothing_else():
    r = Readiness(lockstep=False)
    _first_on_board(r, 1, 0)
    r.asked(1, 0)
    r.announce(2, 3)
    assert r.refusals_owed() == 3 and r.replies_owed(5) == 5  # owed, none arrived
    assert not r.may_act(2, 5, True)
    r.fleet(2)
    assert r.may_act(2, 5, True)  # replies and refusals owed, but a real-time robot acts on what it has
    assert r.may_decide(2, [])
    assert not r.may_decide(2, [7])  # its Resolve's requests it still waits for (until its deadline)


# -- replies to an AGV -----------------------------------------------------------------------------------------------
def test_a_reply_announced_but_not_arrived_blocks_the_agv_with_a_request_outstanding():
    r = _ready()
    r.asked(2, 1)  # asked at step 2, one reply sent to it before
    assert r.may_act(3, 1, True)  # nothing sent since
    assert r.replies_owed(2) == 1
    assert not r.may_act(3, 2, True)  # the on-board state says a reply was sent since: wait for it
    assert r.may_act(3, 2, False)  # no request outstanding (or the final tick): the count is not waited for
    assert r.reply("picker-5", 7, 2)
    assert r.replies_owed(2) == 0
    assert r.may_act(3, 2, True)


def test_a_reply_held_or_lost_counts_once_when_it_arrives_and_not_again_when_released():
    r = _ready()
    r.asked(2, 0)
    assert r.reply("picker-5", 7, 2)  # arrived and held (or dropped) by the fault layer: it has arrived
    assert r.may_act(3, 1, True)
    assert not r.reply("picker-5", 7, 2)  # the same copy released later, or a duplicate: counted once
    assert r.replies_owed(2) == 1  # a second copy does not stand in for another reply


def test_replies_are_counted_from_the_agvs_own_request_on():
    r = _ready()
    assert r.reply("picker-5", 1, 4)  # the answer to an earlier request, arrived before the AGV asked again
    r.asked(5, 3)  # the on-board count 3 includes it
    assert r.replies_owed(3) == 0
    assert r.reply("picker-6", 1, 3)  # a late answer decided before this request: not one of those owed
    assert r.replies_owed(4) == 1
    assert r.reply("picker-6", 2, 5)  # decided at the step of the request: owed
    assert r.replies_owed(4) == 0


def test_a_reply_arriving_before_the_on_board_state_that_announces_it_counts():
    r = _ready()
    r.asked(5, 0)
    assert r.reply("picker-5", 9, 5)  # its path was quicker than the sim's
    assert r.may_act(6, 1, True)


# -- refusals to any robot --------------------------------------------------------------------------------------------
def test_a_refusal_announced_but_not_arrived_blocks_both_decision_points():
    r = _ready()
    _first_on_board(r, 1, 0)
    r.announce(2, 1)  # the sim refused one commitment at the boundary before tick 2
    assert r.refusals_owed() == 1
    assert not r.may_act(2, 0, False)
    assert not r.may_decide(2, [])
    assert r.refusal("sim", 9, 2)
    assert r.refusals_owed() == 0
    assert r.may_act(2, 0, False) and r.may_decide(2, [])


def test_a_restarted_robot_does_not_wait_for_refusals_sent_before_its_first_on_board_state():
    r = _ready()
    _first_on_board(r, 10, 4)  # its predecessor had those four
    assert r.may_act(10, 0, False)
    assert r.refusal("sim", 30, 8)  # one of them reaching this process late changes nothing
    assert r.refusals_owed() == 0
    r.announce(11, 5)
    assert r.refusals_owed() == 1  # the tick-8 refusal does not stand in for the one sent before tick 11
    assert r.refusal("sim", 31, 11)
    assert r.refusals_owed() == 0


def test_no_refusal_is_owed_before_the_first_on_board_state():
    r = _ready()
    assert r.refusal("sim", 3, 1)  # arrived ahead of the robot's first on-board state
    assert r.refusals_owed() == 0
    assert r.may_act(0, 0, False)


def test_duplicate_refusals_count_once():
    r = _ready()
    _first_on_board(r, 1, 0)
    r.announce(2, 2)
    assert r.refusal("sim", 9, 2)
    assert not r.refusal("sim", 9, 2)  # a copy (the same sender and sequence number)
    assert r.refusals_owed() == 1
    assert r.refusal("sim", 10, 2)
    assert r.refusals_owed() == 0


def test_only_the_newest_on_board_state_announces():
    r = _ready()
    _first_on_board(r, 1, 0)
    r.announce(3, 2)
    r.announce(2, 1)  # an older one arriving late (a skipped tick's) takes nothing back
    assert r.refusals_owed() == 2


def test_a_refusal_arriving_before_the_on_board_state_that_announces_it_counts():
    r = _ready()
    _first_on_board(r, 1, 0)
    assert r.refusal("sim", 4, 2)  # sent at the boundary before tick 2, handled before tick 2's on-board state
    assert r.refusals_owed() == 0
    r.announce(2, 1)
    assert r.refusals_owed() == 0


def test_the_base_stays_while_something_is_owed_and_moves_once_nothing_is():
    r = _ready()
    _first_on_board(r, 1, 0)
    r.announce(2, 2)
    assert r.refusal("sim", 9, 2)
    assert r.refusals_owed() == 1
    assert r.refusals_owed() == 1  # asking again while one is owed settles nothing
    assert r.refusal("sim", 10, 2)
    assert r.refusals_owed() == 0  # the base moves to tick 2: what arrived up to it is settled
    assert r.refusal("sim", 11, 2)  # one more labelled tick 2 (not announced) arriving after the base moved
    r.announce(3, 3)
    assert r.refusals_owed() == 1  # it does not stand in for the one sent before tick 3
    assert r.refusal("sim", 12, 3)
    assert r.refusals_owed() == 0


# -- requests to a picker ---------------------------------------------------------------------------------------------
def test_a_picker_decides_once_every_request_its_resolve_expects_has_arrived():
    r = _ready()
    assert r.may_decide(4, [])  # a Resolve that lists no request for it
    r.request(4, 1)
    assert not r.may_decide(4, [1, 2])
    r.request(3, 2)  # AGV 2's request of another tick is not the one expected
    assert not r.may_decide(4, [1, 2])
    r.request(4, 2)  # delivered, or held or dropped by the fault layer: arrived
    r.request(4, 2)  # a copy changes nothing
    assert r.may_decide(4, [1, 2])


def test_a_decision_forgets_the_requests_of_its_step_and_before_but_not_later_ones():
    r = _ready()
    r.request(3, 1)
    r.request(4, 1)
    r.request(5, 2)
    r.decided(4)
    assert not r.may_decide(3, [1]) and not r.may_decide(4, [1])
    assert r.may_decide(5, [2])


def test_a_picker_waits_for_the_refusals_announced_before_its_requests():
    r = _ready()
    _first_on_board(r, 1, 0)
    r.announce(2, 1)
    r.request(2, 0)
    assert not r.may_decide(2, [0])  # the refusal may end its commitment in flight: wait for it
    assert r.refusal("sim", 5, 2)
    assert r.may_decide(2, [0])
