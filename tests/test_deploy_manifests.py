"""Kubernetes manifests (deploy/k8s) and docker-compose.yml against their published schemas, offline, and against the
supervisor's process graph, the CLI and the restricted Pod Security Standard.

Validators ship their schemas: kubernetes-validate (the Kubernetes OpenAPI schemas per version, strict: unknown
fields fail) and check-jsonschema (the Compose specification's JSON Schema, vendored). No network at test time. No
kustomize binary is here, so the kustomization is rendered the way kustomize would for what it uses (resources,
configMapGenerator and secretGenerator from env and files, namespace, labels) and every rendered object is
validated. The Secrets come from the credentials the documented `morph-sim credentials` command writes.
"""

from __future__ import annotations

import base64
import contextlib
import io
import json
import re
import shlex
import shutil
import tempfile
from importlib import resources
from pathlib import Path

import jsonschema
import kubernetes_validate
import pytest
import yaml

from morph_sim.cli import build_parser, main as cli_main
from services import envconfig
from services.runconfig import RunConfig
from services.supervisor.graph import CHILD_ENV, process_graph

ROOT = Path(__file__).resolve().parent.parent
K8S = ROOT / "deploy" / "k8s"
KUBE_VERSION = "1.30.0"  # the oldest we claim
UID = 10001  # the image's morph user and group (Dockerfile)


def _env_file(path: Path) -> dict[str, str]:
    out = {}
    for line in path.read_text().splitlines():
        if line.strip() and not line.lstrip().startswith("#"):
            k, _, v = line.partition("=")
            out[k.strip()] = v.strip()
    return out


def render(directory: Path) -> list[dict]:
    """The objects `kubectl apply -k <directory>` creates (without kustomize's name hashes)."""
    kust = yaml.safe_load((directory / "kustomization.yaml").read_text())
    known = {"apiVersion", "kind", "namespace", "labels", "resources", "configMapGenerator", "secretGenerator",
             "components"}
    assert set(kust) <= known, f"kustomization uses {set(kust) - known}: teach render() or drop it"
    objs = []
    for res in kust["resources"]:
        objs += [d for d in yaml.safe_load_all((directory / res).read_text()) if d]
    for component in kust.get("components", []):  # a Component adds its resources to the kustomization's
        comp = yaml.safe_load((directory / component / "kustomization.yaml").read_text())
        assert comp["kind"] == "Component" and set(comp) <= {"apiVersion", "kind", "resources"}, component
        for res in comp["resources"]:
            objs += [d for d in yaml.safe_load_all((directory / component / res).read_text()) if d]

    def files(gen: dict) -> dict[str, str]:
        data = {}
        for env in gen.get("envs", []):
            data.update(_env_file(directory / env))
        for spec in gen.get("files", []):
            key, _, src = spec.rpartition("=") if "=" in spec else (Path(spec).name, "", spec)
            data[key] = (directory / src).read_text()
        return data

    for gen in kust.get("configMapGenerator", []):
        objs.append({"apiVersion": "v1", "kind": "ConfigMap", "metadata": {"name": gen["name"]}, "data": files(gen)})
    for gen in kust.get("secretGenerator", []):
        data = {k: base64.b64encode(v.encode()).decode() for k, v in files(gen).items()}
        objs.append({"apiVersion": "v1", "kind": "Secret", "metadata": {"name": gen["name"]}, "type": "Opaque",
                     "data": data})
    for o in objs:
        if o["kind"] != "Namespace":
            o["metadata"]["namespace"] = kust["namespace"]
        for lab in kust.get("labels", []):
            o["metadata"].setdefault("labels", {}).update(lab["pairs"])
    return objs


def credentials_command() -> list[str]:
    """The `morph-sim credentials` command the kustomization's header tells the operator to run."""
    text = (K8S / "kustomization.yaml").read_text()
    (line,) = [x.lstrip("# ").strip() for x in text.splitlines() if x.lstrip("# ").startswith("morph-sim credentials")]
    argv = shlex.split(line)
    assert argv[:2] == ["morph-sim", "credentials"], line
    return argv


