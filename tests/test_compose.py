"""docker-compose.yml without a Docker engine: it parses, its commands are real CLI invocations, its process
graph is the supervisor's, its environment is the RunConfig's, and the services honour its healthcheck and stop signal.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _compose import defaults_of, interpolate, load

from morph_sim import environment
from morph_sim.cli import build_parser
from services import envconfig
from services.runconfig import RunConfig, config_from_args
from services.supervisor.graph import process_graph

from _procs import FEW_ROBOTS

ROOT = Path(__file__).resolve().parent.parent
COMPOSE = load(ROOT / "docker-compose.yml")
THIRD_PARTY = {"prometheus", "grafana"}  # the "monitoring" profile's images, checked in tests/test_monitoring.py


def enabled(compose: dict, environ: dict[str, str]) -> dict:
    """The run's services `docker compose up` starts under ``environ``: those without profiles and those in one of
    COMPOSE_PROFILES (Prometheus and Grafana aside)."""
    active = {p.strip() for p in environ.get("COMPOSE_PROFILES", "").split(",") if p.strip()}
    return {name: s for name, s in compose["services"].items()
            if name not in THIRD_PARTY and (not s.get("profiles") or active & set(s["profiles"]))}


# The run itself as `docker compose up` starts it with an empty environment.
SERVICES = enabled(COMPOSE, {})
DEFAULTS = interpolate(COMPOSE, {})  # what `docker compose up` uses with an empty environment
AGENTS = sorted((n for n in SERVICES if n.startswith("agent-")), key=lambda n: int(n.split("-")[1]))
ROLE_RESTART = {"never": "no", "on-failure": "on-failure"}
PROMETHEUS_FLAG_EXISTS = any(v.flag == "--prometheus-port" for v in environment.command_variables("monitor"))


ROLES = ["sim", "monitor", "agent", "air"]


def role_of(service: dict) -> str:
    return service["command"][1]


def header_commands() -> list[str]:
    """The command lines the compose file's header shows."""
    text = (ROOT / "docker-compose.yml").read_text()
    return [line[1:].split("#")[0].strip() for line in text.splitlines()
            if line.startswith("#   ") and ("docker compose" in line or "morph-sim credentials" in line)]


def _seconds(text: str) -> float:
    m = re.fullmatch(r"(\d+(?:\.\d+)?)(ms|s|m)", str(text))
    assert m, f"duration {text!r} is not like 10s"
    return float(m.group(1)) * {"ms": 0.001, "s": 1.0, "m": 60.0}[m.group(2)]


def _argv(service: str, environ: dict[str, str] | None = None) -> list[str]:
    return interpolate(SERVICES[service]["command"], environ or {})


def _live_monitor_argv(where: str) -> list[str]:
    """The compose monitor's arguments for a live test on this machine: connected to ``where``, its Prometheus
    exporter on a free loopback port (compose's 9464 on every interface may be taken by another test's monitor)."""
    from services.bus.zenoh_bus import free_port

    argv = _without_prometheus(_argv("monitor", {"MORPH_PROMETHEUS_PORT": str(free_port())}))[1:]
    return [where if c == "tcp/sim:7447" else "127.0.0.1" if c == "0.0.0.0" else c for c in argv]


def _parse(argv: list[str]):
    assert argv[0] == "morph-sim", f"command {argv} does not start with morph-sim"
    try:
        return build_parser().parse_args(argv[1:])
    except SystemExit as exc:
        raise AssertionError(f"morph-sim rejects {argv[1:]} (exit {exc.code})") from None


def _without_prometheus(argv: list[str]) -> list[str]:
    """Until the monitor has --prometheus-port, check the rest of its command line."""
    if PROMETHEUS_FLAG_EXISTS or "--prometheus-port" not in argv:
        return argv
    i = argv.index("--prometheus-port")
    return argv[:i] + argv[i + 2:]


# -- Compose's interpolation ------------------------------------------------------------------------------------------
def test_interpolation_follows_compose():
    assert interpolate("${A:-x}/${B-y}/${C}/$$D", {"A": "", "B": ""}) == "x///$D"
    assert defaults_of("${A:-1}:${B}") == [("A", "1"), ("B", None)]


