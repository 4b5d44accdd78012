"""Distances to straight paths: how near a point comes to a vehicle flying straight from one place to
another (the gateways' separation rule, the swarm's assignment of targets)."""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["segment_distance"]


def segment_distance(a: Sequence[float], b: Sequence[float], q: Sequence[float]) -> float:
    """Distance from point ``q`` to the segment ``a``–``b`` (points of any one dimension)."""
    ab = [y - x for x, y in zip(a, b, strict=True)]
    aq = [y - x for x, y in zip(a, q, strict=True)]
    n2 = sum(x * x for x in ab)
    k = 0.0 if n2 == 0.0 else max(0.0, min(1.0, sum(x * y for x, y in zip(ab, aq, strict=True)) / n2))
    return math.dist(q, [x + k * d for x, d in zip(a, ab, strict=True)])