def _with_credentials(into: Path) -> Path:
    """deploy/k8s copied to ``into``, with the credentials the documented command writes, run by the real CLI."""
    shutil.copytree(K8S, into / "k8s", ignore=shutil.ignore_patterns("credentials"))
    argv = credentials_command()
    out = argv.index("--out") + 1
    assert Path(argv[out]) == Path("deploy/k8s/credentials"), "the kustomization reads credentials/ beside it"
    argv[out] = str(into / "k8s" / "credentials")
    with contextlib.redirect_stdout(io.StringIO()):
        assert cli_main(argv[1:]) == 0
    return into / "k8s"


_RENDERED = tempfile.TemporaryDirectory(prefix="k8s-render-")
RENDERED = _with_credentials(Path(_RENDERED.name))
OBJECTS = render(RENDERED)
RECORDS = render(K8S / "records")


def _get(kind: str, name: str, objects=None) -> dict:
    (obj,) = [o for o in (OBJECTS if objects is None else objects)
              if o["kind"] == kind and o["metadata"]["name"] == name]
    return obj


def _container(obj: dict) -> dict:
    (c,) = obj["spec"]["template"]["spec"]["containers"]
    return c


RUN_ENV = _get("ConfigMap", "morph-run")["data"]
CONFIG = RunConfig.from_env(RUN_ENV)
AGENTS = sorted((o for o in OBJECTS if o["kind"] == "Job" and o["metadata"]["name"].startswith("agent-")),
                key=lambda o: int(o["metadata"]["name"].split("-")[1]))
WORKLOADS = {"sim": _get("Job", "sim"), "monitor": _get("Job", "monitor"), "agent": AGENTS[0]}
POD_KINDS = {"Job", "Deployment", "StatefulSet", "DaemonSet", "ReplicaSet", "CronJob", "Pod"}


def pod_templates(objects) -> list[tuple[str, dict]]:
    out = []
    for o in objects:
        if o["kind"] in POD_KINDS:
            spec = o["spec"]
            if o["kind"] == "CronJob":
                spec = spec["jobTemplate"]["spec"]
            out.append((f"{o['kind']}/{o['metadata']['name']}",
                        o["spec"] if o["kind"] == "Pod" else spec["template"]["spec"]))
    return out


# -- schema validation ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("obj", OBJECTS + RECORDS, ids=lambda o: f"{o['kind']}/{o['metadata']['name']}")
def test_every_rendered_object_passes_the_kubernetes_schema_strictly(obj):
    kubernetes_validate.validate(obj, KUBE_VERSION, strict=True)


def test_the_kubernetes_validator_can_fail():
    bad = json.loads(json.dumps(WORKLOADS["agent"]))
    bad["spec"]["backoffLimit"] = "six"
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(bad, KUBE_VERSION, strict=True)
    typo = json.loads(json.dumps(WORKLOADS["sim"]))
    typo["spec"]["template"]["spec"]["containers"][0]["comand"] = ["morph-sim"]
    with pytest.raises(kubernetes_validate.ValidationError):
        kubernetes_validate.validate(typo, KUBE_VERSION, strict=True)


# -- the restricted Pod Security Standard ------------------------------------------------------------------------------
RESTRICTED_VOLUMES = {"configMap", "csi", "downwardAPI", "emptyDir", "ephemeral", "persistentVolumeClaim",
                      "projected", "secret"}
SAFE_SYSCTLS = {"kernel.shm_rmid_forced", "net.ipv4.ip_local_port_range", "net.ipv4.ip_unprivileged_port_start",
                "net.ipv4.tcp_syncookies", "net.ipv4.ping_group_range", "net.ipv4.ip_local_reserved_ports",
                "net.ipv4.tcp_keepalive_time", "net.ipv4.tcp_fin_timeout", "net.ipv4.tcp_keepalive_intvl",
                "net.ipv4.tcp_keepalive_probes"}
SELINUX_TYPES = {"", "container_t", "container_init_t", "container_kvm_t", "container_engine_t"}


