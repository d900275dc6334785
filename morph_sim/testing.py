"""The conformance kit for coordination policies: :func:`check_policy` (``morph-sim policy check NAME``), in the role
Gymnasium's ``check_env`` and PettingZoo's ``api_test`` play for environments.

It runs the policy in the lab and, unless told not to, in a real distributed run, and checks the rules a policy must
keep for the testbed's results to mean anything (services/policies/interface.py says what a policy sees):

* ``interface`` — it builds from its default parameters, for one robot and for the fleet; its rows have the fleet's
  shape; a probability is finite and in [0, 1]; a candidate is a free picker or -1; a choice is an index or -1;
* ``determinism`` — the same seed gives the same decisions, episode after episode in one process;
* ``own-view`` — one brain for the whole fleet and one brain per robot decide alike (a robot's decisions depend on
  what it is handed, not on which other robots share its process);
* ``restore`` — a robot's brain restored from the states its fleet published decides as the brain that never
  stopped;
* ``robustness`` — under stale and lost fleet views, lost dispatch messages and refused commitments it raises
  nothing and decides within ``decision_limit`` seconds;
* ``state-size`` — what it publishes for a restore fits the transport's message bound;
* ``distributed`` — ``morph-sim up`` (one process per robot, over Zenoh) records the same run as the lab.

Each broken rule is one line: the rule, the robot and tick where it broke, and what was seen.
"""

from __future__ import annotations

import importlib.util
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from services.policies.interface import CoordinationPolicy, Coordinator, Fleet, state_message
from services.policies.loading import make_policy, resolve

#: the rules, in the order they are checked
RULES = ("interface", "determinism", "own-view", "restore", "robustness", "state-size", "distributed")
#: seconds one decision (learn, candidate, probability, choose) may take at the kit's scale: a decision takes well
#: under a millisecond; the bound catches a policy that scales badly, not a busy machine
DECISION_LIMIT = 0.25
#: the per-tick columns the lab and a distributed run must agree on
SHARED_COLUMNS = ("deliveries_total", "requests", "commits", "links")


@dataclass(frozen=True)
class Finding:
    """One broken rule: where (robot, tick) and what was seen."""

    rule: str
    detail: str
    robot: int | None = None
    tick: int | None = None

    def __str__(self) -> str:
        where = []
        if self.robot is not None:
            where.append(f"robot {self.robot}")
        if self.tick is not None:
            where.append(f"tick {self.tick}")
        return f"{self.rule}: {', '.join(where) + ': ' if where else ''}{self.detail}"


class PolicyCheckFailed(AssertionError):
    """A policy broke one or more rules; ``findings`` lists them, the message has one line each."""

    def __init__(self, name: str, findings: Sequence[Finding]):
        self.findings = list(findings)
        super().__init__(f"policy {name!r} breaks {len(self.findings)} rule(s):\n"
                         + "\n".join(str(f) for f in self.findings))


class _Stop(Exception):
    """Raised through the lab when a policy's call raised: the episode ends there."""


# -- watching a policy's decisions ------------------------------------------------------------------------------------
class _Watch:
    """What the wrapped brains saw: the decisions, the slowest call, the first exception."""

    def __init__(self, limit: float):
        self.limit = limit
        self.decisions: list[tuple] = []
        self.slowest: tuple[float, int | None, int | None, str] = (0.0, None, None, "")
        self.error: Finding | None = None
        self.views: dict[int, list[tuple]] = {}  # robot -> what it was handed, in order (per-robot brains)
        self.tick: int | None = None  # the tick of the view learnt last

    def call(self, what: str, robot: int | None, tick: int | None, fn: Callable, *args):
        start = time.perf_counter()
        try:
            out = fn(*args)
        except _Stop:
            raise
        except Exception as exc:
            if self.error is None:
                self.error = Finding("robustness", f"{what} raised {type(exc).__name__}: {exc}", robot, tick)
            raise _Stop from None
        took = time.perf_counter() - start
        if took > self.slowest[0]:
            self.slowest = (took, robot, tick, what)
        return out


def _tick(obs) -> int | None:
    return None if obs is None else int(obs.t)


