"""Finding a policy by name: a shipped one (:data:`services.policies.coordinators.POLICIES`), an installed one (an
entry point of the group ``morph_sim.policies``), or any importable class (``package.module:Class``).

The name is what a run's configuration carries (``--policy``, ``MORPH_POLICY``, the Python API), what its record
says and what every agent process checks against its sim's: a policy is found the same way in each process.
"""

from __future__ import annotations

import importlib
import re
from collections.abc import Mapping
from functools import lru_cache
from importlib import metadata
from typing import Any

from services.policies.coordinators import POLICIES
from services.policies.interface import CoordinationPolicy

#: the entry-point group a policy package registers its policy class under (pyproject: [project.entry-points])
ENTRY_POINT_GROUP = "morph_sim.policies"

_IMPORT_PATH = re.compile(r"^[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*:[A-Za-z_][\w]*(\.[A-Za-z_][\w]*)*$")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def installed_policies() -> dict[str, metadata.EntryPoint]:
    """The entry points of :data:`ENTRY_POINT_GROUP` by name (a shipped name is never shadowed)."""
    return {ep.name: ep for ep in metadata.entry_points(group=ENTRY_POINT_GROUP) if ep.name not in POLICIES}


def policy_names() -> tuple[str, ...]:
    """The names ``--policy`` takes without a module path: the shipped ones, then the installed ones."""
    return (*POLICIES, *sorted(installed_policies()))


def check_name(name: str) -> str:
    """``name`` if it has the shape of a policy name or an import path; ValueError naming the field otherwise."""
    if not isinstance(name, str) or not (_NAME.match(name) or _IMPORT_PATH.match(name)):
        raise ValueError(f"policy: {name!r} is neither a policy name nor a package.module:Class path")
    return name


@lru_cache(maxsize=64)
def resolve(name: str) -> type[CoordinationPolicy]:
    """The policy class of ``name``; ValueError with one line saying why not (unknown name, module not importable,
    no such class, not a policy)."""
    check_name(name)
    if name in POLICIES:
        return POLICIES[name]
    if ":" in name:
        module_name, _, attr = name.partition(":")
        try:
            obj: Any = importlib.import_module(module_name)
        except ImportError as exc:
            raise ValueError(f"policy: cannot import {module_name!r} ({exc.msg})") from None
        except Exception as exc:  # the module itself raised while being imported
            raise ValueError(f"policy: importing {module_name!r} failed: {type(exc).__name__}: {exc}") from None
        for part in attr.split("."):
            if not hasattr(obj, part):
                raise ValueError(f"policy: module {module_name!r} has no {attr!r}")
            obj = getattr(obj, part)
        return _check_class(obj, name)
    installed = installed_policies()
    if name in installed:
        try:
            obj = installed[name].load()
        except Exception as exc:
            raise ValueError(f"policy: the installed policy {name!r} ({installed[name].value}) does not load: "
                             f"{type(exc).__name__}: {exc}") from None
        return _check_class(obj, name)
    raise ValueError(f"policy: unknown {name!r} (known: {', '.join(policy_names())}; or package.module:Class)")


def _check_class(obj: Any, name: str) -> type[CoordinationPolicy]:
    if not (isinstance(obj, type) and issubclass(obj, CoordinationPolicy)):
        raise ValueError(f"policy: {name!r} is not a CoordinationPolicy subclass "
                         "(services.policies.interface.CoordinationPolicy)")
    if getattr(obj, "__abstractmethods__", None):
        raise ValueError(f"policy: {name!r} leaves {', '.join(sorted(obj.__abstractmethods__))} unimplemented")
    return obj


def make_policy(name: str, options: Mapping[str, Any] | None = None, **more: Any) -> CoordinationPolicy:
    """The policy ``name`` with its options (a mapping and/or keywords); ValueError with one line naming the option
    or the policy on a bad one."""
    cls = resolve(name)
    return cls.from_options({**(options or {}), **more})


def parse_option(text: str) -> tuple[str, str]:
    """``KEY=VALUE`` (a ``--policy-option``); ValueError naming the flag otherwise."""
    key, sep, value = text.partition("=")
    key = key.strip()
    if not sep or not re.match(r"^[A-Za-z_]\w{0,63}$", key):
        raise ValueError(f"policy-option: {text!r} is not KEY=VALUE (KEY a parameter name)")
    return key, value