def restricted_violations(spec: dict) -> list[str]:
    """What in a pod spec the restricted Pod Security Standard (1.30, baseline included) refuses, plus this
    deployment's own rule: a read-only root filesystem in every container."""
    out = []
    pod = spec.get("securityContext") or {}
    for field in ("hostNetwork", "hostPID", "hostIPC"):
        if spec.get(field):
            out.append(f"{field} is set")
    if (pod.get("windowsOptions") or {}).get("hostProcess"):
        out.append("a Windows host process")
    for vol in spec.get("volumes", []):
        kind = next(k for k in vol if k != "name")
        if kind not in RESTRICTED_VOLUMES:
            out.append(f"volume {vol['name']} is a {kind}")
    for sysctl in pod.get("sysctls", []):
        if sysctl["name"] not in SAFE_SYSCTLS:
            out.append(f"unsafe sysctl {sysctl['name']}")
    if pod.get("runAsUser") == 0:
        out.append("the pod runs as uid 0")
    selinux = pod.get("seLinuxOptions") or {}
    if selinux.get("type", "") not in SELINUX_TYPES or selinux.get("user") or selinux.get("role"):
        out.append("pod seLinuxOptions")
    containers = [*spec.get("initContainers", []), *spec.get("containers", []), *spec.get("ephemeralContainers", [])]
    for c in containers:
        sc = c.get("securityContext") or {}
        name = c["name"]
        if sc.get("privileged"):
            out.append(f"{name}: privileged")
        if sc.get("allowPrivilegeEscalation") is not False:
            out.append(f"{name}: allowPrivilegeEscalation is not false")
        caps = sc.get("capabilities") or {}
        if "ALL" not in caps.get("drop", []):
            out.append(f"{name}: capabilities do not drop ALL")
        if set(caps.get("add", [])) - {"NET_BIND_SERVICE"}:
            out.append(f"{name}: adds capabilities {sorted(set(caps['add']) - {'NET_BIND_SERVICE'})}")
        if sc.get("runAsNonRoot", pod.get("runAsNonRoot")) is not True:
            out.append(f"{name}: runAsNonRoot is not true")
        if sc.get("runAsUser") == 0:
            out.append(f"{name}: runs as uid 0")
        seccomp = (sc.get("seccompProfile") or pod.get("seccompProfile") or {}).get("type")
        if seccomp not in ("RuntimeDefault", "Localhost"):
            out.append(f"{name}: seccomp profile {seccomp}")
        if any(port.get("hostPort") for port in c.get("ports", [])):
            out.append(f"{name}: a host port")
        if sc.get("procMount", "Default") != "Default":
            out.append(f"{name}: procMount {sc['procMount']}")
        selinux = sc.get("seLinuxOptions") or {}
        if selinux.get("type", "") not in SELINUX_TYPES or selinux.get("user") or selinux.get("role"):
            out.append(f"{name}: seLinuxOptions")
        if (sc.get("appArmorProfile") or {}).get("type", "RuntimeDefault") not in ("RuntimeDefault", "Localhost"):
            out.append(f"{name}: AppArmor profile")
        if sc.get("readOnlyRootFilesystem") is not True:
            out.append(f"{name}: the root filesystem is writable")
    return out


@pytest.mark.parametrize("where,spec", pod_templates(OBJECTS), ids=lambda x: x if isinstance(x, str) else "")
def test_every_pod_meets_the_restricted_pod_security_standard(where, spec):
    assert not restricted_violations(spec), f"{where}: {restricted_violations(spec)}"
    assert spec.get("automountServiceAccountToken") is False, f"{where}: a run's pods do not talk to the API server"