class _WatchedBrains:
    """A policy's brains with every decision recorded (delegates everything else)."""

    def __init__(self, inner: Coordinator, watch: _Watch):
        self._inner, self._watch = inner, watch
        self.draws, self.memoryless, self.broadcast = inner.draws, inner.memoryless, inner.broadcast
        self.fleet, self.owners = inner.fleet, inner.owners
        self._solo = int(inner.owners[0]) if len(inner.owners) == 1 else None

    def __getattr__(self, name: str):
        return getattr(self._inner, name)

    def learn(self, obs) -> None:
        self._watch.tick = _tick(obs)
        if self._solo is not None:
            self._watch.views.setdefault(self._solo, []).append(("learn", obs))
        self._watch.call("learn", self._solo, _tick(obs), self._inner.learn, obs)

    def receive(self, agent, mail) -> None:
        if self._solo is not None:
            self._watch.views.setdefault(self._solo, []).append(("receive", agent, list(mail)))
        self._watch.decisions.append((self._watch.tick, agent, "receive",
                                      tuple((m.sender, m.t, repr(sorted(m.data.items()))) for m in mail)))
        self._watch.call("receive", agent, None, self._inner.receive, agent, mail)

    def take_outbox(self, agent):
        out = self._watch.call("send", agent, None, self._inner.take_outbox, agent)
        if out:
            self._watch.decisions.append((self._watch.tick, agent, "send", tuple(out)))
        return out

    def candidate(self, agv, obs, free=None) -> int:
        out = self._watch.call("candidate", agv, _tick(obs), self._inner.candidate, agv, obs, free)
        self._watch.decisions.append((_tick(obs), agv, "candidate", int(out)))
        if self._solo is not None:
            self._watch.views[self._solo].append(("candidate", agv, obs, None if free is None else free.copy(), out))
        return out

    def probability(self, agv, picker, obs) -> float:
        out = self._watch.call("probability", agv, _tick(obs), self._inner.probability, agv, picker, obs)
        self._watch.decisions.append((_tick(obs), agv, "probability", int(picker), float(out)))
        if self._solo is not None:
            self._watch.views[self._solo].append(("probability", agv, picker, obs, out))
        return out

    def choose(self, picker, agvs, obs) -> int:
        out = self._watch.call("choose", picker, _tick(obs), self._inner.choose, picker, agvs, obs)
        self._watch.decisions.append((_tick(obs), picker, "choose", tuple(agvs), out))
        if self._solo is not None:
            self._watch.views.setdefault(picker, []).append(("choose", picker, list(agvs), obs, out))
        return out


def _isolated(name: str, options: Mapping[str, Any]) -> CoordinationPolicy:
    """The policy built from a private copy of its module: what a robot in a process of its own would run. Module
    state (a global a policy reads or writes) is then the robot's alone, as it is in a distributed run."""
    cls = resolve(name)
    spec = importlib.util.find_spec(cls.__module__)
    if spec is None or spec.loader is None:
        return cls.from_options(options)
    copy = importlib.util.module_from_spec(spec)
    original = sys.modules.get(cls.__module__)
    sys.modules[cls.__module__] = copy  # while it runs: its dataclasses and pydantic models look themselves up there
    try:
        spec.loader.exec_module(copy)
    finally:
        if original is not None:
            sys.modules[cls.__module__] = original
        else:
            sys.modules.pop(cls.__module__, None)
    fresh = copy
    for part in cls.__qualname__.split("."):
        fresh = getattr(fresh, part)
    return fresh.from_options(options)


class _Watched(CoordinationPolicy):
    """A policy whose brains are watched; each ``brains`` call builds them from a private copy of the policy's
    module (one for the fleet's brain, one per robot for per-robot brains)."""

    def __init__(self, name: str, options: Mapping[str, Any], watch: _Watch):
        self.inner = make_policy(name, options)
        self.policy_name, self.options_given, self.watch = name, options, watch
        self.name = self.inner.name
        self.broadcast = self.inner.broadcast

    def brains(self, fleet, owners, seed):
        inner = _isolated(self.policy_name, self.options_given)
        return _WatchedBrains(inner.brains(fleet, owners, seed), self.watch)


