"""The catalogue of metrics: every metric of a run defined once (name, unit, help, how it is computed).

The monitor's per-tick rows (``metrics.csv`` columns), its metric streams ``metrics/<name>`` (with the unit on the
wire), the Prometheus exporter, the README's table of streams and the lab's W-block summaries all read this module;
nothing else lists metric names. Each entry says where its value comes from:

* ``row`` — the monitor's per-tick row, from the sim's ticks and the agents' acks, commits and state rows (the
  dispatch outcomes: the sim's counters on its ticks plus each robot's on its acks);
* ``messages`` — the monitor's statistics of the messages themselves (counts, sequence gaps, latency, dispatch);
* ``link`` — the per key class link statistics (``services.faults.linkstats``), every ``--state-every`` ticks;
* ``network`` — the network model's counters, under a network profile (``--network``);
* ``air`` — the shared air's counters per access point, under a profile with rate-limited queues (label ``ap``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from schemas import MetricSample

RATE_WINDOW = 50  # ticks of the sliding window of delivery_rate
#: per key class counters of the link statistics and what each counts
LINK_COUNTERS = {
    "sent": "messages sent (highest sequence number + 1)",
    "delivered": "messages delivered (duplicates included)",
    "dropped": "messages lost (sent − distinct delivered)",
    "duplicated": "extra copies delivered",
    "late": "messages delivered after their phase deadline",
}
LINK_LATENCIES = ("mean", "p50", "p90", "p99", "max")
#: what became of the dispatch protocol's messages (services.protocol.dispatch.Outcomes), cumulative up to the end of
#: step t: the sim's counters (on its ticks) plus the robots' (on their acks, which are never faulted)
DISPATCH_OUTCOMES = {
    "on_time": "commitments applied at the boundary of the step they were sent in",
    "late_applied": "commitments applied at a later step boundary (late, not lost)",
    "expired": "help requests unanswered within the AGV's request timeout",
    "commitment_expired": "picker commitments neither applied nor refused within the timeout",
    "refused_stale": "commitments no longer valid when they reached the sim (refused, both sides told)",
    "duplicates": "copies of a request or commitment already seen (counted once)",
    "declined": "help requests a picker answered with no",
}


@dataclass(frozen=True)
class Metric:
    name: str
    unit: str
    help: str
    source: str  # "row" | "messages" | "link" | "network" | "air" (module docstring)
    #: Prometheus family name (counters without the ``_total`` the client adds) and type, if exported
    prometheus: str | None = None
    kind: str = "gauge"  # "gauge" | "counter" | "histogram"


#: Row metrics first, in the column order of ``metrics.csv`` (after ``t`` and ``sim_time``).
CATALOGUE: tuple[Metric, ...] = (
    Metric("deliveries", "deliveries", "shelves delivered in step t", "row"),
    Metric("deliveries_total", "deliveries", "cumulative deliveries up to step t", "row",
           "morph_deliveries", "counter"),
    Metric("requests", "messages", "help requests sent in tick t", "row"),
    Metric("commits", "messages", "picker commitments in tick t", "row"),
    Metric("links", "links", "undirected coordination links after the update of step t", "row", "morph_links"),
    Metric("lambda2", "1", "algebraic connectivity λ₂ of the link graph", "row", "morph_lambda2"),
    Metric("eta", "1", "mean neuromodulation signal η over the agents (plastic policies)", "row", "morph_eta"),
    Metric("acks", "agents", "agents that acknowledged tick t", "row"),
    # what the robots knew of each other at tick t: the age of each agent's latest fleet broadcast at its decision
    # point (0 when every broadcast arrives in its tick; grows while an agent's broadcasts are late or lost)
    Metric("view_age_mean", "s", "mean age of the agents' fleet views at their decision point of tick t", "row",
           "morph_view_age_mean_seconds"),
    Metric("view_age_max", "s", "largest age of an agent's fleet view at tick t", "row",
           "morph_view_age_max_seconds"),
    Metric("w_agv_agv", "1", "mean W between AGVs (every --state-every ticks)", "row", "morph_w_agv_agv"),
    Metric("w_agv_picker", "1", "mean W between AGVs and pickers", "row", "morph_w_agv_picker"),
    Metric("w_picker_picker", "1", "mean W between pickers", "row", "morph_w_picker_picker"),
    *(Metric(f"dispatch_{name}", "messages", f"cumulative {what}", "row", f"morph_dispatch_{name}", "counter")
      for name, what in DISPATCH_OUTCOMES.items()),
    Metric("delivery_rate", "deliveries/s", f"deliveries per sim second over the last {RATE_WINDOW} steps",
           "messages", "morph_delivery_rate_per_second"),
    Metric("agents_alive", "agents", "agents heard from (acked) in tick t; labels: the missing ids", "messages",
           "morph_agents_alive"),
    Metric("dispatch_delay", "s", "mean sim seconds from an AGV's first help request to a picker's commit, step t",
           "messages", "morph_dispatch_delay_seconds", "histogram"),
    Metric("messages_total", "messages", "messages seen by the monitor; labels: count per kind", "messages",
           "morph_messages", "counter"),
    Metric("drops_total", "messages", "messages lost: sequence gaps per sender and key, plus rejected payloads",
           "messages", "morph_dropped_messages", "counter"),
    Metric("refused_by_robot", "messages", "robots' messages the monitor refused, cumulative; labels: count per robot "
           "id (a robot that floods the run stands out by name)", "messages", "morph_refused_robot_messages",
           "counter"),
    Metric("latency_seconds", "s", "bus latency publish→monitor over the last second: values = [p50, p90, p99]",
           "messages", "morph_bus_latency_seconds", "histogram"),
    *(Metric(f"link/{c}", "messages", f"cumulative {what} per key class; labels: key, receiver", "link")
      for c, what in LINK_COUNTERS.items()),
    *(Metric(f"link/latency/{q}", "s", f"observed latency per key class: {q} since the start", "link")
      for q in LINK_LATENCIES),
    # with a network profile (--network): the robots' Wi-Fi as they drive through it (docs/faults.md)
    Metric("net/handovers", "hand-overs", "with `--network`: cumulative access-point hand-overs of all robots",
           "network"),
    Metric("net/in_outage", "robots", "with `--network`: robots whose radio is in a hand-over outage at step t",
           "network"),
    Metric("net/outage_seconds", "s", "with `--network`: cumulative hand-over outage, all robots", "network"),
    Metric("net/stopped", "robots",
           "with `--network`: robots held in place at step t, silent for the profile's `silence_stop`", "network"),
    # with a rate-limited profile (congested): each access point's shared medium, as the air judged it (label ap)
    Metric("net/ap_load", "B/s", "rate-limited profile: bytes the access point took in per sim second over the last "
           "step; label ap", "air", "morph_net_ap_load_bytes_per_second"),
    Metric("net/ap_queue", "messages", "rate-limited profile: messages in the access point's queue at the start of "
           "step t; label ap", "air", "morph_net_ap_queue_messages"),
    Metric("net/ap_drops", "messages", "rate-limited profile: messages the access point dropped with a full queue, "
           "cumulative; label ap", "air", "morph_net_ap_drops", "counter"),
)

BY_NAME: dict[str, Metric] = {m.name: m for m in CATALOGUE}
NAMES: tuple[str, ...] = tuple(m.name for m in CATALOGUE)
#: the per-tick row's metrics, in ``metrics.csv`` column order
ROW: tuple[str, ...] = tuple(m.name for m in CATALOGUE if m.source == "row")
#: the columns of ``metrics.csv``
COLUMNS: tuple[str, ...] = ("t", "sim_time", *ROW)
#: mean W per role block: the names the monitor's rows and the lab's summaries give them
W_BLOCKS: tuple[str, ...] = ("w_agv_agv", "w_agv_picker", "w_picker_picker")


#: Lab-only columns of the lab's tick table (``EpisodeResult.ticks``, ``ms.episode(...).ticks``, a study's
#: ``ticks.csv``), one value per step t like the rows. The lab's other columns are the row metrics above, under their
#: names and meanings; these have no counterpart in a run record and names no row metric uses.
LAB_TICK_METRICS: tuple[Metric, ...] = (
    Metric("links_directed", "links", "directed coordination links (i→j) after the update of step t", "lab"),
    Metric("mean_w_links", "1", "mean W over the linked pairs after the update of step t (1 for Full-Graph, 0 for "
           "the other memoryless policies)", "lab"),
    Metric("fiedler_ref", "1", "the reference code's λ₂: Fiedler value of the normalised Laplacian of the link graph "
           "(NaN between the steps it is computed at)", "lab"),
    Metric("gate_p_sum", "1", "cumulative Σ P(respond) over the gate decisions up to step t", "lab"),
    Metric("h_mean", "1", "mean homeostatic threshold h over the agents (MORPH)", "lab"),
    Metric("formed", "links", "mean links formed per agent in the update of step t (MORPH)", "lab"),
    Metric("pruned", "links", "mean links pruned per agent in the update of step t (MORPH)", "lab"),
)
LAB_TICKS: tuple[str, ...] = tuple(m.name for m in LAB_TICK_METRICS)

#: Per-episode metrics: the columns of the sweep's tidy table and of the studies' episode tables, one value per
#: episode, each the episode's aggregate of the row metric of the same name where there is one (``deliveries``: the
#: episode's deliveries, the last row's ``deliveries_total``; ``commits``: Σ of the rows' ``commits``).
EPISODE_METRICS: tuple[Metric, ...] = (
    Metric("deliveries", "deliveries", "shelves delivered in the episode (Σ deliveries = the last deliveries_total)",
           "episode"),
    Metric("mean_links", "links", "mean over the steps of links", "episode"),
    Metric("requests", "messages", "help requests sent in the episode (Σ requests)", "episode"),
    Metric("commits", "messages", "picker commitments in the episode (Σ commits)", "episode"),
    Metric("eta_mean", "1", "mean over the steps of eta (plastic policies)", "episode"),
    Metric("median_lifetime", "steps", "median lifetime of a link event (a pair linked without a break)", "episode"),
    Metric("dispatch_delay", "s", "mean sim seconds (= ticks: the lab's step is 1 s) from an AGV's first help "
           "request to a picker's commitment", "episode"),
    Metric("messages_per_delivery", "messages", "dispatch messages sent per delivery", "episode"),
    Metric("bytes_per_delivery", "bytes", "dispatch bytes sent per delivery", "episode"),
    Metric("view_age_mean", "s", "mean over the steps of view_age_mean", "episode"),
    Metric("messages_dropped", "messages", "dispatch messages lost in the episode", "episode"),
    Metric("network_handovers", "hand-overs", "with a network profile: access-point hand-overs of all robots",
           "episode"),
    Metric("network_outage_seconds", "s", "with a network profile: hand-over outage, all robots", "episode"),
    Metric("network_stops", "robot-steps", "with a network profile: steps robots were held, silent too long",
           "episode"),
    # measured inside the agents' gates: only the lab's in-process episode sees them
    Metric("lab_gate_decisions", "decisions", "lab only: gate evaluations (a request that reached a candidate)",
           "episode"),
    Metric("lab_mean_p_respond", "1", "lab only: mean P(respond) over the gate decisions", "episode"),
)
EPISODE_BY_NAME: dict[str, Metric] = {m.name: m for m in EPISODE_METRICS}


def episode_metrics(*names: str) -> tuple[str, ...]:
    """A study's per-episode metric columns, checked against :data:`EPISODE_METRICS` (KeyError naming an unknown)."""
    for name in names:
        if name not in EPISODE_BY_NAME:
            raise KeyError(f"{name}: not a per-episode metric of the catalogue")
    return names