def test_the_restricted_check_can_fail():
    spec = json.loads(json.dumps(WORKLOADS["sim"]["spec"]["template"]["spec"]))
    container = spec["containers"][0]
    container["securityContext"]["capabilities"] = {"add": ["NET_ADMIN"]}
    del container["securityContext"]["allowPrivilegeEscalation"]
    del spec["securityContext"]["runAsNonRoot"]
    spec["securityContext"]["seccompProfile"] = {"type": "Unconfined"}
    spec["volumes"].append({"name": "host", "hostPath": {"path": "/var/run"}})
    spec["hostNetwork"] = True
    container["securityContext"]["readOnlyRootFilesystem"] = False
    found = " | ".join(restricted_violations(spec))
    for part in ("drop ALL", "NET_ADMIN", "allowPrivilegeEscalation", "runAsNonRoot", "seccomp", "hostPath",
                 "hostNetwork", "root filesystem"):
        assert part in found, part


def test_the_namespace_enforces_the_restricted_standard_and_the_image_user_is_the_pods():
    ns = _get("Namespace", "morph-sim", RECORDS)
    assert ns["metadata"]["labels"]["pod-security.kubernetes.io/enforce"] == "restricted"
    dockerfile = (ROOT / "Dockerfile").read_text()
    (user,) = re.findall(r"^USER (\S+)$", dockerfile, re.M)
    assert user == f"{UID}:{UID}", "a numeric user, so the kubelet can verify runAsNonRoot against the image"
    assert f"--uid {UID}" in dockerfile and f"--gid {UID}" in dockerfile
    for where, spec in pod_templates(OBJECTS):
        pod = spec["securityContext"]
        assert (pod["runAsUser"], pod["runAsGroup"], pod["fsGroup"]) == (UID, UID, UID), where


def test_writable_paths_are_volumes():
    """With a read-only root filesystem, what a process writes goes to a volume: the records (the monitor) and a
    scratch /tmp (every process)."""
    for role, obj in WORKLOADS.items():
        mounts = {m["mountPath"]: m for m in _container(obj)["volumeMounts"]}
        assert "/tmp" in mounts and not mounts["/tmp"].get("readOnly"), role
        vols = {v["name"]: v for v in obj["spec"]["template"]["spec"]["volumes"]}
        assert "emptyDir" in vols[mounts["/tmp"]["name"]], role
    mounts = {m["mountPath"]: m["name"] for m in _container(WORKLOADS["monitor"])["volumeMounts"]}
    vols = {v["name"]: v for v in WORKLOADS["monitor"]["spec"]["template"]["spec"]["volumes"]}
    assert "persistentVolumeClaim" in vols[mounts[RUN_ENV["MORPH_OUTPUT_DIR"]]]


def _compose_schema() -> dict:
    return json.loads((resources.files("check_jsonschema.builtin_schemas.vendor") / "compose-spec.json").read_text())


def test_docker_compose_passes_the_compose_specification_schema():
    doc = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    schema = _compose_schema()
    errors = sorted(jsonschema.Draft7Validator(schema).iter_errors(doc), key=str)
    assert not errors, [f"{'/'.join(map(str, e.path))}: {e.message}" for e in errors]
    bad = json.loads(json.dumps(doc))
    bad["services"]["sim"]["restart"] = ["no"]
    bad["services"]["agent-0"]["deploy"] = {"replica": 3}
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
    """The sim hosts the run's endpoint (Service zenoh) and every other process connects to it: the supervisor's
    own topology, with the endpoint's in-cluster name."""
    endpoint = "tcp/zenoh:7447"
    specs = process_graph(CONFIG, endpoint)
    roles = {s.role for s in specs}
    assert roles == set(WORKLOADS)
    for obj in [WORKLOADS["sim"], WORKLOADS["monitor"], *AGENTS]:
        c = _container(obj)
        argv = c["command"]
        assert argv[0] == "morph-sim" and c["image"] == "morph-sim:0.1.0"
        try:
            args = build_parser().parse_args(argv[1:])
        except SystemExit as exc:
            raise AssertionError(f"morph-sim rejects {argv[1:]} (exit {exc.code})") from None
        role = args.command
        spec = next(s for s in specs if s.role == role and (role != "agent" or s.agent == args.id))
        if role == "sim":
            assert args.cfg_listen == "tcp/0.0.0.0:7447"
            zenoh = _get("Service", "zenoh")
            assert zenoh["spec"]["ports"][0]["port"] == 7447
            assert all(obj["spec"]["template"]["metadata"]["labels"].get(k) == v
                       for k, v in zenoh["spec"]["selector"].items())
        else:  # the role's own flags are the supervisor's
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


