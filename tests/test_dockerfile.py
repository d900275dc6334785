"""The Dockerfile without a Docker engine: its instructions are checked, and its steps are replayed — the build
context it would see, the wheel it builds (its contents, console script and requirements read off it), and (slow) a
fresh venv that installs that wheel and `morph-sim up` from it.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import zipfile
from pathlib import Path

import pytest
from _compose import interpolate, load

from morph_sim.cli import build_parser, main

ROOT = Path(__file__).resolve().parent.parent
BASE_IMAGE = "python:3.11-slim"


def instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs, continuation lines joined and comments dropped."""
    out, pending = [], ""
    for line in text.splitlines():
        stripped = line.strip()
        if not pending and (not stripped or stripped.startswith("#")):
            continue
        if pending and stripped.startswith("#"):
            continue  # a comment inside a continued instruction
        if stripped.endswith("\\"):
            pending += stripped[:-1] + " "
            continue
        full = (pending + stripped).strip()
        pending = ""
        word, _, rest = full.partition(" ")
        out.append((word.upper(), rest.strip()))
    assert not pending, "the Dockerfile ends inside a continued instruction"
    return out


DOCKERFILE = instructions((ROOT / "Dockerfile").read_text())


def stages() -> list[list[tuple[str, str]]]:
    result: list[list[tuple[str, str]]] = []
    for ins in DOCKERFILE:
        if ins[0] == "FROM":
            result.append([])
        if result:
            result[-1].append(ins)
    return result


def build_args() -> dict[str, str]:
    args = {}
    for word, rest in DOCKERFILE:
        if word == "FROM":
            break
        if word == "ARG":
            name, _, default = rest.partition("=")
            args[name] = default
    return args


def _image(from_args: str) -> str:
    image = from_args.split()[0]
    return re.sub(r"\$\{(\w+)\}", lambda m: build_args()[m.group(1)], image)


# -- .dockerignore, as Docker applies it -------------------------------------------------------------------------------
def _pattern_regex(pattern: str) -> re.Pattern:
    out, i = "", 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out += "(?:.*/)?"
            i += 3
        elif pattern.startswith("**", i):
            out += ".*"
            i += 2
        elif pattern[i] == "*":
            out += "[^/]*"
            i += 1
        elif pattern[i] == "?":
            out += "[^/]"
            i += 1
        else:
            out += re.escape(pattern[i])
            i += 1
    return re.compile(out + "$")


def ignore_rules() -> list[tuple[bool, re.Pattern, str]]:
    rules = []
    for line in (ROOT / ".dockerignore").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        negate = line.startswith("!")
        pattern = line[1:] if negate else line
        pattern = os.path.normpath(pattern).lstrip("/")
        rules.append((negate, _pattern_regex(pattern), pattern))
    return rules


def excluded(rel: str, rules=None) -> bool:
    """Docker's rule: the last pattern matching the path or one of its parent directories decides."""
    rules = ignore_rules() if rules is None else rules
    parts = rel.split("/")
    candidates = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    result = False
    for negate, regex, _ in rules:
        if any(regex.match(c) for c in candidates):
            result = not negate
    return result