# -- structure ----------------------------------------------------------------------------------------------------
def test_services_are_the_sim_the_monitor_and_one_service_per_robot():
    assert set(SERVICES) == {"sim", "monitor", *(f"agent-{n}" for n in range(8))}
    assert len(AGENTS) == RunConfig(run_id="x").n_agents == 8  # the tiny scale's 5 AGVs + 3 pickers
    version = re.search(r'^version = "([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M).group(1)
    for name, service in SERVICES.items():
        assert service["image"] == f"morph-sim:{version}" and service["build"] == ".", name  # one image, this build
        assert service["init"] is True, f"{name}: init forwards signals and reaps children"
        assert "deploy" not in service, f"{name}: one container per service (its credentials name one process)"
    for name in AGENTS:
        assert "ports" not in SERVICES[name] and "container_name" not in SERVICES[name]


@pytest.mark.parametrize("name", ["sim", "monitor", "agent-0", "agent-7"])
def test_every_command_is_a_real_cli_invocation(name):
    argv = _without_prometheus(_argv(name))
    args = _parse(argv)
    assert args.command == role_of(SERVICES[name])
    env = DEFAULTS["services"][name]["environment"]
    config = config_from_args(args, environ=env)  # validates the whole config (ValueError names a bad field)
    assert config.run_id == "compose" and config.output_dir == Path("/data/runs")
    if args.command == "agent":
        assert args.id == int(name.split("-")[1])  # robot N, whose credentials agent-N.json5 are


def test_the_monitor_serves_prometheus_on_the_published_port():
    argv = _argv("monitor", {"MORPH_PROMETHEUS_PORT": "9500"})
    args = _parse(argv)
    assert int(args.prometheus_port) == 9500
    assert interpolate(SERVICES["monitor"]["ports"], {"MORPH_PROMETHEUS_PORT": "9500"}) == ["127.0.0.1:9500:9500"]


def test_the_prometheus_port_is_published_with_the_flags_variable():
    ports = SERVICES["monitor"]["ports"]
    assert defaults_of(ports[0]) == [("PUBLISH_HOST", "127.0.0.1")] + [("MORPH_PROMETHEUS_PORT", "9464")] * 2
    argv = SERVICES["monitor"]["command"]
    assert argv[argv.index("--prometheus-port") + 1] == "${MORPH_PROMETHEUS_PORT:-9464}"
    assert envconfig.env_for_flag("--prometheus-port") == "MORPH_PROMETHEUS_PORT"


# -- the same process graph as `morph-sim up` ---------------------------------------------------------------------
SMALL = {"MORPH_SCALE": "small", "COMPOSE_PROFILES": "small", "MORPH_POLICY": "constant", "MORPH_P": "0.5",
         "MORPH_SEED": "7", "MORPH_RUN_ID": "exp-1"}


# a rate-limited radio: its air process is the supervisor's too
CONGESTED = {"MORPH_NETWORK": "congested", "COMPOSE_PROFILES": "air"}


@pytest.mark.parametrize("role", ROLES)
@pytest.mark.parametrize("host_env", [{}, SMALL, CONGESTED], ids=["defaults", "small", "congested"])
def test_the_compose_graph_is_the_supervisors(host_env, role):
    compose = interpolate(COMPOSE, host_env)
    services = enabled(compose, host_env)
    env = {k: v for k, v in services["sim"]["environment"].items() if k != "ZENOH_CONFIG"}
    config = RunConfig.from_env(env)
    specs = process_graph(config, "tcp/sim:7447")
    assert {spec.name for spec in specs} == set(services)
    for spec in (s for s in specs if s.role == role):
        service = services[spec.name]
        mine_env = {k: v for k, v in service["environment"].items() if k != "ZENOH_CONFIG"}
        assert mine_env == env, f"{spec.name}: every service sees the same run configuration"
        for name, value in spec.env.items():  # the supervisor's child environment (Zenoh runtime, BLAS threads)
            assert service["environment"].get(name) == value, f"{spec.name}: {name} differs from the supervisor's"
        assert service.get("restart", "no") == ROLE_RESTART[spec.restart], spec.name
        theirs = _parse(list(spec.argv))
        ours = _parse(_without_prometheus(service["command"]))
        assert ours.command == theirs.command == role
        mine = config_from_args(ours, environ=mine_env).model_dump()
        sup = config_from_args(theirs, environ={}).model_dump()
        # Where the Zenoh endpoint is differs by design (container DNS name, all interfaces); the rest is equal.
        for field in ("endpoint", "listen"):
            mine.pop(field), sup.pop(field)
        assert mine == sup, f"{spec.name}: compose and supervisor configure the run differently"
        if role == "sim":
            assert ours.cfg_listen == "tcp/0.0.0.0:7447" and theirs.cfg_listen == "tcp/sim:7447"
        else:
            assert ours.cfg_endpoint == theirs.cfg_endpoint == "tcp/sim:7447"
        if role == "agent":
            assert ours.id == theirs.id == spec.agent


def _agent_containers(compose: dict, environ: dict[str, str]) -> int:
    """How many `morph-sim agent` containers `docker compose up` starts under ``environ``."""
    services = enabled(interpolate(compose, environ), environ)
    return sum(int((s.get("deploy") or {}).get("replicas", 1)) for s in services.values() if role_of(s) == "agent")


def test_the_headers_scaling_example_starts_the_scales_fleet():
    """Each `docker compose up` line of the header, with its variables, through the file's own interpolation and
    profiles: as many robot containers as the run's fleet."""
    examples = [c for c in header_commands() if "docker compose up" in c]
    assert any("MORPH_SCALE=small" in c for c in examples)
    for line in examples:
        environ = dict(x.split("=", 1) for x in line.split("docker compose")[0].split())
        sim_env = interpolate(COMPOSE, environ)["services"]["sim"]["environment"]
        fleet = RunConfig.from_env({k: v for k, v in sim_env.items() if k != "ZENOH_CONFIG"}).n_agents
        assert _agent_containers(COMPOSE, environ) == fleet, f"{line!r}: not the fleet of {fleet} robots"


@pytest.mark.parametrize("scale", ["tiny", "small", "medium", "large", "extralarge"])
def test_the_scales_profile_starts_exactly_its_fleet(scale):
    environ = {"MORPH_SCALE": scale, "COMPOSE_PROFILES": scale}
    services = enabled(interpolate(COMPOSE, environ), environ)
    ids = sorted(_parse(s["command"]).id for s in services.values() if role_of(s) == "agent")
    assert ids == list(range(RunConfig(run_id="x", scale=scale).n_agents))


# -- secure by default, published on loopback ---------------------------------------------------------------------
def test_ports_are_published_on_loopback_unless_told():
    for environ, host in (({}, "127.0.0.1"), ({"PUBLISH_HOST": "0.0.0.0"}, "0.0.0.0")):
        compose = interpolate(COMPOSE, environ)
        published = [p for s in compose["services"].values() for p in s.get("ports", [])]
        assert published and all(p.startswith(f"{host}:") and p.count(":") == 2 for p in published), published
    assert DEFAULTS["services"]["sim"]["ports"] == ["127.0.0.1:7447:7447"]


def _credentials(tmp_path: Path, here: bool = False) -> tuple[Path, str]:
    """The header's `morph-sim credentials` command, run by the real CLI with its output in ``tmp_path`` (``here``:
    mounted where it is written, for processes on this machine)."""
    import contextlib
    import io
    import shlex

    from morph_sim.cli import main as cli_main

    (line,) = [c for c in header_commands() if c.startswith("morph-sim credentials")]
    argv = shlex.split(line)
    out = tmp_path / "credentials"
    argv[argv.index("--out") + 1] = str(out)
    if here:
        argv[argv.index("--mounted-at") + 1] = str(out)
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli_main(argv[1:]) == 0
    return out, argv[argv.index("--mounted-at") + 1]


def test_every_container_gets_only_its_own_credentials_as_a_secret(tmp_path):
    out, mounted_at = _credentials(tmp_path)
    sources = {name: s["file"] for name, s in DEFAULTS["secrets"].items()}
    for name, service in DEFAULTS["services"].items():
        if name in THIRD_PARTY:
            continue
        secrets = {x["source"]: x["target"] for x in service["secrets"]}
        config = service["environment"]["ZENOH_CONFIG"]
        assert config in secrets.values(), f"{name}: ZENOH_CONFIG is not one of its secrets"
        for source, target in secrets.items():
            assert Path(target).parent == Path(mounted_at), f"{name}: {target} is not where the credentials are"
            assert Path(sources[source]).name == Path(target).name
            assert Path(sources[source]).parent == Path("./credentials")
        expected = {"sim": {"endpoint.json5", "passwords.txt"}, "monitor": {"monitor.json5"}}.get(
            name, {f"{name}.json5"})
        assert {Path(t).name for t in secrets.values()} == expected, name
        if name in SERVICES:
            assert all((out / Path(t).name).is_file() for t in secrets.values()), f"{name}: credentials not written"
    endpoint = json.loads((out / "endpoint.json5").read_text())
    sim_secrets = {x["source"]: x["target"] for x in DEFAULTS["services"]["sim"]["secrets"]}
    assert endpoint["transport"]["auth"]["usrpwd"]["dictionary_file"] == sim_secrets["passwords"]
    assert endpoint["access_control"]["default_permission"] == "deny"
    assert (out / "operator.json5").is_file() and "operator" not in DEFAULTS["secrets"], "the operator keeps theirs"


def test_grafanas_admin_password_comes_from_the_environment():
    grafana = COMPOSE["services"]["grafana"]
    assert defaults_of(grafana["environment"]["GF_SECURITY_ADMIN_PASSWORD"]) == [("GRAFANA_ADMIN_PASSWORD", "")]
    assert interpolate(grafana, {"GRAFANA_ADMIN_PASSWORD": "s3cret"})["environment"][
        "GF_SECURITY_ADMIN_PASSWORD"] == "s3cret"
    # without a password the container stops before Grafana could create admin/admin; with one it goes on to the
    # image's entrypoint (absent here: exit 127)
    entrypoint = interpolate(grafana, {})["entrypoint"]
    assert entrypoint[:2] == ["sh", "-c"]
    for password, code in (("", 1), ("s3cret", 127)):
        run = subprocess.run(entrypoint, env={"PATH": os.environ["PATH"], "GF_SECURITY_ADMIN_PASSWORD": password},
                             capture_output=True, text=True, timeout=10)
        assert run.returncode == code, run.stderr
        assert ("GRAFANA_ADMIN_PASSWORD" in run.stderr) == (code == 1)


# -- environment ⇄ flags ⇄ RunConfig ------------------------------------------------------------------------------
def test_environment_variables_are_the_cli_flags_with_the_same_defaults():
    env = COMPOSE["x-morph-env"]
    fixed = {"MORPH_RUN_ID": "compose", "MORPH_OUTPUT_DIR": "/data/runs"}  # container-wide choices (documented)
    by_env = {v.env: v for v in envconfig.config_variables()}
    morph = {k: v for k, v in env.items() if k.startswith("MORPH_")}
    expected = set(by_env) - {"MORPH_ENDPOINT", "MORPH_LISTEN"}  # set per service by its command line
    assert set(morph) == expected, (
        f"compose env and RunConfig differ: missing {sorted(expected - set(morph))}, "
        f"extra {sorted(set(morph) - expected)}")
    for name, raw in morph.items():
        if name == "MORPH_OUTPUT_DIR":
            assert raw == fixed[name]
            continue
        assert defaults_of(raw) == [(name, defaults_of(raw)[0][1])], f"{name} must interpolate ${{{name}:-…}}"
        default = defaults_of(raw)[0][1]
        if name in fixed:
            assert default == fixed[name]
        else:
            assert default == ("" if by_env[name].default is None else by_env[name].default), name
        assert envconfig.flag_for_env(name) == by_env[name].flag
    # Every variable reaches the model under the flag's name: the compose env means the same as these flags.
    override = {"MORPH_SCALE": "small", "MORPH_PHASE_TIMEOUT": "2.5", "MORPH_AGVS": "4", "MORPH_ABLATION": ""}
    container_env = interpolate(env, override)
    from_env = RunConfig.from_env(container_env)
    argv = environment.env_to_argv("sim", container_env)
    from_flags = config_from_args(build_parser().parse_args(["sim", *argv]), environ={})
    assert from_env == from_flags
    assert (from_env.scale, from_env.phase_timeout, from_env.agvs, from_env.ablation) == ("small", 2.5, 4, None)
    with pytest.raises(ValueError, match="MORPH_NOT_A_FLAG"):
        environment.env_to_argv("sim", {"MORPH_NOT_A_FLAG": "1"})
    with pytest.raises(ValueError, match="scale"):
        RunConfig.from_env(interpolate(env, {"MORPH_SCALE": "huge"}))


def test_per_command_options_follow_their_variables():
    import argparse

    from services.runconfig import add_config_arguments

    parser = argparse.ArgumentParser()
    parser.add_argument("--max-rate", type=float, default=10.0)
    parser.add_argument("--no-wait-monitor", action="store_true")
    parser.add_argument("--log-level", choices=["INFO", "WARNING"], default="WARNING")
    add_config_arguments(parser)
    envconfig.apply_env_defaults(parser, {"MORPH_MAX_RATE": "2.5", "MORPH_NO_WAIT_MONITOR": "true",
                                          "MORPH_LOG_LEVEL": "INFO", "MORPH_SCALE": "small"})
    args = parser.parse_args([])
    assert (args.max_rate, args.no_wait_monitor, args.log_level) == (2.5, True, "INFO")
    assert args.cfg_scale is None  # RunConfig fields stay with config_from_args (flags, then env, then defaults)
    assert config_from_args(args, environ={"MORPH_SCALE": "small"}).scale == "small"
    assert parser.parse_args(["--max-rate", "4"]).max_rate == 4.0  # a flag beats its variable
    with pytest.raises(ValueError, match="MORPH_MAX_RATE"):
        envconfig.apply_env_defaults(parser, {"MORPH_MAX_RATE": "fast"})
    with pytest.raises(ValueError, match="MORPH_LOG_LEVEL"):
        envconfig.apply_env_defaults(parser, {"MORPH_LOG_LEVEL": "LOUD"})
    table = environment.markdown_table("agent")  # the real command: every option, RunConfig ones with their defaults
    assert "| `MORPH_SCALE` | `--scale` | `tiny` |" in table and "`MORPH_ENDPOINT`" in table


# -- start order, health, stop ------------------------------------------------------------------------------------
def test_agents_and_monitor_start_after_the_endpoint_is_healthy():
    assert "healthcheck" in SERVICES["sim"]
    for name in ("monitor", *AGENTS):
        assert SERVICES[name]["depends_on"] == {"sim": {"condition": "service_healthy"}}
    for name in ("sim", "monitor"):
        check = SERVICES[name]["healthcheck"]
        assert check["test"][0] == "CMD" and check["test"][1] == "python"  # exec form: the image has no shell tools
        assert _seconds(check["timeout"]) < _seconds(check["interval"])


def _run_check(test: list[str], port: int) -> int:
    cmd = [sys.executable if c == "python" else c.replace("7447", str(port)) for c in test[1:]]
    return subprocess.run(cmd, timeout=10, capture_output=True).returncode


def _wait_port(port: int, timeout: float) -> None:
    import socket

    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), 0.5).close()
            return
        except OSError:
            assert time.monotonic() < deadline, f"nothing listens on {port}"
            time.sleep(0.1)