def test_the_robots_are_one_job_each_for_the_whole_fleet():
    """A Job per robot ends when its agent exits with the run; the Jobs are the fleet of run.env, robot N runs
    `agent --id N`, and apart from the id they are the same Job."""
    ids = []
    for job in AGENTS:
        args = build_parser().parse_args(_container(job)["command"][1:])
        assert job["metadata"]["name"] == f"agent-{args.id}"
        assert job["spec"]["template"]["spec"]["restartPolicy"] == "OnFailure"
        ids.append(args.id)
    assert ids == list(range(CONFIG.n_agents)), "one Job per robot of the fleet"
    assert CONFIG.role_of(ids[-1]) == "picker" and CONFIG.role_of(0) == "agv"

    def without_id(job: dict) -> str:
        n = job["metadata"]["name"].split("-")[1]
        text = json.dumps(job)
        return text.replace(f"agent-{n}", "agent-N").replace(f'"--id", "{n}"', '"--id", "N"') \
            .replace(f'"morph-sim.io/robot": "{n}"', '"morph-sim.io/robot": "N"')

    assert len({without_id(job) for job in AGENTS}) == 1
    assert not [o for o in OBJECTS if o["kind"] in ("StatefulSet", "Deployment")], "no controller outlives the run"


# -- credentials and access ------------------------------------------------------------------------------------------
def _secret_files(name: str) -> dict[str, str]:
    return {k: base64.b64decode(v).decode() for k, v in _get("Secret", name)["data"].items()}


def test_each_pod_mounts_only_its_own_credentials_from_morph_sim_credentials():
    generated = RENDERED / "credentials"
    argv = credentials_command()
    mounted_at = argv[argv.index("--mounted-at") + 1]
    owners = {"morph-endpoint": ["endpoint.json5", "passwords.txt"], "morph-monitor": ["monitor.json5"],
              "morph-air": ["air.json5"],
              **{f"morph-agent-{n}": [f"agent-{n}.json5"] for n in range(CONFIG.n_agents)}}
    for obj in [WORKLOADS["sim"], WORKLOADS["monitor"], *AGENTS]:
        pod = obj["spec"]["template"]["spec"]
        secrets = [v for v in pod["volumes"] if "secret" in v]
        assert len(secrets) == 1, f"{obj['metadata']['name']}: one Secret, its own"
        (vol,) = secrets
        name = vol["secret"]["secretName"]
        files = _secret_files(name)
        assert sorted(files) == sorted(owners.pop(name)), name
        for key, text in files.items():
            assert text == (generated / key).read_text(), f"{name}/{key} is not what morph-sim credentials wrote"
        c = _container(obj)
        (mount,) = [m for m in c["volumeMounts"] if m["name"] == vol["name"]]
        assert mount["mountPath"] == mounted_at and mount.get("readOnly")
        env = {e["name"]: e.get("value") for e in c["env"]}
        config_file = Path(env["ZENOH_CONFIG"])
        assert config_file.parent == Path(mounted_at) and config_file.name in files
        assert vol["secret"]["defaultMode"] & 0o007 == 0, "not readable by other users of the node"
    # mounted by the air component's pod, with MORPH_NETWORK=congested (test_the_air_component_…)
    assert sorted(_secret_files("morph-air")) == owners.pop("morph-air")
    assert not owners, f"Secrets no pod mounts: {sorted(owners)}"
    # the endpoint reads the passwords where its Secret is mounted; its access control is this run's fleet
    endpoint = json.loads(_secret_files("morph-endpoint")["endpoint.json5"])
    assert endpoint["transport"]["auth"]["usrpwd"]["dictionary_file"] == f"{mounted_at}/passwords.txt"
    acl = endpoint["access_control"]
    assert acl["enabled"] and acl["default_permission"] == "deny"
    users = {u for subject in acl["subjects"] for u in subject["usernames"]}
    assert users == {"operator", "monitor", "air", *(f"agent-{n}" for n in range(CONFIG.n_agents))}
    assert all(f"morph/{CONFIG.run_id}/" in k for rule in acl["rules"] for k in rule["key_exprs"]
               if not k.startswith("morph/**"))
    assert not [o for o in OBJECTS if o["kind"] == "Secret" and "operator.json5" in o["data"]], \
        "the operator's credentials stay with the operator"


