"""The world as the sim sends it: what a Tick carries beyond the robots' observation, and the controller of a run.

Pure conversion from the world's state (``services.world``) to the fields of the wire messages (``schemas.tick``);
the sim service publishes what these return.
"""

from __future__ import annotations

import logging

import numpy as np

from schemas.tick import TickObservation
from services.runconfig import RunConfig
from services.world.cta import CTAController
from services.world.warehouse import Warehouse, WarehouseConfig

log = logging.getLogger("morph_sim.sim")


def world_fields(ctl: CTAController, obs: TickObservation) -> dict:
    """The Tick fields that describe the world beyond the observation (monitor, live views)."""
    wh = ctl.wh
    queue = set(wh.queue)
    partner = [-1] * ctl.n
    by_cell = {m.cell: p for p, m in ctl.picker_missions.items()}
    for agv, m in ctl.agv_missions.items():
        p = by_cell.get(m.cell)
        if p is not None:
            partner[agv] = int(p)  # plain ints: the sim packs this map without the model (encode_tick_body)
            partner[p] = int(agv)
    loads, unloads = handling_pairs(obs, wh.carrying)
    return dict(
        heading=[int(d) for d in wh.dir], busy=[bool(b) for b in wh.busy],
        carrying=[bool(c) for c in wh.carrying], carrying_requested=[bool(c) and c in queue for c in wh.carrying],
        partner=partner, request_queue=[int(q) for q in wh.queue], loads=loads, unloads=unloads,
        deliveries_total=int(ctl.deliveries),
    )


def handling_pairs(obs: TickObservation, carrying) -> tuple[list[tuple[int, int]], list[tuple[int, int]]]:
    """(AGV, picker) pairs that loaded / unloaded in step t−1, from the observation's ``handled`` robots.

    A load or unload always has the AGV and one picker on the same cell (cta.py), so the pairs carry ``handled``
    exactly; an unpaired handled robot would be a controller bug and is logged.
    """
    handled = getattr(obs, "handled", None)
    if handled is None:
        return [], []
    cells = obs.cells
    pickers = {(int(cells[p, 0]), int(cells[p, 1])): p for p in np.flatnonzero(handled[obs.n_agvs:]) + obs.n_agvs}
    loads, unloads, paired = [], [], set()
    for agv in np.flatnonzero(handled[: obs.n_agvs]):
        p = pickers.get((int(cells[agv, 0]), int(cells[agv, 1])))
        if p is None:
            continue
        (loads if carrying[agv] else unloads).append((int(agv), int(p)))
        paired.update((int(agv), int(p)))
    missing = set(np.flatnonzero(handled).tolist()) - paired
    if missing:
        log.error("sim: handled robots %s have no load/unload partner; agents will not see them", sorted(missing))
    return loads, unloads


def make_controller(config: RunConfig) -> CTAController:
    """The world of a run: a warehouse of the configured size and fleet, reset with the run's seed."""
    wh_cfg = WarehouseConfig.named(config.scale, config.n_agvs, config.n_pickers,
                                   max_steps=max(config.steps + 1, 500))
    ctl = CTAController(Warehouse(wh_cfg))
    ctl.reset(config.seed)
    return ctl