# -- the rules ----------------------------------------------------------------------------------------------------------
@dataclass
class _Setup:
    name: str
    options: dict[str, Any]
    scale: str
    steps: int
    seed: int
    limit: float

    def policy(self) -> CoordinationPolicy:
        return make_policy(self.name, self.options)

    def spec(self, **fields):
        from morph_sim.lab.runner import EpisodeSpec

        return EpisodeSpec(scale=self.scale, condition="policy-check", seed=self.seed, steps=self.steps,
                           policy_name=self.name, policy_options=self.options, compare_dispatch=False, **fields)

    def episode(self, **fields):
        """(watch, result or None) of one lab episode."""
        from morph_sim.lab.runner import run_episode

        watch = _Watch(self.limit)
        try:
            result = run_episode(self.spec(**fields), policy=_Watched(self.name, self.options, watch))
        except _Stop:
            return watch, None
        return watch, result


def _interface(setup: _Setup) -> list[Finding]:
    from services.world.cta import CTAController
    from services.world.warehouse import Warehouse, WarehouseConfig

    try:
        policy = setup.policy()
    except Exception as exc:
        return [Finding("interface", f"the policy does not build from these options: {type(exc).__name__}: {exc}")]
    cta = CTAController(Warehouse(WarehouseConfig.named(setup.scale, max_steps=setup.steps + 1)))
    cta.reset(setup.seed)
    fleet = Fleet(cta.n_agvs, cta.n_pickers, setup.scale)
    out: list[Finding] = []
    obs = cta.begin_tick()
    for owners in ([0], list(range(fleet.n))):
        try:
            brains = policy.brains(fleet, owners, setup.seed)
            brains.learn(obs)
            rows = np.asarray(brains.link_rows())
            weights = np.asarray(brains.weight_rows())
        except Exception as exc:
            return [Finding("interface", f"brains for robots {owners[:3]}…: {type(exc).__name__}: {exc}")]
        for what, arr in (("link_rows", rows), ("weight_rows", weights)):
            if arr.shape != (len(owners), fleet.n):
                out.append(Finding("interface", f"{what} has shape {arr.shape}, not {(len(owners), fleet.n)}",
                                   owners[0] if len(owners) == 1 else None, int(obs.t)))
    brains = policy.brains(fleet, range(fleet.n), setup.seed)
    brains.learn(obs)
    for agv in range(fleet.n_agvs):
        picker = brains.candidate(agv, obs)
        if picker != -1 and not (fleet.n_agvs <= picker < fleet.n and obs.free_picker[picker]):
            out.append(Finding("interface", f"candidate {picker} is not a free picker (nor -1)", agv, int(obs.t)))
            continue
        if picker >= 0:
            p = brains.probability(agv, picker, obs)
            if not (isinstance(p, float | int | np.floating) and math.isfinite(p) and 0.0 <= p <= 1.0):
                out.append(Finding("interface", f"probability {p!r} is not a number in [0, 1]", agv, int(obs.t)))
    for picker in range(fleet.n_agvs, fleet.n):
        k = brains.choose(picker, [0, 1][: fleet.n_agvs], obs)
        if not isinstance(k, int | np.integer) or not -1 <= k < min(2, fleet.n_agvs):
            out.append(Finding("interface", f"choose returned {k!r}, not an index of the requests or -1", picker,
                               int(obs.t)))
    return out


def _first_difference(a: list[tuple], b: list[tuple], rule: str, what: str) -> Finding | None:
    """The first decision where ``a`` and ``b`` part; ``what`` says how they were run, with {a} and {b}."""
    for x, y in zip(a, b):
        if x != y:
            return Finding(rule, what.format(a=_shown(x), b=_shown(y)), x[1], x[0])
    if len(a) != len(b):
        longer = a if len(a) > len(b) else b
        x = longer[min(len(a), len(b))]
        return Finding(rule, f"{what}: one run made {len(a)} decisions, the other {len(b)}", x[1], x[0])
    return None


def _shown(decision: tuple) -> str:
    kind, rest = decision[2], decision[3:]
    if kind == "probability":
        return f"P(ask picker {rest[0]}) = {rest[1]:.6g}"
    if kind == "candidate":
        return f"candidate picker {rest[0]}"
    if kind == "send":
        return f"sent {len(rest[0])} message(s) to {[to for to, _ in rest[0]]}"
    if kind == "receive":
        return f"received {len(rest[0])} message(s) from {[m[0] for m in rest[0]]}"
    return f"choice {rest[1]} of AGVs {list(rest[0])}"


