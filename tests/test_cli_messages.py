"""What the command line says: choices listed in the help, switches that need no value, one comma convention for
lists, errors in one line naming the field in the user's words (no pydantic wording), the usage of the subcommand
that was mistyped, and no reference to documents a user does not have."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from morph_sim.cli import main as cli_main
from morph_sim.environment import command_parser, env_to_argv
from services.runconfig import RunConfig, config_from_args

ROOT = Path(__file__).resolve().parents[1]
NOT_FOR_USERS = re.compile(r"\bissue \d+|shared/reference|Value error,|spec: spec:")


@pytest.mark.parametrize("command", ["up", "run", "sim", "agent", "monitor"])
def test_help_lists_the_choices_of_policy_preset_mode_and_scale(command, capsys):
    with pytest.raises(SystemExit):
        cli_main([command, "--help"])
    out = capsys.readouterr().out
    assert "--policy POLICY" in out and "--policy-option KEY=VALUE" in out
    # the shipped names, in the flag's help (any installed or importable policy is taken too)
    assert "(full,full-broadcast,constant,tsg,proximity,none,morph)" in "".join(out.split())
    assert "--preset {reference,paper}" in out
    assert "--mode {lockstep,paced}" in out
    assert "--scale {tiny,small,medium,large,extralarge}" in out
    assert "--ablation {full,v1,v1_paper,no_threshold,no_reward,no_neuromod,reset_at_boundary}" in out


def test_bench_distributed_help_lists_the_choices(capsys):
    with pytest.raises(SystemExit):
        cli_main(["bench", "distributed", "--help"])
    out = capsys.readouterr().out
    assert "--policy POLICY" in out and "--preset {reference,paper}" in out


def test_a_bad_choice_is_refused_naming_the_flag_and_the_choices(capsys):
    assert _exit(["run", "--mode", "bogus"]) == 2
    err = capsys.readouterr().err
    assert "morph-sim run: error: argument --mode: invalid choice: 'bogus'" in err and "'lockstep'" in err
    assert _exit(["run", "--policy", "bogus"]) == 2
    err = capsys.readouterr().err
    assert err.strip().splitlines() == ["morph-sim run: error: policy: unknown 'bogus' (known: full, full-broadcast, "
                                        "constant, tsg, proximity, none, morph; or package.module:Class)"]


def test_cold_restart_is_a_switch_on_the_command_line_in_the_environment_and_for_children():
    parser = command_parser("agent")
    assert config_from_args(parser.parse_args(["--cold-restart"]), environ={}).cold_restart is True
    assert config_from_args(parser.parse_args(["--no-cold-restart"]),
                            environ={"MORPH_COLD_RESTART": "true"}).cold_restart is False
    assert config_from_args(parser.parse_args([]), environ={"MORPH_COLD_RESTART": "true"}).cold_restart is True
    cold = RunConfig(run_id="r", cold_restart=True)
    assert "--cold-restart" in cold.to_argv() and "True" not in cold.to_argv()
    assert config_from_args(parser.parse_args(cold.to_argv()), environ={}) == cold
    warm = RunConfig(run_id="r")
    assert config_from_args(parser.parse_args(warm.to_argv()), environ={"MORPH_COLD_RESTART": "1"}) == warm
    assert env_to_argv("agent", {"MORPH_COLD_RESTART": "true"}) == ["--cold-restart"]
    assert env_to_argv("agent", {"MORPH_COLD_RESTART": "False"}) == ["--no-cold-restart"]
    # the supervisor's cold restart appends the switch after the child's argv: the last one wins
    assert config_from_args(parser.parse_args([*warm.to_argv(), "--cold-restart"]), environ={}).cold_restart


def test_bench_sim_takes_comma_separated_scales(capsys):
    assert cli_main(["bench", "sim", "--scales", "tiny,small", "--steps", "5", "--json"]) == 0
    rows = [json.loads(line) for line in capsys.readouterr().out.splitlines() if line.startswith("{")]
    assert [r["scale"] for r in rows] == ["tiny", "small"]
    assert _exit(["bench", "sim", "--scales", "tiny,huge", "--steps", "5"]) == 2
    assert "scales: unknown size(s) huge" in capsys.readouterr().err


def test_bench_sim_output_cites_nothing_a_user_lacks(capsys):
    assert cli_main(["bench", "sim", "--scales", "tiny", "--steps", "5"]) == 0
    out = capsys.readouterr().out
    assert "original steps/s" in out and not NOT_FOR_USERS.search(out), out


@pytest.mark.parametrize("argv, expected", [
    (["faults", "set", "--run", "x", "--spec", '{"crash": {"agent": 1}}'], "spec.crash: crash needs at_tick or every"),
    (["faults", "set", "--run", "x", "--spec", '{"loss": {"percent": 200}}'],
     "spec.loss.percent: Input should be less than or equal to 100"),
    (["faults", "set", "--run", "x", "--spec", '{"los": {"percent": 2}}'], "spec.los: not a known field"),
    (["run", "--steps", "0"], "steps: Input should be greater than or equal to 1"),
])
def test_errors_name_the_field_once_in_the_users_words(argv, expected, capsys):
    assert cli_main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.endswith(f"error: {expected}\n") and not NOT_FOR_USERS.search(err), err


def test_an_environment_value_error_is_worded_for_users():
    proc = subprocess.run([sys.executable, "-m", "morph_sim.cli", "run", "--steps", "1"], capture_output=True,
                          text=True, timeout=60, env={"MORPH_SCALE": "huge", "PATH": "/usr/bin:/bin"})
    assert proc.returncode == 2
    assert proc.stderr == ("morph-sim run: error: scale: unknown size 'huge'; choose one of tiny, small, medium, "
                           "large, extralarge\n")


@pytest.mark.parametrize("argv, usage", [
    (["faults", "set", "--run", "x", "--bogus", "1"], "usage: morph-sim faults set"),
    (["run", "--bogus"], "usage: morph-sim run"),
    (["bench", "sim", "--scales", "tiny", "small"], "usage: morph-sim bench sim"),
    (["experiment", "scale", "--nope"], "usage: morph-sim experiment"),
])
def test_an_unknown_flag_prints_the_usage_of_that_subcommand(argv, usage, capsys):
    assert _exit(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(usage), err
    prog = usage.removeprefix("usage: ")
    assert f"{prog}: error: unrecognized arguments: " in err


def test_the_readme_cites_no_issue_numbers_or_reference_files():
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    assert not NOT_FOR_USERS.search(text), NOT_FOR_USERS.search(text)


def _exit(argv) -> int:
    try:
        return cli_main(argv)
    except SystemExit as exc:
        return int(exc.code)


def test_run_refuses_a_schedule_with_a_crash_it_cannot_carry_out(tmp_path, capsys):
    schedule = tmp_path / "crash.toml"
    schedule.write_text('[[at]]\ntick = 0\nspec = { loss = { percent = 5 } }\n'
                        '[[at]]\ntick = 0\nspec = { crash = { agent = 1, at_tick = 5 } }\n')
    assert cli_main(["run", "--fault-schedule", str(schedule), "--steps", "10", "--output-dir", str(tmp_path)]) == 2
    assert capsys.readouterr().err == ("morph-sim run: error: fault_schedule: at[1] is a crash fault, which needs "
                                       "agent processes and a supervisor to kill and restart them: use "
                                       "`morph-sim up`\n")
