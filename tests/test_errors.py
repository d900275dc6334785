"""One formatter of validation errors: every config, CLI value and fault spec error is one line naming the field."""

from __future__ import annotations

import subprocess
import sys

import pytest

from schemas.errors import one_line
from schemas.messages import FaultCommand
from services.faults.schedule import parse_schedule
from services.policies.presets import load_preset
from services.runconfig import RunConfig


def _error(make) -> str:
    with pytest.raises(ValueError) as info:
        make()
    return str(info.value)


@pytest.mark.parametrize("make,expected", [
    (lambda: RunConfig.coerce({"steps": 0}), "steps: Input should be greater than or equal to 1"),
    (lambda: RunConfig.coerce({"ablation": "zz"}), "ablation: unknown 'zz'"),
    (lambda: parse_schedule({"at": [{"tick": 1, "op": "set", "spec": {"loss": {"percent": 120}}}]}),
     "schedule: at[0].spec.loss.percent: Input should be less than or equal to 100"),
    (lambda: load_preset("reference").resolve("nonexistent"), "ablation: unknown 'nonexistent'"),
])
def test_errors_are_one_line_naming_the_field(make, expected):
    text = _error(make)
    assert text.startswith(expected), text
    assert "\n" not in text and "Value error" not in text and "errors.pydantic.dev" not in text


def test_a_field_is_never_named_twice():
    with pytest.raises(ValueError) as info:
        FaultCommand(op="set", spec={"loss": {"percent": 500}})
    text = one_line(info.value)
    assert text.startswith("spec.loss.percent: ") and "spec: spec" not in text, text


def test_the_cli_prints_one_line_and_exits_2_on_a_bad_value(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "morph_sim.cli", "run", "--steps", "0",
                           "--output-dir", str(tmp_path)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("morph-sim run: error: steps: Input should be greater than or equal to 1"), lines
