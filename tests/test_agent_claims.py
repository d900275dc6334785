"""`morph-sim agent` without --id claims its robot id from the sim's registry (C1/C2), and processes read
the deployment's Zenoh config from ZENOH_CONFIG (C3). Live, on 127.0.0.1 only."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys

import pytest

from services.process import ZENOH_CONFIG_ENV, base_zenoh_config

AGVS, PICKERS = 5, 3
TIMEOUT = 120.0


def _kill_all(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=5)


def test_agents_without_ids_claim_every_id_with_the_fleet_roles_and_the_run_completes(tmp_path):
    """Three robots (two AGVs, a picker), each agent a fresh interpreter with its own --instance: ids and roles do not
    depend on the fleet's size; the test below starts the tiny fleet's eight by hand."""
    from services.bus.zenoh_bus import free_port

    agvs, pickers = 2, 1
    where = f"tcp/127.0.0.1:{free_port()}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MORPH_") and k != ZENOH_CONFIG_ENV}
    common = ["--run-id", "claims", "--scale", "tiny", "--agvs", str(agvs), "--pickers", str(pickers),
              "--steps", "20", "--ready-timeout", "60", "--output-dir", str(tmp_path)]
    cli = [sys.executable, "-m", "morph_sim.cli"]
    procs: list[subprocess.Popen] = []
    try:
        sim = subprocess.Popen(cli + ["sim", "--listen", where, "--no-wait-monitor", *common], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(sim)
        agents = [subprocess.Popen(cli + ["agent", "--endpoint", where, "--instance", f"box-{i}", *common],
                                   env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                  for i in range(agvs + pickers)]
        procs += agents
        out, err = sim.communicate(timeout=TIMEOUT)
        assert sim.returncode == 0, err[-3000:]
        result = json.loads(out.strip().splitlines()[-1])
        assert result["steps"] == 20 and result["stopped_early"] is None and result["absences"] == 0
        claimed = {}
        for proc in agents:
            text, err = proc.communicate(timeout=30)
            assert proc.returncode == 0, err[-2000:]
            report = json.loads(text.strip().splitlines()[-1])
            assert report["ticks"] == 21  # 20 steps and the final report
            claimed[report["agent"]] = (report["role"], report["instance"])
        assert sorted(claimed) == list(range(agvs + pickers))
        assert [claimed[i][0] for i in range(agvs + pickers)] == ["agv"] * agvs + ["picker"] * pickers
        assert {inst for _, inst in claimed.values()} == {f"box-{i}" for i in range(agvs + pickers)}
    finally:
        _kill_all(procs)


def test_eight_agents_started_by_hand_without_id_or_instance_on_one_host_form_a_run(tmp_path):
    """As the README promises: sim + monitor + eight `morph-sim agent` processes with no --id, no --instance and no
    MORPH_INSTANCE (so all on one host name) each claim a distinct free id and the run completes with a record."""
    from services.bus.zenoh_bus import free_port

    where = f"tcp/127.0.0.1:{free_port()}"
    env = {k: v for k, v in os.environ.items() if not k.startswith("MORPH_") and k != ZENOH_CONFIG_ENV}
    common = ["--run-id", "byhand", "--scale", "tiny", "--steps", "30", "--ready-timeout", "60",
              "--output-dir", str(tmp_path)]
    cli = [sys.executable, "-m", "morph_sim.cli"]
    procs: list[subprocess.Popen] = []
    try:
        sim = subprocess.Popen(cli + ["sim", "--listen", where, *common], env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(sim)
        monitor = subprocess.Popen(cli + ["monitor", "--endpoint", where, *common], env=env,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(monitor)
        agents = [subprocess.Popen(cli + ["agent", "--endpoint", where, *common], env=env,
                                   stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                  for _ in range(AGVS + PICKERS)]
        procs += agents
        out, err = sim.communicate(timeout=TIMEOUT)
        assert sim.returncode == 0, err[-3000:]
        result = json.loads(out.strip().splitlines()[-1])
        assert result["steps"] == 30 and result["stopped_early"] is None and result["absences"] == 0
        claimed = {}
        for proc in agents:
            text, err = proc.communicate(timeout=30)
            assert proc.returncode == 0, err[-2000:]
            report = json.loads(text.strip().splitlines()[-1])
            claimed[report["agent"]] = report["instance"]
        assert sorted(claimed) == list(range(AGVS + PICKERS))  # eight distinct ids, the whole fleet
        assert len(set(claimed.values())) == AGVS + PICKERS
        _, err = monitor.communicate(timeout=30)
        assert monitor.returncode == 0, err[-2000:]
        summary = json.loads((tmp_path / "byhand" / "summary.json").read_text())
        assert summary["steps"] == 30 and summary["finished"]
        assert len((tmp_path / "byhand" / "metrics.csv").read_text().splitlines()) == 1 + 30
    finally:
        _kill_all(procs)


def test_zenoh_config_names_the_deployment_file_and_a_bad_one_is_refused(tmp_path):
    good = tmp_path / "client.json5"
    good.write_text('{ transport: { auth: { usrpwd: { user: "agent", password: "secret" } } } }')
    assert base_zenoh_config({}) is None
    cfg = base_zenoh_config({ZENOH_CONFIG_ENV: str(good)})
    assert '"agent"' in cfg.get_json("transport/auth/usrpwd/user")
    with pytest.raises(ValueError, match=ZENOH_CONFIG_ENV):
        base_zenoh_config({ZENOH_CONFIG_ENV: str(tmp_path / "missing.json5")})


def test_an_agent_with_a_bad_zenoh_config_exits_with_a_message_naming_it(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("MORPH_")}
    env[ZENOH_CONFIG_ENV] = str(tmp_path / "missing.json5")
    proc = subprocess.run([sys.executable, "-m", "morph_sim.cli", "agent", "--id", "0", "--run-id", "x",
                           "--endpoint", "tcp/127.0.0.1:9"], env=env, capture_output=True, text=True, timeout=60)
    assert proc.returncode != 0
    assert ZENOH_CONFIG_ENV in proc.stderr
