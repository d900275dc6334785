"""``morph-sim policy list|show|new|check``: the policies a run can use, a template for a new one, and the
conformance kit (docs/policies.md)."""

from __future__ import annotations

import argparse
import keyword
import math
import re
import sys
from importlib import resources
from pathlib import Path

NAME = "policy"
HELP = "list, describe, create (a package template) and check (the conformance kit) coordination policies"
EPILOG = ("exit status: 0 done (check: the policy conforms); 1 check: the policy breaks a rule (one line each); "
          "2 bad name, options or flags")

_NEW_NAME = re.compile(r"^[a-z][a-z0-9_-]{0,39}$")
TEMPLATE_FILES = {
    "pyproject.toml.tmpl": "pyproject.toml",
    "README.md.tmpl": "README.md",
    "policy.py.tmpl": "{package}/policy.py",
    "test_policy.py.tmpl": "tests/test_policy.py",
}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="policy_action", metavar="ACTION", required=True)
    sub.add_parser("list", help="the shipped and the installed policies")
    show = sub.add_parser("show", help="a policy's parameters: name, type, default, meaning")
    show.add_argument("name", metavar="NAME", help="a policy name or package.module:Class")
    new = sub.add_parser("new", help="write a pip-installable policy package (entry point, policy class, tests)")
    new.add_argument("name", metavar="NAME", help="the policy's name (lower case letters, digits, - and _)")
    new.add_argument("--out", required=True, metavar="DIR", help="the package's directory (must not exist)")
    check = sub.add_parser("check", help="run the conformance kit (morph_sim.testing.check_policy)")
    check.add_argument("name", metavar="NAME", help="a policy name or package.module:Class")
    check.add_argument("--policy-option", dest="options", action="append", default=[], metavar="KEY=VALUE",
                       help="a parameter of the policy (repeatable)")
    check.add_argument("--scale", default="tiny", help="warehouse size of the check's episodes (default tiny)")
    check.add_argument("--steps", type=int, default=120, help="ticks per episode (default 120)")
    check.add_argument("--seed", type=int, default=1, help="seed of the episodes (default 1)")
    check.add_argument("--no-distributed", dest="distributed", action="store_false",
                       help="skip the distributed run (morph-sim up) against the lab")
    check.add_argument("--decision-limit", type=float, default=None, metavar="SECONDS",
                       help="seconds one decision may take (default 0.25)")


def run(args: argparse.Namespace) -> int:
    return {"list": _list, "show": _show, "new": _new, "check": _check}[args.policy_action](args)


def _list(args) -> int:
    from services.policies.coordinators import POLICIES
    from services.policies.loading import installed_policies, resolve

    for name in POLICIES:
        print(f"{name:16} shipped    {_summary(resolve(name))}")
    for name, entry in sorted(installed_policies().items()):
        print(f"{name:16} installed  {entry.value}")
    return 0


def _summary(cls) -> str:
    doc = (cls.__doc__ or "").strip().splitlines()
    return doc[0] if doc else ""


def _show(args) -> int:
    from services.policies.loading import resolve

    cls = resolve(args.name)
    fields = cls.Params.model_fields
    print(f"policy {args.name}: {cls.__module__}:{cls.__qualname__}")
    if not fields:
        print("  no parameters")
    for field, info in fields.items():
        kind = getattr(info.annotation, "__name__", str(info.annotation))
        default = info.get_default(call_default_factory=True)
        print(f"  {field} ({kind}, default {default!r}): {info.description or ''}")
    return 0


def _new(args) -> int:
    name = args.name
    if not _NEW_NAME.match(name):
        raise ValueError(f"name: {name!r} must be lower case letters, digits, - and _, starting with a letter")
    package = name.replace("-", "_")
    if keyword.iskeyword(package):
        raise ValueError(f"name: {name!r} is a Python keyword")
    from services.policies.coordinators import POLICIES

    if name in POLICIES:
        raise ValueError(f"name: {name!r} is a shipped policy's name")
    out = Path(args.out)
    if out.exists():
        raise ValueError(f"out: {out} exists; choose a new directory")
    if not out.parent.is_dir():
        raise ValueError(f"out: {out.parent} is not a directory")
    cls = "".join(part.capitalize() for part in re.split(r"[-_]", name) if part) + "Policy"
    values = {"name": name, "dist": name, "package": package, "cls": cls}
    template = resources.files("morph_sim").joinpath("template")
    for source, target in TEMPLATE_FILES.items():
        path = out / target.format(**values)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(template.joinpath(source).read_text().format(**values))
    (out / package / "__init__.py").write_text(f'"""{name}: a coordination policy for morph-sim."""\n')
    print(f"wrote {out}: policy {name!r} ({package}.policy:{cls})")
    print(f"next: pip install -e {out} && morph-sim policy check {name}")
    return 0


def _check(args) -> int:
    from morph_sim.testing import DECISION_LIMIT, RULES, policy_findings
    from services.policies.loading import make_policy
    from services.runconfig import parse_policy_options

    if args.steps < 2 or args.steps > 100_000:
        raise ValueError(f"steps: {args.steps} outside 2..100000")
    limit = DECISION_LIMIT if args.decision_limit is None else args.decision_limit
    if not (math.isfinite(limit) and 0 < limit <= 60):
        raise ValueError(f"decision-limit: {args.decision_limit} is not a number of seconds in (0, 60]")
    options = parse_policy_options(args.options)
    make_policy(args.name, options)  # a bad name or option: one line, exit 2, before anything runs
    findings = policy_findings(args.name, options, scale=args.scale, steps=args.steps, seed=args.seed,
                               distributed=args.distributed, decision_limit=limit)
    broken = {f.rule for f in findings}
    for finding in findings:
        print(finding)
    checked = [r for r in RULES if args.distributed or r != "distributed"]
    kept = [r for r in checked if r not in broken]
    print(f"policy {args.name}: {len(kept)} of {len(checked)} rules kept" + (
        "" if not broken else f"; broken: {', '.join(r for r in RULES if r in broken)}"), file=sys.stderr)
    return 1 if findings else 0
