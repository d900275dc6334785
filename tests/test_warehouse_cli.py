"""``morph-sim warehouse`` and ``morph-sim bench sim``."""

import json

import pytest
from PIL import Image

from morph_sim.cli import main


def test_warehouse_prints_summary(capsys):
    assert main(["warehouse", "--scale", "tiny", "--seed", "0", "--steps", "200", "--no-progress"]) == 0
    out = capsys.readouterr().out
    assert "tiny 5+3 seed 0" in out
    assert "deliveries  14" in out  # the original's cumulative deliveries at t = 200 for tiny 5+3 seed 0
    assert "pick rate   50.4 lines/h" in out  # 14 * 3600 / (5 * 200)
    for word in ("clashes", "stucks", "steps/s"):
        assert word in out


def test_warehouse_custom_fleet_and_images(tmp_path, capsys):
    png, gif = tmp_path / "last.png", tmp_path / "ep.gif"
    code = main(["warehouse", "--scale", "small", "--agvs", "3", "--pickers", "2", "--steps", "30", "--png", str(png),
                 "--gif", str(gif), "--gif-every", "5", "--cell-px", "8", "--no-progress"])
    assert code == 0
    out = " ".join(capsys.readouterr().out.split())  # the console wraps a long image path at its width
    assert "small 3+2" in out and "(6 frames)" in out
    with Image.open(png) as im:
        assert im.size[0] > 14 * 8
    with Image.open(gif) as im:
        assert im.n_frames == 6


@pytest.mark.parametrize(
    "argv, field",
    [
        (["--scale", "huge"], "scale"),
        (["--agvs", "300"], "agvs"),
        (["--pickers", "-1"], "pickers"),
        (["--steps", "-5"], "steps"),
        (["--steps", "0"], "steps"),
        (["--gif-every", "0"], "gif-every"),
    ],
)
def test_warehouse_bad_input_exit_2_naming_field(argv, field, capsys):
    assert main(["warehouse", "--no-progress", *argv]) == 2
    err = capsys.readouterr().err
    assert f"{field}:" in err and "Traceback" not in err


def test_bench_sim_runs_episode_in_child_process(capsys):
    assert main(["bench", "sim", "--scales", "tiny", "--steps", "100", "--json"]) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert row["scale"] == "tiny" and row["steps"] == 100 and row["agvs"] == 5 and row["pickers"] == 3
    assert row["deliveries"] == 8  # the original's cumulative deliveries at t = 100, seed 0
    assert row["original_steps_per_s"] == 770
    assert row["steps_per_s_cpu"] > 0 and row["speedup_cpu"] > 0
    assert 10 < row["peak_rss_mb"] < 500


def test_bench_sim_table(capsys):
    assert main(["bench", "sim", "--scales", "tiny", "--steps", "50"]) == 0
    out = capsys.readouterr().out
    assert "tiny" in out and "5+3" in out and "uoe-agents@6109c33" in out  # the baseline named for a user


def test_bench_needs_a_target_and_valid_scales(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["bench"])
    assert exc.value.code == 2
    assert main(["bench", "sim", "--scales", "gigantic"]) == 2
    assert "scales:" in capsys.readouterr().err
