"""Describe the machine a benchmark ran on (CPU, cores, library versions)."""

from __future__ import annotations

import os
import platform
import sys
from datetime import datetime, timezone


def _cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.lower().startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def _version(module: str) -> str:
    try:
        mod = __import__(module)
    except Exception:  # noqa: BLE001 - absent or broken optional dependency
        return "absent"
    return str(getattr(mod, "__version__", "unknown"))


def machine_info() -> dict:
    """CPU model, logical cores, OS, and python/numpy/onnxruntime versions, plus a UTC timestamp."""
    try:
        usable = len(os.sched_getaffinity(0))
    except AttributeError:
        usable = os.cpu_count() or 0
    try:
        load = [round(x, 2) for x in os.getloadavg()]
    except OSError:
        load = []
    return {
        "cpu_model": _cpu_model(),
        "logical_cores": os.cpu_count() or 0,
        "usable_cores": usable,
        "load_average_1_5_15min": load,
        "platform": platform.platform(),
        "python": sys.version.split()[0],
        "numpy": _version("numpy"),
        "onnxruntime": _version("onnxruntime"),
        "scikit_image": _version("skimage"),
        "timestamp_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
    }


def machine_line(info: dict) -> str:
    """One human-readable line summarising :func:`machine_info`."""
    return (
        f"{info['cpu_model']}, {info['usable_cores']} cores usable ({info['logical_cores']} logical), "
        f"{info['platform']}; python {info['python']}, numpy {info['numpy']}, "
        f"onnxruntime {info['onnxruntime']}; load average at start {info['load_average_1_5_15min']}; "
        f"{info['timestamp_utc']}"
    )