def _service_env(name: str, env: dict[str, str], credentials: Path) -> dict[str, str]:
    """``env`` with the service's ZENOH_CONFIG pointing at its file among ``credentials`` (where the container would
    have it mounted)."""
    return {**env, "ZENOH_CONFIG": str(credentials / Path(SERVICES[name]["environment"]["ZENOH_CONFIG"]).name)}


async def _tokens(where: str, run: str, expected: set, timeout: float, procs: list[subprocess.Popen],
                  operator: Path) -> set:
    """The ids whose liveliness tokens are up, once ``expected`` are (or the timeout passes / a process exits)."""
    import zenoh

    from schemas.keys import RunKeys
    from services.bus.zenoh_bus import ZenohBus, zenoh_config

    keys = RunKeys(run)
    config = zenoh_config(connect=where, mode="client", connect_timeout=5.0,
                          base=zenoh.Config.from_file(str(operator)))
    bus = await ZenohBus.open("compose-test", connect=where, mode="client", config=config, connect_timeout=5.0)
    try:
        deadline = time.monotonic() + timeout
        while True:
            present = {keys.alive_id(k) for k in await bus.alive(keys.alive_all)}
            dead = [p for p in procs if p.poll() is not None]
            if expected <= present or dead or time.monotonic() > deadline:
                for p in dead:
                    raise AssertionError(f"{p.args[3]} exited early: {p.stdout.read().decode()[-2000:]}")
                return present
            await asyncio.sleep(0.2)
    finally:
        await bus.close()