#: what every study of dispatch under faults measures per episode (the fault and network studies)
COST_METRICS = episode_metrics("deliveries", "mean_links", "dispatch_delay", "messages_per_delivery",
                               "bytes_per_delivery", "view_age_mean")


def unit(name: str) -> str | None:
    """The unit of stream ``name`` (None for a name outside the catalogue)."""
    metric = BY_NAME.get(name)
    return metric.unit if metric else None


def sample(name: str, t: int, sim_time: float, **fields) -> MetricSample:
    """A sample of stream ``name`` with the catalogue's unit on it (``value=…`` or ``values=…``, ``labels=…``)."""
    return MetricSample(name=name, t=t, sim_time=sim_time, unit=BY_NAME[name].unit, **fields)


def w_block_values(blocks) -> dict[str, float | None]:
    """The W block means of a :class:`~services.metrics.measures.BlockMeans` (or None) under their metric names."""
    if blocks is None:
        return dict.fromkeys(W_BLOCKS)
    return {"w_agv_agv": blocks.agv_agv, "w_agv_picker": blocks.agv_picker, "w_picker_picker": blocks.picker_picker}


def outcome_values(counts: Mapping[str, int]) -> dict[str, int]:
    """The dispatch outcome columns of a row from the protocol's counters (``Outcomes.as_dict()``)."""
    return {f"dispatch_{name}": int(counts.get(name, 0)) for name in DISPATCH_OUTCOMES}


def markdown_table() -> str:
    """The README's table of metric streams (a test checks the README holds exactly this)."""
    lines = ["| stream | unit | meaning |", "|---|---|---|"]
    lines += [f"| `{m.name}` | {m.unit} | {m.help} |" for m in CATALOGUE]
    return "\n".join(lines)


def prometheus_names() -> list[str]:
    """The exported Prometheus family names as a scraper sees them (counters with ``_total``)."""
    return [m.prometheus + ("_total" if m.kind == "counter" else "") for m in CATALOGUE if m.prometheus]
