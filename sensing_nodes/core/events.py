"""The one event order: samples of several stamped streams as one stream, in the order the
graph's consumers see them (the fusion's reorder buffer releases its inputs in it:
core/fusion/timeline.py).

Stamp order (int64 ns); samples of one stamp in the streams' rank (the order they are given in:
wheels or joints, then the IMU, then scans, as RANK in core/fusion/inputs.py), those of one stream
in their own order. The simulator's input chain (core/sim/inputs.py), the evaluation's readings
(core/evaluation/fusion.py) and the benchmarks' merged inputs take their order from here.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class Event:
    """One sample of a stream: its stamp (ns), the stream's name and its index in the stream."""

    stamp_ns: int
    source: str
    index: int


def time_ordered(streams: Mapping[str, Sequence[int] | np.ndarray]) -> list[Event]:
    """Every sample of the streams (name -> stamps ns, ranked in the mapping's order) as Events
    in the one event order: by stamp, then stream rank, then index."""
    names = list(streams)
    stamps = [np.asarray(streams[name], dtype=np.int64).reshape(-1) for name in names]
    if not any(s.size for s in stamps):
        return []
    stamp = np.concatenate(stamps)
    rank = np.concatenate([np.full(s.size, r, dtype=np.int64) for r, s in enumerate(stamps)])
    index = np.concatenate([np.arange(s.size, dtype=np.int64) for s in stamps])
    order = np.lexsort((index, rank, stamp))   # the last key is the primary one
    return [Event(t, names[r], i) for t, r, i in zip(stamp[order].tolist(),
                                                      rank[order].tolist(),
                                                      index[order].tolist())]
