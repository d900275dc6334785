"""Kubernetes manifests (deploy/k8s) and docker-compose.yml against their published schemas, offline, and against the
supervisor's process graph and the CLI.

Validators ship their schemas: kubernetes-validate (the Kubernetes OpenAPI schemas per version, strict: unknown
fields fail) and check-jsonschema (the Compose specification's JSON Schema, vendored). No network at test time. No
kustomize binary is here, so the kustomization is rendered the way kustomize would for what it uses (resources,
configMapGenerator from env and files, namespace, labels) and every rendered object is validated.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

import jsonschema
import kubernetes_validate
import pytest
import yaml

from morph_sim.cli import build_parser
from services import envconfig
from services.runconfig import RunConfig
from services.supervisor.graph import CHILD_ENV, process_graph

ROOT = Path(__file__).resolve().parent.parent
K8S = ROOT / "deploy" / "k8s"
KUBE_VERSION = "1.30.0"  # the oldest we claim; the pod-index label the agents read is there from 1.28


def _env_file(path: Path) -> dict[str, str]:
    out = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            k, _, v = line.partition("=")
            out[k.strip()] = v.strip()
    return out


def render() -> list[dict]:
    """The objects `kubectl apply -k deploy/k8s` creates (without kustomize's name hashes)."""
    kust = yaml.safe_load((K8S / "kustomization.yaml").read_text())
    known = {"apiVersion", "kind", "namespace", "labels", "resources", "configMapGenerator"}
    assert set(kust) <= known, f"kustomization uses {set(kust) - known}: teach render() or drop it"
    objs = []
    for res in kust["resources"]:
        objs += [d for d in yaml.safe_load_all((K8S / res).read_text()) if d]
    for gen in kust.get("configMapGenerator", []):
        data = {}
        for env in gen.get("envs", []):
            data.update(_env_file(K8S / env))
        for spec in gen.get("files", []):
            key, _, src = spec.partition("=")
            data[key] = (K8S / src).read_text()
        objs.append({"apiVersion": "v1", "kind": "ConfigMap", "metadata": {"name": gen["name"]}, "data": data})
    for o in objs:
        if o["kind"] != "Namespace":
            o["metadata"]["namespace"] = kust["namespace"]
        for lab in kust.get("labels", []):
            o["metadata"].setdefault("labels", {}).update(lab["pairs"])
    return objs


OBJECTS = render()


def _get(kind: str, name: str) -> dict:
    (obj,) = [o for o in OBJECTS if o["kind"] == kind and o["metadata"]["name"] == name]
    return obj


def _container(obj: dict) -> dict:
    (c,) = obj["spec"]["template"]["spec"]["containers"]
    return c


RUN_ENV = _get("ConfigMap", "morph-run")["data"]
CONFIG = RunConfig.from_env(RUN_ENV)
WORKLOADS = {"sim": _get("Job", "sim"), "monitor": _get("Job", "monitor"), "agent": _get("StatefulSet", "agent")}


# -- schema validation ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("obj", OBJECTS, ids=lambda o: f"{o['kind']}/{o['metadata']['name']}")
def test_every_rendered_object_passes_the_kubernetes_schema_strictly(obj):
    kubernetes_validate.validate(obj, KUBE_VERSION, strict=True)


def test_the_kubernetes_validator_can_fail():
    bad = json.loads(json.dumps(WORKLOADS["agent"]))
    bad["spec"]["replicas"] = "eight"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(bad, KUBE_VERSION, strict=True)
    typo = json.loads(json.dumps(WORKLOADS["sim"]))
    typo["spec"]["template"]["spec"]["containers"][0]["comand"] = ["morph-sim"]
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(typo, KUBE_VERSION, strict=True)


def _compose_schema() -> dict:
    return json.loads((resources.files("check_jsonschema.builtin_schemas.vendor") / "compose-spec.json").read_text())


def test_docker_compose_passes_the_compose_specification_schema():
    doc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    schema = _compose_schema()
    errors = sorted(jsonschema.Draft7Validator(schema).iter_errors(doc), key=str)
    assert not errors, [f"{'/'.join(map(str, e.path))}: {e.message}" for e in errors]
    bad = json.loads(json.dumps(doc))
    bad["services"]["sim"]["restart"] = ["no"]
    bad["services"]["agent"]["deploy"]["replica"] = 3
    assert len(list(jsonschema.Draft7Validator(schema).iter_errors(bad))) >= 2


# -- the process graph and the CLI ----------------------------------------------------------------------------------
def test_the_run_configuration_is_a_valid_runconfig_and_the_fault_schedule_loads():
    from services.faults.schedule import load_schedule

    assert set(RUN_ENV) <= {v.env for v in envconfig.config_variables()}
    assert CONFIG.output_dir == Path("/data/runs") and CONFIG.fault_schedule is None
    path = K8S / "faults.toml"
    schedule = load_schedule(path)
    assert schedule.at and schedule.at[0].spec.loss.percent == 20
    # every pod mounts the schedule where MORPH_FAULT_SCHEDULE would point
    key = next(iter(_get("ConfigMap", "morph-faults")["data"]))
    for obj in WORKLOADS.values():
        mounts = {m["name"]: m["mountPath"] for m in _container(obj)["volumeMounts"]}
        vols = {v["name"]: v for v in obj["spec"]["template"]["spec"]["volumes"]}
        assert vols["faults"]["configMap"]["name"] == "morph-faults"
        assert f"{mounts['faults']}/{key}" == "/etc/morph/faults/schedule.toml"
    assert "MORPH_FAULT_SCHEDULE=/etc/morph/faults/schedule.toml" in path.read_text()


def test_the_workloads_are_the_supervisors_process_graph():
    endpoint = "tcp/zenoh:7447"
    specs = process_graph(CONFIG.model_copy(update={"endpoint": endpoint}), endpoint)
    roles = {s.role for s in specs}
    assert roles == set(WORKLOADS)
    assert WORKLOADS["agent"]["spec"]["replicas"] == sum(s.role == "agent" for s in specs) == CONFIG.n_agents
    for role, obj in WORKLOADS.items():
        c = _container(obj)
        argv = c["command"]
        assert argv[0] == "morph-sim" and c["image"] == "morph-sim:0.1.0"
        try:
            args = build_parser().parse_args(argv[1:])
        except SystemExit as exc:
            raise AssertionError(f"morph-sim rejects {argv[1:]} (exit {exc.code})") from None
        assert args.command == role
        # the role's own flags are the supervisor's when the run uses a router
        spec = next(s for s in specs if s.role == role)
        assert argv[argv.index("--endpoint"):argv.index("--endpoint") + 2] == \
            list(spec.argv[spec.argv.index("--endpoint"):spec.argv.index("--endpoint") + 2])
        env = {e["name"]: e.get("value") for e in c["env"]}
        for name, value in CHILD_ENV.items():
            assert env[name] == value, f"{role}: {name}"
        assert c["envFrom"] == [{"configMapRef": {"name": "morph-run"}}]
        res = c["resources"]
        assert res["requests"]["cpu"] and res["requests"]["memory"] and res["limits"]["memory"]
    # restart policies: the sim never (a new clock would be a new run), the monitor and the agents on failure
    assert WORKLOADS["sim"]["spec"]["template"]["spec"]["restartPolicy"] == "Never"
    assert WORKLOADS["sim"]["spec"]["backoffLimit"] == 0
    assert WORKLOADS["monitor"]["spec"]["template"]["spec"]["restartPolicy"] == "OnFailure"


def test_an_agents_ordinal_is_its_robot_id():
    c = _container(WORKLOADS["agent"])
    (ref,) = [e for e in c["env"] if e["name"] == "MORPH_ID"]
    assert ref["valueFrom"]["fieldRef"]["fieldPath"] == "metadata.labels['apps.kubernetes.io/pod-index']"
    assert envconfig.env_for_flag("--id") == "MORPH_ID"
    import os

    old = os.environ.get("MORPH_ID")
    os.environ["MORPH_ID"] = "5"  # what Kubernetes sets in pod agent-5
    try:
        args = build_parser().parse_args(c["command"][1:])
    finally:
        os.environ.pop("MORPH_ID") if old is None else os.environ.__setitem__("MORPH_ID", old)
    assert args.id == 5 and CONFIG.role_of(5) == "picker" and CONFIG.role_of(0) == "agv"
    sts = WORKLOADS["agent"]["spec"]
    assert sts["podManagementPolicy"] == "Parallel"  # all robots start together; the sim waits for every one
    svc = _get("Service", sts["serviceName"])
    assert svc["spec"]["clusterIP"] == "None" and svc["spec"]["selector"] == sts["selector"]["matchLabels"]


def test_services_and_ports_match_the_commands():
    zenoh = _get("Service", "zenoh")
    router = _get("Deployment", "zenoh-router")
    assert zenoh["spec"]["ports"][0]["port"] == 7447
    assert zenoh["spec"]["selector"] == router["spec"]["selector"]["matchLabels"]
    assert _container(router)["image"] == "eclipse/zenoh:1.10.2"  # the pinned eclipse-zenoh wheel's version
    for obj in WORKLOADS.values():
        assert "tcp/zenoh:7447" in _container(obj)["command"]
    mon = _container(WORKLOADS["monitor"])
    port = int(mon["command"][mon["command"].index("--prometheus-port") + 1])
    assert mon["command"][mon["command"].index("--prometheus-host") + 1] == "0.0.0.0"
    assert mon["ports"][0]["containerPort"] == port
    svc = _get("Service", "monitor")
    assert svc["spec"]["ports"][0]["port"] == port and svc["metadata"]["annotations"]["prometheus.io/port"] == str(port)
    labels = WORKLOADS["monitor"]["spec"]["template"]["metadata"]["labels"]
    assert all(labels.get(k) == v for k, v in svc["spec"]["selector"].items())
    # the records volume is where MORPH_OUTPUT_DIR points
    mounts = {m["name"]: m["mountPath"] for m in mon["volumeMounts"]}
    assert mounts["runs"] == RUN_ENV["MORPH_OUTPUT_DIR"]
    pvc = {v["name"]: v for v in WORKLOADS["monitor"]["spec"]["template"]["spec"]["volumes"]}["runs"]
    assert _get("PersistentVolumeClaim", pvc["persistentVolumeClaim"]["claimName"])
    # the Prometheus config of the monitoring profile scrapes the same name and port
    prom = yaml.safe_load((ROOT / "deploy" / "monitoring" / "prometheus.yml").read_text())
    assert prom["scrape_configs"][0]["static_configs"][0]["targets"] == [f"{svc['metadata']['name']}:{port}"]
