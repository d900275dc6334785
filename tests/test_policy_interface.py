"""The public policy interface: policies found by name, entry point or import path; their options validated from the
command line, the environment and the API with one line naming the option; the conformance kit on every shipped
policy and on three policies that break a rule on purpose (tests/_policies.py)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from morph_sim.cli import main as cli_main
from morph_sim.environment import env_to_argv
from morph_sim.testing import PolicyCheckFailed, check_policy, policy_findings
from services.policies.coordinators import ProximityPolicy
from services.policies.loading import make_policy, resolve
from services.runconfig import RunConfig

TESTS = str(Path(__file__).resolve().parent)
#: the decision-time rule's bound in these tests: the rule is the kit's, the machine running the suite is shared
LIMIT = 2.0


@pytest.fixture(autouse=True)
def _importable(monkeypatch):
    monkeypatch.syspath_prepend(TESTS)  # _policies:Name


def _exit(argv, capsys) -> tuple[int, list[str]]:
    code = cli_main(argv)
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("argv, line", [
    (["run", "--policy", "nope:Thing"], "policy: cannot import 'nope' (No module named 'nope')"),
    (["run", "--policy", "_policies:Missing"], "policy: module '_policies' has no 'Missing'"),
    (["run", "--policy", "_policies:np"], "policy: '_policies:np' is not a CoordinationPolicy subclass "
                                          "(services.policies.interface.CoordinationPolicy)"),
    (["run", "--policy", "proximity", "--policy-option", "radius=near"],
     "policy-option radius: Input should be a valid integer, unable to parse string as an integer, got 'near'"),
    (["run", "--policy", "proximity", "--policy-option", "radius=-1"],
     "policy-option radius: Input should be greater than or equal to 0, got '-1'"),
    (["run", "--policy", "proximity", "--policy-option", "reach=3"],
     "policy-option reach: policy 'proximity' has no such option (its options: radius)"),
    (["run", "--policy", "proximity", "--policy-option", "radius"],
     "policy-option: 'radius' is not KEY=VALUE (KEY a parameter name)"),
    (["run", "--policy", "proximity", "--radius", "2", "--policy-option", "radius=3"],
     "policy-option radius: 3 differs from --radius 2; give it once"),
    (["policy", "check", "proximity", "--policy-option", "radius=x"],
     "policy-option radius: Input should be a valid integer, unable to parse string as an integer, got 'x'"),
    (["policy", "show", "bogus"], "policy: unknown 'bogus' (known: full, full-broadcast, constant, tsg, proximity, "
                                  "none, morph; or package.module:Class)"),
])
def test_a_bad_policy_or_option_is_one_line_and_exit_2(argv, line, capsys):
    code, err = _exit(argv, capsys)
    assert code == 2 and err == [f"morph-sim {argv[0]}: error: {line}"]


def test_options_travel_by_flag_environment_and_api_alike():
    by_api = RunConfig(run_id="r", policy="proximity", policy_options={"radius": 6})
    by_env = RunConfig.from_env({"MORPH_RUN_ID": "r", "MORPH_POLICY": "proximity", "MORPH_POLICY_OPTIONS": "radius=6"})
    by_json = RunConfig.from_env({"MORPH_RUN_ID": "r", "MORPH_POLICY": "proximity",
                                  "MORPH_POLICY_OPTIONS": '{"radius": 6}'})
    for cfg in (by_api, by_env, by_json):
        assert cfg.make_policy() == ProximityPolicy(radius=6)
    # a child process gets them back as repeated flags, a container as one variable
    assert by_api.to_argv(("policy", "policy_options")) == ["--policy", "proximity", "--policy-option", "radius=6"]
    assert RunConfig.from_env(by_env.to_env()).make_policy() == ProximityPolicy(radius=6)
    assert env_to_argv("sim", {"MORPH_POLICY_OPTIONS": "a=1,b=x"}) == ["--policy-option", "a=1", "--policy-option",
                                                                       "b=x"]


def test_a_policy_from_an_import_path_and_from_an_entry_point(tmp_path, monkeypatch):
    assert resolve("_policies:ClosestRequest").name == "closest-request"
    # an installed package registers its policy under the entry-point group; importlib.metadata finds it on sys.path
    dist = tmp_path / "closest_request-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: closest-request\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text("[morph_sim.policies]\nclosest-request = _policies:ClosestRequest\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert make_policy("closest-request").name == "closest-request"
    code = cli_main(["policy", "list"])
    assert code == 0


def test_the_shipped_policies_conform_in_the_lab():
    # both MORPH presets, a baseline of each kind (memoryless gate, broadcast) and a policy that chooses for its pickers
    for name, options in [("morph", {}), ("morph", {"preset": "paper"}), ("full-broadcast", {}), ("proximity", {}),
                          ("_policies:ClosestRequest", {})]:
        assert policy_findings(name, options, steps=60, distributed=False, decision_limit=LIMIT) == [], (name, options)


@pytest.mark.slow
def test_every_shipped_policy_preset_and_ablation_conforms_in_the_lab():
    from services.policies.presets import ABLATIONS

    for name in ("full", "constant", "tsg", "none"):
        assert policy_findings(name, distributed=False, decision_limit=LIMIT) == [], name
    for preset in ("reference", "paper"):
        for ablation in (None, *ABLATIONS):
            assert policy_findings("morph", {"preset": preset, "ablation": ablation}, distributed=False,
                                   decision_limit=LIMIT) == []


@pytest.mark.parametrize("cls, lines", [
    ("ReadsGlobal", ["own-view: robot 3, tick 0: with one brain for the fleet it decided P(ask picker 6) = 0, with a "
                     "brain (and a copy of the policy's module) of its own P(ask picker 6) = 1"]),
    ("NonDeterministic", ["determinism: robot 2, tick 0: the same seed decided P(ask picker 6) = "]),
    ("CannotRestore", ["restore: robot 0, tick 61: probability 0.555556 after restoring from the states of tick 60, "
                       "0.151515 without a restart"]),
])
def test_a_broken_policy_fails_naming_the_rule_the_robot_and_the_tick(cls, lines):
    with pytest.raises(PolicyCheckFailed) as failed:
        check_policy(f"_policies:{cls}", distributed=False, decision_limit=LIMIT)
    found = [str(f) for f in failed.value.findings]
    for line in lines:
        assert any(f.startswith(line) for f in found), found
    kinds = {f.rule for f in failed.value.findings}
    assert kinds <= {"own-view", "determinism", "restore"}, kinds


def test_policy_check_prints_one_line_per_broken_rule_and_exits_1(capsys):
    assert cli_main(["policy", "check", "_policies:CannotRestore", "--no-distributed", "--steps", "80",
                     "--decision-limit", str(LIMIT)]) == 1
    out, err = capsys.readouterr()
    assert out and all(line.startswith("restore: robot ") for line in out.strip().splitlines())
    assert err.strip() == "policy _policies:CannotRestore: 5 of 6 rules kept; broken: restore"


def test_a_policy_that_raises_is_reported_not_crashed():
    found = [str(f) for f in policy_findings("_policies:Raises", distributed=False, decision_limit=LIMIT)]
    assert found == ["robustness: robot 4, tick 20: probability raised KeyError: 6"]
    assert [str(f) for f in policy_findings("_policies:Raises", {"nope": 1}, distributed=False)] == [
        "interface: policy-option nope: policy 'raises' has no such option (its options: none)"]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(pytest.main([__file__]))


# -- policy messages ---------------------------------------------------------------------------------------------------
def test_a_policy_message_is_checked_when_it_is_sent():
    from services.policies.interface import Fleet

    brains = make_policy("_policies:ClosestRequest").brains(Fleet(5, 3, "tiny"), [0], 1)
    brains.send(0, 6, {"bid": 3})
    brains.send(0, None, {"claim": [1, 2]})
    assert [to for to, _ in brains.take_outbox(0)] == [6, None] and brains.take_outbox(0) == []
    for to, data, why in [(0, {"x": 1}, "robot 0 cannot send to 0"), (8, {"x": 1}, "robot 0 cannot send to 8"),
                          (6, [1, 2], "the content must be a mapping"), (6, {"x": "a" * 2000}, "at most 1024"),
                          (6, {"x": object()}, "cannot pack its content")]:
        with pytest.raises(ValueError, match=why):
            brains.send(0, to, data)


def test_a_mailbox_hands_over_what_was_sent_before_this_tick_and_delivered_by_now():
    from schemas.messages import PolicyMessage
    from services.policies.interface import pack_mail
    from services.protocol.dispatch import Mailbox

    box = Mailbox()

    def mail(sender, t, pseq, **data):
        return PolicyMessage(t=t, sender=sender, to=None, pseq=pseq, data=pack_mail(data))

    assert box.receive(mail(3, 4, 1, a=1), due=4.0)
    assert not box.receive(mail(3, 4, 1, a=1), due=4.5)  # a copy
    box.receive(mail(1, 4, 7, b=2), due=4.0)
    box.receive(mail(2, 5, 1, c=3), due=5.0)  # sent this tick: the next one takes it
    box.receive(mail(0, 3, 2, d=4), due=6.5)  # late: delivered after this decision point
    taken = box.take(5, 5.0)
    assert [(m.sender, m.t, dict(m.data)) for m in taken] == [(1, 4, {"b": 2}), (3, 4, {"a": 1})]
    assert [m.sender for m in box.take(6, 6.0)] == [2]
    assert [m.sender for m in box.take(7, 7.0)] == [0]
    with pytest.raises(ValueError, match="not a mapping"):
        box.receive(PolicyMessage(t=1, sender=1, pseq=9, data=b"\x01"), due=1.0)


def test_a_decision_point_waits_for_the_policy_messages_announced_to_it():
    from services.protocol.readiness import Readiness

    r = Readiness(lockstep=True)
    r.fleet(5)
    r.announce(4, 0, 0)
    assert r.may_act(4, 0, False)
    r.announce(5, 0, 2)  # two messages were sent to this robot in tick 4
    assert not r.may_act(5, 0, False) and r.messages_owed() == 2
    assert r.message("agent-1", 10, 4) and not r.message("agent-1", 10, 4)  # a copy counts once
    assert not r.may_act(5, 0, False)
    r.message("agent-2", 3, 4)  # delivered, or held or lost by the fault layer: arrived all the same
    assert r.may_act(5, 0, False)


def test_the_network_study_enters_a_policy_from_outside_by_name():
    from morph_sim.lab.network_study import grid_plan, network_tasks, run_network_task

    plan = grid_plan(scales=("tiny",), profiles=("wifi-legacy-roaming",), conditions=["_policies:ClosestRequest"],
                     seeds=(1,), steps=60)
    episode = run_network_task(network_tasks(plan)[0])["episode"]
    assert episode["condition"] == "_policies:ClosestRequest" and episode["steps"] == 60
    assert episode["messages_per_delivery"] is None or episode["messages_per_delivery"] > 0
    with pytest.raises(ValueError, match="conditions: unknown 'all'; choose from .* or a policy name"):
        grid_plan(conditions=["all"])
