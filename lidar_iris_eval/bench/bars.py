"""Pass/fail bars and the summary table of a benchmark report."""

from __future__ import annotations

from typing import Any

from lidar_iris_eval.bench.settings import (
    BAR_FRAMES,
    BAR_LIDAR_IRIS_LOOP_PAIRS,
    BAR_LIDAR_IRIS_PEAK_GIB,
    BAR_LIDAR_IRIS_PROTOCOL_S,
    BAR_LIDAR_IRIS_SPEEDUP,
    BAR_SCAN_CONTEXT_PROTOCOL2_S,
)


def evaluate_bars(report: dict[str, Any]) -> list[dict[str, Any]]:
    """Issue 8's bars that this report can judge (only for a 4541-frame sequence)."""
    if report["sequence"]["frames"] != BAR_FRAMES:
        return []
    bars = []

    def bar(what, value, limit, met):
        bars.append({"bar": what, "value": value, "limit": limit, "met": bool(met)})

    for e in report["descriptors"]:
        if e["descriptor"] == "lidar-iris":
            for p in (1, 2):
                if f"protocol{p}" in e:
                    wall = e[f"protocol{p}"]["wall_s"]
                    bar(f"lidar-iris protocol {p} wall s", wall, BAR_LIDAR_IRIS_PROTOCOL_S,
                        wall <= BAR_LIDAR_IRIS_PROTOCOL_S)
            peaks = [e[f"protocol{p}"]["peak_rss_bytes"] for p in (1, 2)
                     if f"protocol{p}" in e and e[f"protocol{p}"]["isolated"]]
            if peaks:
                gib = max(peaks) / 2**30
                bar("lidar-iris peak memory GiB", gib, BAR_LIDAR_IRIS_PEAK_GIB,
                    gib <= BAR_LIDAR_IRIS_PEAK_GIB)
            ref = (e.get("loop") or {}).get("reference")
            if ref is not None:
                bar("lidar-iris kernel speedup over per-pair loop", ref["speedup"],
                    BAR_LIDAR_IRIS_SPEEDUP, ref["speedup"] >= BAR_LIDAR_IRIS_SPEEDUP)
                n = e["loop"]["pairs"]
                bar("lidar-iris loop distances identical (pairs)", n,
                    BAR_LIDAR_IRIS_LOOP_PAIRS, ref["identical"] and n >= BAR_LIDAR_IRIS_LOOP_PAIRS)
        if (e["descriptor"] == "scan-context" and e["params"].get("search") == "exhaustive"
                and "protocol2" in e):
            wall = e["protocol2"]["wall_s"]
            bar("scan-context exhaustive protocol 2 wall s", wall, BAR_SCAN_CONTEXT_PROTOCOL2_S,
                wall <= BAR_SCAN_CONTEXT_PROTOCOL2_S)
    return bars


def summary_rows(report: dict[str, Any]) -> list[dict[str, Any]]:
    """One table row per descriptor with the headline figures."""
    rows = []
    for e in report["descriptors"]:
        ex, kernel = e["extraction"], e["kernel"]
        loop = e.get("loop") or {}
        ref = loop.get("reference") or {}
        peaks = [e[k]["peak_rss_bytes"] for k in ("protocol1", "protocol2") if k in e]
        rows.append({
            "descriptor": f"{e['descriptor']}:{e['preset']}",
            "extract_ms_med": ex["median_ms"],
            "extract_ms_iqr": f"{ex['q1_ms']:.1f}-{ex['q3_ms']:.1f}",
            "kernel_pairs_per_s": float(kernel["pairs_per_s"]),
            "loop_speedup": ref.get("speedup", float("nan")),
            "batched==single": loop.get("batched_equals_single", "-"),
            "loop_identical": ref.get("identical", "-"),
            "p1_wall_s": e.get("protocol1", {}).get("wall_s", float("nan")),
            "p2_wall_s": e.get("protocol2", {}).get("wall_s", float("nan")),
            "peak_gib": max(peaks) / 2**30 if peaks else float("nan"),
        })
    return rows