def _selects(selector: dict, labels: dict[str, str]) -> bool:
    if any(labels.get(k) != v for k, v in selector.get("matchLabels", {}).items()):
        return False
    for e in selector.get("matchExpressions", []):
        have = labels.get(e["key"])
        if e["operator"] == "In" and have not in e["values"] or e["operator"] == "NotIn" and have in e["values"]:
            return False
        if e["operator"] == "Exists" and e["key"] not in labels or e["operator"] == "DoesNotExist" and e["key"] in labels:
            return False
    return True


def admitted(policies: list[dict], target: dict[str, str], source: dict[str, str] | None, port: int) -> bool:
    """Whether NetworkPolicies let a pod labelled ``source`` (None: outside the namespace) reach ``port`` of a pod
    labelled ``target`` (in the same namespace)."""
    applying = [p for p in policies if _selects(p["spec"]["podSelector"], target)
                and "Ingress" in p["spec"].get("policyTypes", ["Ingress"])]
    if not applying:
        return True
    for p in applying:
        for rule in p["spec"].get("ingress", []):
            ports = rule.get("ports")
            if ports and not any(x.get("port") == port for x in ports):
                continue
            peers = rule.get("from")
            if not peers or any("podSelector" in peer and "namespaceSelector" not in peer and source is not None
                                and _selects(peer["podSelector"], source) for peer in peers):
                return True
    return False


def _with_the_air() -> list[dict]:
    """The objects of a run under a rate-limited profile: run.env's MORPH_NETWORK=congested and the air component on,
    as the kustomization's comment says."""
    into = Path(tempfile.mkdtemp(prefix="k8s-air-"))
    shutil.copytree(RENDERED, into / "k8s")
    kust_path = into / "k8s" / "kustomization.yaml"
    text = kust_path.read_text()
    assert "# components:\n#   - air\n" in text
    kust_path.write_text(text.replace("# components:\n#   - air\n", "components:\n  - air\n"))
    (into / "k8s" / "run.env").write_text((into / "k8s" / "run.env").read_text() + "MORPH_NETWORK=congested\n")
    return render(into / "k8s")


def test_the_air_component_is_the_supervisors_air_process():
    """Under a rate-limited profile the run has one more process, the air: the component's Job runs the
    supervisor's command with the air's own credentials, passes the schema and the restricted standard, and may
    reach the endpoint."""
    objects = _with_the_air()
    config = RunConfig.from_env(_get("ConfigMap", "morph-run", objects)["data"])
    assert config.shared_air
    (spec,) = [s for s in process_graph(config, "tcp/zenoh:7447") if s.role == "air"]
    air = _get("Job", "air", objects)
    kubernetes_validate.validate(air, KUBE_VERSION, strict=True)
    pod = air["spec"]["template"]["spec"]
    assert not restricted_violations(pod) and pod["restartPolicy"] == "Never" and air["spec"]["backoffLimit"] == 0
    c = _container(air)
    args = build_parser().parse_args(c["command"][1:])
    assert args.command == "air" and args.cfg_endpoint == spec.argv[spec.argv.index("--endpoint") + 1]
    env = {e["name"]: e.get("value") for e in c["env"]}
    assert env["ZENOH_CONFIG"] == "/run/secrets/morph/air.json5"
    assert all(env[k] == v for k, v in CHILD_ENV.items())
    (secret,) = [v["secret"]["secretName"] for v in pod["volumes"] if "secret" in v]
    assert secret == "morph-air" and sorted(_secret_files(secret)) == ["air.json5"]
    policies = [o for o in objects if o["kind"] == "NetworkPolicy"]
    sim_labels = WORKLOADS["sim"]["spec"]["template"]["metadata"]["labels"]
    assert admitted(policies, sim_labels, air["spec"]["template"]["metadata"]["labels"], 7447)