def _stop(proc: subprocess.Popen, grace: float) -> float:
    start = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
        raise AssertionError(f"{proc.args[3]} ignored SIGTERM for {grace} s (compose would SIGKILL it)") from None
    return time.monotonic() - start


def test_the_services_pass_the_healthcheck_and_stop_within_the_grace_period(tmp_path):
    """Live: a sim, an agent and a monitor process (the compose commands, on 127.0.0.1) under SIGTERM."""
    from services.bus.zenoh_bus import free_port

    port = free_port()
    grace = min(_seconds(SERVICES[n]["stop_grace_period"]) for n in SERVICES)
    env = {**os.environ, **interpolate(COMPOSE["x-morph-env"], {}), "MORPH_OUTPUT_DIR": str(tmp_path)}
    credentials, _ = _credentials(tmp_path, here=True)
    cli = [sys.executable, "-m", "morph_sim.cli"]
    assert _run_check(SERVICES["sim"]["healthcheck"]["test"], port) != 0, "healthcheck passes with nothing listening"
    procs: list[subprocess.Popen] = []
    try:
        sim_argv = [c.replace("tcp/0.0.0.0:7447", f"tcp/127.0.0.1:{port}") for c in _argv("sim")[1:]]
        procs.append(subprocess.Popen(cli + sim_argv, env=_service_env("sim", env, credentials),
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT))
        _wait_port(port, 30.0)
        assert _run_check(SERVICES["sim"]["healthcheck"]["test"], port) == 0
        where = f"tcp/127.0.0.1:{port}"
        agent_argv = [c.replace("tcp/sim:7447", where) for c in _argv("agent-0")[1:]]
        monitor_argv = _live_monitor_argv(where)
        procs.append(subprocess.Popen(cli + agent_argv, env=_service_env("agent-0", env, credentials),
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT))
        procs.append(subprocess.Popen(cli + monitor_argv, env=_service_env("monitor", env, credentials),
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT))
        # A service declares its liveliness token after installing its signal handlers: once all three tokens are
        # up, SIGTERM tests the handlers, not Python's default (which would just kill the process).
        expected = {"sim", "monitor", 0}
        present = asyncio.run(_tokens(where, env["MORPH_RUN_ID"], expected, 30.0, procs,
                                      credentials / "operator.json5"))
        assert expected <= present, f"services did not come up: tokens {present}"
        for proc in reversed(procs):
            took = _stop(proc, grace)
            assert took < grace
            assert proc.returncode >= 0, f"{proc.args[3]} died of signal {-proc.returncode} instead of stopping"
    finally:
        for proc in procs:
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)