def build_context(dest: Path) -> list[str]:
    """Copy what `docker build .` would send (the repo minus .dockerignore) to ``dest``; return the relative paths."""
    rules = ignore_rules()
    negations = [p for negate, _, p in rules if negate]
    copied = []
    for dirpath, dirnames, filenames in os.walk(ROOT):
        rel_dir = os.path.relpath(dirpath, ROOT)
        rel_dir = "" if rel_dir == "." else rel_dir
        keep = []
        for d in dirnames:
            rel = f"{rel_dir}/{d}" if rel_dir else d
            # Prune excluded directories no negation can reach into (.git, .venv …).
            if excluded(rel, rules) and not any(n == rel or n.startswith(rel + "/") for n in negations):
                continue
            keep.append(d)
        dirnames[:] = keep
        for f in filenames:
            rel = f"{rel_dir}/{f}" if rel_dir else f
            if not excluded(rel, rules):
                (dest / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(ROOT / rel, dest / rel)
                copied.append(rel)
    return copied


# -- static checks -------------------------------------------------------------------------------------------------
def test_every_stage_builds_from_python_3_11_slim():
    froms = [rest for word, rest in DOCKERFILE if word == "FROM"]
    assert len(froms) == 2, "a build stage and a runtime stage"
    assert all(_image(f) == BASE_IMAGE for f in froms)
    assert DOCKERFILE[0][0] == "ARG" or DOCKERFILE[0][0] == "FROM"


def test_the_runtime_stage_runs_as_a_non_root_user_without_dev_tools():
    runtime = stages()[-1]
    users = [rest for word, rest in runtime if word == "USER"]
    assert users and users[-1] not in ("root", "0") and not users[-1].startswith("0:")
    runs = " && ".join(rest for word, rest in runtime if word == "RUN")
    # numeric, so that Kubernetes can check runAsNonRoot against the image (a name it cannot resolve)
    assert "useradd --system --uid 10001 --gid morph" in runs and users[-1] == "10001:10001"
    for tool in ("apt-get", "apk ", "gcc", "build-essential", "git ", "make ", "pytest", "[test]", "-e "):
        assert tool not in runs, f"runtime stage installs or uses {tool.strip()!r}"
    assert "pip install /tmp/wheels/*.whl" in runs, "the runtime installs the wheel built in the first stage"
    assert "pip uninstall --yes setuptools wheel pip" in runs, "the installers do not stay in the image"
    copies = [rest for word, rest in runtime if word == "COPY"]
    assert copies == ["--from=build /wheels /tmp/wheels"], "only the wheel crosses into the runtime stage"
    # The user owns the records volume.
    env = " ".join(rest for word, rest in runtime if word == "ENV")
    assert "MORPH_OUTPUT_DIR=/data/runs" in env and "chown morph:morph /data/runs" in runs


def test_the_default_command_is_a_real_morph_sim_invocation():
    cmd = [rest for word, rest in DOCKERFILE if word == "CMD"]
    assert len(cmd) == 1
    argv = json.loads(cmd[0])  # exec form: SIGTERM reaches morph-sim, not a shell
    assert argv[0] == "morph-sim"
    args = build_parser().parse_args(argv[1:])
    assert args.command == "up"
    assert not any(word == "ENTRYPOINT" for word, _ in DOCKERFILE)


def test_exposed_ports_are_the_ones_compose_uses():
    compose = interpolate(load(ROOT / "docker-compose.yml"), {})
    exposed = {p.split("/")[0] for word, rest in DOCKERFILE if word == "EXPOSE" for p in rest.split()}
    sim_port = compose["services"]["sim"]["command"][-1].rsplit(":", 1)[1]
    prom_port = compose["services"]["monitor"]["ports"][0].rsplit(":", 1)[1]
    assert exposed == {sim_port, prom_port}


def test_the_build_context_holds_what_the_dockerfile_copies_and_nothing_private():
    build = stages()[0]
    sources = []
    for word, rest in build:
        if word == "COPY":
            parts = rest.split()
            assert not parts[0].startswith("--from")
            sources += parts[:-1]
    assert sources == ["pyproject.toml", "README.md", "schemas", "services", "morph_sim"]
    for src in sources:
        assert not excluded(src), f".dockerignore excludes {src}, which the Dockerfile copies"
    for shipped in ("services/world/layouts.toml", "schemas/json/tick.json", "services/sim/__init__.py"):
        assert not excluded(shipped), f".dockerignore excludes {shipped}, which the image needs"
    for private in (".venv/bin/python", ".git/config", "runs/x/manifest.json", "tests/test_keys.py",
                    "deploy/zenoh/credentials.txt", "morph_sim/__pycache__/cli.cpython-311.pyc",
                    "morph_sim.egg-info/PKG-INFO", "docs/deploy.md"):
        assert excluded(private), f"{private} would be sent to the Docker daemon"


def test_the_build_stage_builds_a_wheel():
    runs = [rest for word, rest in stages()[0] if word == "RUN"]
    assert runs == ["python -m pip wheel --no-deps --wheel-dir /wheels ."]


# -- the steps, replayed -------------------------------------------------------------------------------------------
def tree_packages() -> set[str]:
    """Every importable package of the source tree: a folder with an ``__init__.py`` under a top-level package."""
    found = set()
    for top in ("schemas", "services", "morph_sim"):
        for init in (ROOT / top).rglob("__init__.py"):
            if "__pycache__" not in init.parts:
                found.add(".".join(init.parent.relative_to(ROOT).parts))
    return found


def build_the_wheel(tmp_path: Path) -> Path:
    """Build stage: the context and `pip wheel` as in the Dockerfile (an isolated build, as in the image); the wheel
    holds every package of the tree and the data files the services read."""
    missing = [p for p in ("pyproject.toml", "README.md") if not (ROOT / p).exists()]
    assert not missing, f"the Dockerfile copies {missing}, which do not exist (pyproject's readme needs README.md)"
    context = tmp_path / "context"
    context.mkdir()
    files = build_context(context)
    assert "morph_sim/cli.py" in files and not any(f.startswith(("tests/", ".venv/", ".git/")) for f in files)

    wheels = tmp_path / "wheels"
    built = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--wheel-dir", str(wheels), "."],
                           cwd=context, capture_output=True, text=True, timeout=300)
    assert built.returncode == 0, built.stdout[-3000:] + built.stderr[-3000:]
    (wheel,) = wheels.glob("morph_sim-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
    in_wheel = {n.rsplit("/", 1)[0].replace("/", ".") for n in names if n.endswith("/__init__.py")}
    assert tree_packages() - in_wheel == set(), f"packages missing from the wheel: {tree_packages() - in_wheel}"
    for data in ("schemas/json/tick.json", "services/world/layouts.toml", "services/policies/presets/morph_paper.toml"):
        assert data in names, f"{data} is missing from the wheel"
    return wheel


# The default suite's twin of the slow test below: the same build, and what the installed wheel would need to run
# `morph-sim up` read off the wheel itself (the installer and the run add ~8 CPU-s and are replayed with -m slow).
def test_the_wheel_holds_the_tree_its_console_script_and_requirements_this_environment_meets(tmp_path):
    """The wheel the build stage builds holds the tree's code byte for byte (every module, the data files), declares
    the ``morph-sim`` console script the image's CMD runs, and requires only what is installed here at versions that
    satisfy it (what `pip check` checks in the slow test, e.g. the eclipse-zenoh pin)."""
    from email.parser import Parser
    from importlib.metadata import PackageNotFoundError, version

    from packaging.requirements import Requirement

    wheel = build_the_wheel(tmp_path)
    with zipfile.ZipFile(wheel) as archive:
        names = set(archive.namelist())
        (info,) = {n.split("/", 1)[0] for n in names if n.split("/", 1)[0].endswith(".dist-info")}
        modules = {n: archive.read(n) for n in names if n.endswith(".py")}
        entry_points = archive.read(f"{info}/entry_points.txt").decode()
        metadata = Parser().parsestr(archive.read(f"{info}/METADATA").decode())
    for name, code in modules.items():
        assert code == (ROOT / name).read_bytes(), f"{name} in the wheel differs from the tree"
    tree_modules = {str(p.relative_to(ROOT)) for pkg in tree_packages() for p in (ROOT / pkg.replace(".", "/")).glob("*.py")}
    assert tree_modules - set(modules) == set(), f"modules missing from the wheel: {tree_modules - set(modules)}"

    assert "[console_scripts]" in entry_points and "morph-sim = morph_sim.cli:main" in entry_points.splitlines()
    cmd = json.loads(next(rest for word, rest in DOCKERFILE if word == "CMD"))
    assert cmd[0] == "morph-sim"  # the image runs the script the wheel installs
    assert callable(main)  # the script's target, in the tree's morph_sim/cli.py that the wheel holds unchanged

    unmet = []
    for line in metadata.get_all("Requires-Dist"):
        req = Requirement(line)
        if req.marker is not None and not req.marker.evaluate({"extra": ""}):
            continue  # an extra's requirement: the image installs none
        try:
            have = version(req.name)
        except PackageNotFoundError:
            have = None
        if have is None or not req.specifier.contains(have, prereleases=True):
            unmet.append(f"{req} (installed: {have})")
    assert metadata.get_all("Requires-Dist") and not unmet, f"the wheel's requirements are not met: {unmet}"


@pytest.mark.slow
def test_the_wheel_installs_into_a_fresh_venv_and_runs_up(tmp_path):
    """Build stage: the context and `pip wheel` as in the Dockerfile. Runtime stage: a fresh venv installs that wheel
    (and nothing of the source tree); its dependencies come from the project's venv on a path appended after the
    venv's own site-packages (this machine cannot download eclipse-zenoh), so `import morph_sim` can only find the
    wheel's copy. Then `morph-sim up --scale tiny` runs a real distributed run from the installed console script.
    """
    wheel = build_the_wheel(tmp_path)

    # The venv has no pip of its own (seeding one costs seconds of CPU; the image uninstalls its pip anyway): this
    # process's pip installs into it and checks it (pip --python).
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=120)
    py = venv / "bin" / "python"
    pip = [sys.executable, "-m", "pip", "--python", str(py)]
    installed = subprocess.run([*pip, "install", "--no-deps", "--no-index", str(wheel)],
                               capture_output=True, text=True, timeout=300)
    assert installed.returncode == 0, installed.stdout[-3000:] + installed.stderr[-3000:]
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    deps = sysconfig.get_paths()["purelib"]
    (Path(site) / "zz_project_dependencies.pth").write_text(deps + "\n")

    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "MORPH_", "VIRTUAL_ENV"))}
    run_dir = tmp_path / "work"
    run_dir.mkdir()
    where = subprocess.run([str(py), "-c", "import morph_sim, schemas, services.sim, zenoh; print(services.sim.__file__)"], cwd=run_dir,
                           env=env, capture_output=True, text=True, timeout=120)
    assert where.returncode == 0, where.stderr
    assert where.stdout.strip().startswith(str(venv)), f"services imported from {where.stdout.strip()}"
    check = subprocess.run([*pip, "check"], cwd=run_dir, env=env, capture_output=True, text=True, timeout=120)
    assert check.returncode == 0, f"the wheel's requirements are not met: {check.stdout}"  # e.g. eclipse-zenoh pin

    up = subprocess.run([str(venv / "bin" / "morph-sim"), "up", "--scale", "tiny", "--steps", "20", "--quiet",
                         "--run-id", "from-wheel", "--output-dir", str(run_dir / "runs")],
                        cwd=run_dir, env=env, capture_output=True, text=True, timeout=300)
    assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-3000:]
    record = run_dir / "runs" / "from-wheel"
    assert (record / "manifest.json").exists() and (record / "summary.json").exists()
    assert "completed" in up.stdout