def _restore(setup: _Setup, watch: _Watch) -> list[Finding]:
    """Replay what each robot was handed: a brain restored at mid-episode from the fleet's published states against
    the brain that never stopped, on the same inputs after the cut."""
    from services.world.layout import named_sizes

    _, n_agvs, n_pickers = named_sizes()[setup.scale][:3]
    fleet = Fleet(n_agvs, n_pickers, setup.scale)
    # the cut: after the learn of this tick's view (a state is published after a decision point's learning)
    cut = max(1, setup.steps // 2)
    running = {r: _isolated(setup.name, setup.options).brains(fleet, [r], setup.seed) for r in range(fleet.n)}
    position: dict[int, int] = {}
    for r, events in watch.views.items():
        position[r] = len(events)
        for i, event in enumerate(events):
            if event[0] == "learn" and event[1].t > cut:
                position[r] = i
                break
            _replay(running[r], event)
    states = {r: state_message(brains, r, "agv" if fleet.is_agv(r) else "picker", cut)
              for r, brains in running.items()}
    out: list[Finding] = []
    from schemas.codec import encode
    from schemas.limits import max_payload

    bound = max_payload(["agent", "0", "state"])
    for r, st in states.items():
        size = len(encode(st))
        if size > bound:
            out.append(Finding("state-size", f"its state is {size} bytes, the bound is {bound}", r, cut))
    for r, events in watch.views.items():
        restored = _isolated(setup.name, setup.options).brains(fleet, [r], setup.seed)
        try:
            restored.restore(r, states)
        except Exception as exc:
            out.append(Finding("restore", f"restore raised {type(exc).__name__}: {exc}", r, cut))
            continue
        for event in events[position[r]:]:
            want = _replay(running[r], event)
            got = _replay(restored, event)
            if event[0] not in ("learn", "receive") and not _same(want, got):
                view = event[2] if event[0] == "candidate" else event[3]
                out.append(Finding("restore", f"{event[0]} {_plain(got)} after restoring from the states of tick "
                                   f"{cut}, {_plain(want)} without a restart", r, _tick(view)))
                break
    return out


def _plain(value) -> str:
    return f"{float(value):.6g}" if isinstance(value, float | np.floating) else str(value)


def _replay(brains: Coordinator, event: tuple):
    kind = event[0]
    if kind == "learn":
        brains.learn(event[1])
        brains.take_outbox(int(brains.owners[0]))  # what it sends goes nowhere here
        return None
    if kind == "receive":
        return brains.receive(event[1], event[2])
    if kind == "candidate":
        _, agv, obs, free, _ = event
        return brains.candidate(agv, obs, free)
    if kind == "probability":
        _, agv, picker, obs, _ = event
        return brains.probability(agv, picker, obs)
    _, picker, agvs, obs, _ = event
    return brains.choose(picker, agvs, obs)


def _same(a, b) -> bool:
    if isinstance(a, float | np.floating) or isinstance(b, float | np.floating):
        return math.isclose(float(a), float(b), rel_tol=1e-9, abs_tol=1e-12)
    return a == b


def _distributed(setup: _Setup, lab) -> list[Finding]:
    """``morph-sim up`` of the same episode, its metrics.csv against the lab's tick table."""
    import csv

    options = [a for k, v in setup.options.items() for a in ("--policy-option", f"{k}={_option_text(v)}")]
    with tempfile.TemporaryDirectory(prefix="morph-policy-check-") as out:
        cmd = [sys.executable, "-m", "morph_sim.cli", "up", "--scale", setup.scale, "--steps", str(setup.steps),
               "--seed", str(setup.seed), "--policy", setup.name, *options, "--run-id", "check", "--output-dir", out,
               "--quiet", "--insecure"]
        try:
            done = subprocess.run(cmd, capture_output=True, text=True, timeout=max(120, setup.steps),
                                  env={**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (os.getcwd(),
                                       os.environ.get("PYTHONPATH", "")) if p)})
        except subprocess.TimeoutExpired:
            return [Finding("distributed", "morph-sim up did not finish in time")]
        if done.returncode != 0:
            last = (done.stderr.strip().splitlines() or ["(no output)"])[-1]
            return [Finding("distributed", f"morph-sim up exited {done.returncode}: {last}")]
        with open(Path(out) / "check" / "metrics.csv", newline="") as f:
            rows = list(csv.DictReader(f))
    for t, row in enumerate(rows):
        for col in SHARED_COLUMNS:
            want = float(lab.ticks[col][t])
            got = float(row[col]) if row.get(col) not in (None, "") else float("nan")
            if not (want == got or (math.isnan(want) and math.isnan(got))):
                return [Finding("distributed", f"{col}: {got:g} in morph-sim up, {want:g} in the lab", tick=t)]
    if len(rows) != setup.steps:
        return [Finding("distributed", f"morph-sim up recorded {len(rows)} ticks of {setup.steps}")]
    return []


