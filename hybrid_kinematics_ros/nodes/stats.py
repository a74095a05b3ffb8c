"""Request counters and latency percentiles for the kinematics node's diagnostics (no ROS here).

Services answer on two threads (FK on one, IK and reload on another), so every update takes a lock.
Latencies are kept for the most recent requests only: the percentiles describe the node now, not since
its start.
"""

from __future__ import annotations

import threading
from collections import deque

import numpy as np

WINDOW = 1000  # most recent requests per service whose latencies make the percentiles
PERCENTILES = (50, 90, 99)


class RequestStats:
    def __init__(self, services: tuple[str, ...] = ("fk", "ik"), window: int = WINDOW) -> None:
        self._lock = threading.Lock()
        self.served = dict.fromkeys(services, 0)
        self.failed = dict.fromkeys(services, 0)
        self.out_of_range = 0  # configurations (FK) or solutions (IK) outside the calibrated range
        self._latency = {name: deque(maxlen=window) for name in services}

    def record(self, service: str, seconds: float, success: bool, out_of_range: int = 0) -> None:
        with self._lock:
            self.served[service] += 1
            self.failed[service] += 0 if success else 1
            self.out_of_range += out_of_range
            self._latency[service].append(seconds)

    def snapshot(self) -> dict[str, str]:
        """Key-value pairs as diagnostics carry them; latencies in ms over the recent window."""
        with self._lock:
            out = {"out_of_range_count": str(self.out_of_range)}
            for name, latencies in self._latency.items():
                out[f"{name}_requests_served"] = str(self.served[name])
                out[f"{name}_requests_failed"] = str(self.failed[name])
                values = np.fromiter(latencies, dtype=float)
                for p in PERCENTILES:
                    value = f"{1e3 * np.percentile(values, p):.3f}" if len(values) else "nan"
                    out[f"{name}_latency_p{p}_ms"] = value
        return out
