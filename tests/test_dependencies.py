"""Dependencies by role: a service process runs with the base dependencies alone (no plotting, terminal UI or
process-inspection libraries), so a container of one service installs only those."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
EXTRAS_ONLY = ("matplotlib", "rich", "psutil", "PIL")

# Runs in a fresh interpreter where importing any extra fails, as in an environment without them.
_PROBE = """
import importlib.abc, json, sys
BLOCKED = {blocked!r}
class Block(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{{name}} is not installed (blocked by the test)")
sys.meta_path.insert(0, Block())
{body}
print(json.dumps(sorted({{m.split(".")[0] for m in sys.modules}} & set(BLOCKED))))
"""


def _probe(body: str) -> subprocess.CompletedProcess:
    code = _PROBE.format(blocked=EXTRAS_ONLY, body=body)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=ROOT)


def test_every_service_imports_with_the_base_dependencies_only():
    proc = _probe("import services.agent.service, services.agent.command, services.sim.service, "
                  "services.sim.command, services.monitor.service, services.monitor.command, "
                  "services.monitor.prometheus, services.supervisor.launcher")
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(proc.stdout.splitlines()[-1]) == []


def test_python_m_services_help_runs_with_the_base_dependencies_only():
    body = "import contextlib, io, runpy\n"
    for service in ("agent", "sim", "monitor"):
        body += (f"out = io.StringIO()\nsys.argv = ['{service}', '--help']\n"
                 f"with contextlib.redirect_stdout(out):\n"
                 f"    try:\n        runpy.run_module('services.{service}', run_name='__main__')\n"
                 f"    except SystemExit as exc:\n        assert exc.code in (0, None), exc.code\n"
                 f"assert 'usage:' in out.getvalue(), '{service}'\n")
    proc = _probe(body)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(proc.stdout.splitlines()[-1]) == []


def test_the_base_dependencies_hold_no_extra():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    base = " ".join(project["dependencies"]).lower()
    for name in ("matplotlib", "rich", "psutil", "pillow"):
        assert name not in base, f"{name} belongs in an extra, not in the base dependencies"
    extras = project["optional-dependencies"]
    (everything,) = extras["all"]
    assert set(everything.removeprefix("morph-sim[").rstrip("]").split(",")) == set(extras) - {"all", "test"}
