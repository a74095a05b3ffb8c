"""The diagnostics' counters and percentiles, without ROS."""

from __future__ import annotations

import threading

import numpy as np

from hybrid_kinematics_ros.nodes.stats import RequestStats


def test_counts_and_percentiles_over_the_recent_window():
    stats = RequestStats(window=100)
    assert stats.snapshot()["fk_latency_p50_ms"] == "nan"
    latencies = np.random.default_rng(0).uniform(1e-4, 1e-2, 150)
    for i, seconds in enumerate(latencies):
        stats.record("fk", float(seconds), success=i % 10 != 0, out_of_range=1 if i < 5 else 0)
    snap = stats.snapshot()
    assert snap["fk_requests_served"] == "150" and snap["fk_requests_failed"] == "15"
    assert snap["out_of_range_count"] == "5" and snap["ik_requests_served"] == "0"
    assert float(snap["fk_latency_p90_ms"]) == float(f"{1e3 * np.percentile(latencies[-100:], 90):.3f}")


def test_two_threads_lose_no_count():
    stats = RequestStats()
    threads = [threading.Thread(target=lambda: [stats.record("ik", 1e-3, True) for _ in range(2000)]) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert stats.snapshot()["ik_requests_served"] == "4000"