def test_stop_grace_period_covers_the_services_own_shutdown_bound():
    from services.bus.zenoh_bus import CLOSE_TIMEOUT
    from services.supervisor.launcher import SHUTDOWN_BOUND

    for name, service in SERVICES.items():
        assert _seconds(service["stop_grace_period"]) >= max(SHUTDOWN_BOUND, CLOSE_TIMEOUT) + 2, name


def test_run_records_go_to_a_named_volume():
    assert "runs" in COMPOSE["volumes"]
    for name in ("sim", "monitor"):
        assert "runs:/data/runs" in SERVICES[name]["volumes"]
    assert COMPOSE["x-morph-env"]["MORPH_OUTPUT_DIR"] == "/data/runs"
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert 'VOLUME ["/data/runs"]' in dockerfile and "chown morph:morph /data/runs" in dockerfile


def test_the_deploy_guide_lists_every_variable_and_sample():
    doc = (ROOT / "docs" / "deploy.md").read_text()
    for v in envconfig.config_variables():
        assert f"`{v.env}` | `{v.flag}`" in doc, f"docs/deploy.md does not list {v.env}"
    for name in ("router.json5", "credentials.txt", "client-agent-0.json5", "client-operator.json5"):
        assert (ROOT / "deploy" / "zenoh" / name).exists() and name in doc
    assert "eclipse/zenoh:1.10.2" in doc  # the router image matching the pinned eclipse-zenoh wheel
    pin = re.search(r'"eclipse-zenoh==([\d.]+)"', (ROOT / "pyproject.toml").read_text())
    assert pin and pin.group(1) == "1.10.2"


