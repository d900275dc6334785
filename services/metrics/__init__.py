"""Measuring a run as pure code: the metric catalogue (:mod:`.catalogue`, the one source of every metric's name, unit
and meaning) and the measures computed from a run's state (:mod:`.measures`: links, connectivity, block means,
delivery rates, recovery times, statistics). The monitor, ``replay``, the lab and the studies all use them. The rows
of a run's record are reduced from its messages here too (:mod:`.rows`, the monitor's and ``replay``'s).
"""