def _option_text(value: Any) -> str:
    from services.runconfig import option_text

    return option_text(value)


# -- entry points -------------------------------------------------------------------------------------------------------
def policy_findings(policy: str | type[CoordinationPolicy], options: Mapping[str, Any] | None = None, *,
                    scale: str = "tiny", steps: int = 120, seed: int = 1, distributed: bool = True,
                    decision_limit: float = DECISION_LIMIT) -> list[Finding]:
    """Every broken rule of ``policy`` (a name ``--policy`` takes, or a policy class importable by its module path);
    empty when it conforms."""
    name = policy if isinstance(policy, str) else f"{policy.__module__}:{policy.__qualname__}"
    try:
        resolve(name)
        setup = _Setup(name, dict(options or {}), scale, steps, seed, decision_limit)
        setup.policy()
    except ValueError as exc:
        return [Finding("interface", str(exc))]
    found = _interface(setup)
    if found:
        return found
    first, lab = setup.episode()
    if lab is None:
        return [first.error] if first.error else [Finding("robustness", "the episode stopped")]
    again, _ = setup.episode()
    found += [f for f in [again.error, _first_difference(first.decisions, again.decisions, "determinism",
                                                         "the same seed decided {a} in one episode, {b} in the next")] if f]
    solo, solo_result = setup.episode(per_robot_brains=True)
    if solo_result is None:
        found.append(solo.error or Finding("robustness", "the episode stopped"))
    else:
        diff = _first_difference(first.decisions, solo.decisions, "own-view",
                                 "with one brain for the fleet it decided {a}, with a brain (and a copy of the policy's "
                                 "module) of its own {b}")
        if diff:
            found.append(diff)
        found += _restore(setup, solo)
    found += _robustness(setup)
    if distributed and not found:
        if name.startswith("__main__:"):
            found.append(Finding("distributed", "a policy defined in __main__ cannot be loaded by other processes; "
                                 "put it in a module"))
        else:
            found += _distributed(setup, lab)
    return found


def _robustness(setup: _Setup) -> list[Finding]:
    """An episode under lost and late fleet views and lost dispatch messages (hence refusals and expiries)."""
    from morph_sim.lab.network import FLEET_KEY
    from schemas.faults import FaultSpec, Latency, Loss, Scope

    faults = (
        FaultSpec(id="views-lost", seed=setup.seed, scope=Scope(key_expr=FLEET_KEY),
                  loss=Loss(model="bernoulli", percent=30.0)),
        FaultSpec(id="views-late", seed=setup.seed, scope=Scope(key_expr=FLEET_KEY),
                  latency=Latency(delay=2.5, jitter=1.0)),
    )
    watch, result = setup.episode(faults=faults, loss_percent=20.0)
    out = []
    if result is None and watch.error is not None:
        out.append(watch.error)
    took, robot, tick, what = watch.slowest
    if took > setup.limit:
        out.append(Finding("robustness", f"{what} took {took * 1000:.1f} ms, the bound is {setup.limit * 1000:.0f} ms",
                           robot, tick))
    return out


def check_policy(policy: str | type[CoordinationPolicy], options: Mapping[str, Any] | None = None, **kwargs: Any
                 ) -> None:
    """Raise :class:`PolicyCheckFailed` (one line per broken rule) unless ``policy`` conforms; for a policy
    package's own tests (``morph-sim policy new`` writes one). Keywords as :func:`policy_findings`."""
    found = policy_findings(policy, options, **kwargs)
    if found:
        name = policy if isinstance(policy, str) else policy.__qualname__
        raise PolicyCheckFailed(name, found)


__all__ = ["DECISION_LIMIT", "RULES", "Finding", "PolicyCheckFailed", "check_policy", "policy_findings"]
