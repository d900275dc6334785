"""The monitor's latest-state queryable: what a late joiner asks for with ``get`` on ``state/**``.

It answers with the run's configuration (``state/config``, for a recorder that joins: replay needs it), the latest
sample of every metric stream (``state/metrics/<name>``) and each agent's newest state (``state/agent/<id>``, from
which a restarted agent restores itself).
"""

from __future__ import annotations

from schemas import AgentState, Event, MetricSample
from schemas.keys import RunKeys, intersects
from services.bus.base import Query
from services.runconfig import RunConfig


class LatestState:
    """The latest state of the run of ``config``; ``metrics`` is the publisher's latest sample per stream."""

    def __init__(self, config: RunConfig, keys: RunKeys, metrics: dict[str, MetricSample]):
        self.config = config
        self.keys = keys
        self.metrics = metrics
        self.agents: dict[int, AgentState] = {}

    def agent(self, state: AgentState) -> None:
        """Keep ``state`` if it is its agent's newest."""
        prev = self.agents.get(state.agent)
        if prev is None or state.t >= prev.t:
            self.agents[state.agent] = state

    def answer(self, query: Query, t: int) -> None:
        """Reply to ``query`` with every latest value its key expression takes; ``t``: the run's newest tick."""
        key = self.keys.latest("config")
        if intersects(key, query.key_expr):
            query.reply(key, Event(kind="run.config", source="monitor", t=max(t, 0),
                                   details={"config": self.config.model_dump(mode="json")}))
        metrics, states = list(self.metrics.items()), sorted(self.agents.items())
        for name, sample in metrics:
            key = self.keys.latest("metrics", name)
            if intersects(key, query.key_expr):
                query.reply(key, sample)
        for agent, state in states:
            key = self.keys.latest("agent", str(agent))
            if intersects(key, query.key_expr):
                query.reply(key, state)
