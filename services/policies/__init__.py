"""Coordination as pure code: which robot asks which for help, and what it learns from the answer.

MORPH's plasticity (:mod:`.plasticity`), its parameter presets as TOML data (:mod:`.presets`, ``presets/*.toml``)
and every coordination policy with the one list of their names (:mod:`.coordinators`). No I/O and no bus: an agent
process (:mod:`services.agent`) and the in-process lab drive the same objects.
"""