def test_only_the_runs_pods_reach_the_endpoint():
    policies = [o for o in OBJECTS if o["kind"] == "NetworkPolicy"]
    labels = {role: obj["spec"]["template"]["metadata"]["labels"] for role, obj in WORKLOADS.items()}
    assert all(admitted(policies, labels["sim"], labels[role], 7447) for role in ("monitor", "agent"))
    for job in AGENTS:
        assert admitted(policies, labels["sim"], job["spec"]["template"]["metadata"]["labels"], 7447)
    assert not admitted(policies, labels["sim"], {"app": "anything-else"}, 7447)
    assert not admitted(policies, labels["sim"], None, 7447), "nothing from other namespaces"
    assert not admitted(policies, labels["sim"], labels["monitor"], 9464), "only the endpoint's port"
    assert not admitted(policies, labels["agent"], labels["monitor"], 7447), "the robots take no traffic"
    assert admitted(policies, labels["monitor"], None, 9464), "Prometheus scrapes the monitor from elsewhere"
    assert not admitted(policies, labels["monitor"], labels["agent"], 7447)


def test_every_container_has_liveness_and_readiness_probes():
    for obj in [WORKLOADS["sim"], WORKLOADS["monitor"], *AGENTS]:
        c = _container(obj)
        ports = {p["name"]: p["containerPort"] for p in c.get("ports", [])}
        for kind in ("livenessProbe", "readinessProbe"):
            probe = c[kind]
            if "tcpSocket" in probe or "httpGet" in probe:
                port = (probe.get("tcpSocket") or probe.get("httpGet"))["port"]
                assert port in ports or port in ports.values(), f"{obj['metadata']['name']}: {kind} port {port}"
            else:
                argv = probe["exec"]["command"]
                assert argv[:2] == ["python", "-c"]
                compile(argv[2], kind, "exec")
    sim = _container(WORKLOADS["sim"])
    assert sim["readinessProbe"]["tcpSocket"]["port"] == "zenoh" and sim["ports"][0]["containerPort"] == 7447
    mon = _container(WORKLOADS["monitor"])
    assert mon["livenessProbe"]["httpGet"]["path"] == "/metrics"


def test_the_records_outlive_the_run():
    """`kubectl delete -k deploy/k8s` deletes what deploy/k8s renders: the namespace and the records volume are
    applied apart (deploy/k8s/records), so the documented teardown keeps them."""
    assert not [o for o in OBJECTS if o["kind"] in ("Namespace", "PersistentVolumeClaim")]
    assert {o["kind"] for o in RECORDS} == {"Namespace", "PersistentVolumeClaim"}
    claim = {v["name"]: v for v in WORKLOADS["monitor"]["spec"]["template"]["spec"]["volumes"]}["runs"]
    assert _get("PersistentVolumeClaim", claim["persistentVolumeClaim"]["claimName"], RECORDS)
    ns = {o["metadata"].get("namespace") for o in OBJECTS} | {o["metadata"].get("namespace") for o in RECORDS}
    assert ns == {"morph-sim", None} and _get("Namespace", "morph-sim", RECORDS)
    doc = (ROOT / "docs" / "deploy.md").read_text()
    assert "kubectl apply -k deploy/k8s/records" in doc and "kubectl delete -k deploy/k8s " in doc
    assert "kubectl delete -k deploy/k8s/records" not in doc.split("## 5. Kubernetes")[1].split("```")[1]


def test_services_and_ports_match_the_commands():
    for obj in [WORKLOADS["monitor"], *AGENTS]:
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
    # the Prometheus config of the monitoring profile scrapes the same name and port
    prom = yaml.safe_load((ROOT / "deploy" / "monitoring" / "prometheus.yml").read_text())
    assert prom["scrape_configs"][0]["static_configs"][0]["targets"] == [f"{svc['metadata']['name']}:{port}"]
