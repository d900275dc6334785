"""The latency distributions of a fault spec, as plain functions: what the fault layer draws from and what the
network model adds on top of a profile. Kept apart from the layer so both import it without importing each other."""

from __future__ import annotations

import math
from statistics import NormalDist

from schemas.faults import Latency

_STD_NORMAL = NormalDist()
_EPS = 1e-12


def pareto_params(mean: float, std: float) -> tuple[float, float]:
    """(shape a, scale xm) of the Pareto distribution with this mean and standard deviation."""
    a = 1.0 + math.sqrt(1.0 + (mean / std) ** 2)
    return a, mean * (a - 1.0) / a


def latency_quantile(lat: Latency, q: float) -> float:
    """Quantile ``q`` of the configured latency distribution (no correlation), in seconds."""
    q = min(max(q, _EPS), 1.0 - _EPS)
    if lat.jitter == 0.0:
        return lat.delay
    if lat.distribution == "uniform":
        return lat.delay - lat.jitter + 2.0 * lat.jitter * q
    if lat.distribution == "normal":
        return max(0.0, lat.delay + lat.jitter * _STD_NORMAL.inv_cdf(q))
    if lat.delay == 0.0:
        return 0.0
    a, xm = pareto_params(lat.delay, lat.jitter)
    return xm * (1.0 - q) ** (-1.0 / a)