def test_a_compose_shaped_run_completes_secured_by_its_credentials(tmp_path):
    """Live, on 127.0.0.1: the compose commands (sim listening, monitor, the robots' services), each process with
    only its own credentials file as its container would have it, run a short lock-step run to the end; a process
    without credentials cannot join it. The fleet is three robots, set with compose's own MORPH_AGVS/MORPH_PICKERS
    (tests/_procs.py FEW_ROBOTS): what is checked is each service's credentials, the same for every robot, and every
    agent process costs its start (the graph of all 8 is compared with the supervisor's above)."""
    from services.bus.zenoh_bus import free_port

    port = free_port()
    where = f"tcp/127.0.0.1:{port}"
    agvs, pickers = FEW_ROBOTS[FEW_ROBOTS.index("--agvs") + 1], FEW_ROBOTS[FEW_ROBOTS.index("--pickers") + 1]
    fleet = AGENTS[:int(agvs) + int(pickers)]
    env = {**os.environ, **interpolate(COMPOSE["x-morph-env"], {}), "MORPH_OUTPUT_DIR": str(tmp_path),
           "MORPH_STEPS": "10", "MORPH_READY_TIMEOUT": "60", "MORPH_AGVS": agvs, "MORPH_PICKERS": pickers}
    credentials, _ = _credentials(tmp_path, here=True)
    cli = [sys.executable, "-m", "morph_sim.cli"]
    procs: list[subprocess.Popen] = []
    try:
        sim_argv = [c.replace("tcp/0.0.0.0:7447", where) for c in _argv("sim")[1:]]
        sim = subprocess.Popen(cli + sim_argv, env=_service_env("sim", env, credentials), stdout=subprocess.PIPE,
                               stderr=subprocess.STDOUT, text=True)
        procs.append(sim)
        _wait_port(port, 30.0)
        # it tries for its whole connect timeout (10 s) before it gives up: meanwhile the run goes on
        stranger = subprocess.Popen(cli + [c.replace("tcp/sim:7447", where) for c in _argv("agent-0")[1:]],
                                    env={k: v for k, v in env.items() if k != "ZENOH_CONFIG"},
                                    stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        procs.append(stranger)
        monitor_argv = _live_monitor_argv(where)
        procs.append(subprocess.Popen(cli + monitor_argv, env=_service_env("monitor", env, credentials),
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        agents = []
        for name in fleet:
            agent_argv = [c.replace("tcp/sim:7447", where) for c in _argv(name)[1:]]
            agents.append(subprocess.Popen(cli + agent_argv, env=_service_env(name, env, credentials),
                                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True))
        procs += agents
        out, _ = sim.communicate(timeout=180)
        assert sim.returncode == 0, out[-3000:]
        assert "open" not in out, "the sim hosted an open endpoint"
        ids = []
        for proc in agents:
            text, _ = proc.communicate(timeout=30)
            assert proc.returncode == 0, text[-2000:]
            ids.append(json.loads(text.strip().splitlines()[-1])["agent"])
        assert sorted(ids) == list(range(len(fleet)))
        _, refused = stranger.communicate(timeout=60)
        assert stranger.returncode != 0, "an agent without credentials joined the run"
        assert f"cannot reach the Zenoh endpoint {where}" in refused, refused[-2000:]
    finally:
        for proc in procs:
            if proc.poll() is None:
                os.kill(proc.pid, signal.SIGKILL)
                proc.wait(timeout=5)
