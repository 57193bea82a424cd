"""What a measurement ran on: CPU, cores, torch, device, date and the git revision of crfedit,
stamped on benchmark reports."""

from __future__ import annotations

import os
import platform
import subprocess
from datetime import datetime, timezone
from pathlib import Path

import torch


def cpu_model() -> str:
    """The CPU's model name from /proc/cpuinfo (Linux), else what :mod:`platform` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text(errors="replace").splitlines():
            key, _, value = line.partition(":")
            if key.strip() in ("model name", "Model", "Hardware", "cpu model") and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def git_revision(folder: Path | None = None) -> str:
    """Short commit of the checkout holding crfedit (``+dirty`` with uncommitted changes), or ``unknown``."""
    folder = folder or Path(__file__).resolve().parent.parent
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=folder, capture_output=True, text=True, timeout=10)
        if rev.returncode != 0:
            return "unknown"
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=folder, capture_output=True, text=True, timeout=10
        )
        return rev.stdout.strip() + ("+dirty" if dirty.returncode == 0 and dirty.stdout.strip() else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def machine_info(device: torch.device | str = "cpu") -> dict[str, str]:
    """CPU model, cores (usable / total), torch version and threads, device, date (UTC), git revision."""
    device = torch.device(device)
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    info = {
        "cpu": cpu_model(),
        "cores": f"{usable} usable of {os.cpu_count()}",
        "torch": torch.__version__,
        "threads": str(torch.get_num_threads()),
        "device": device.type,
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "revision": git_revision(),
        "python": platform.python_version(),
    }
    if device.type == "cuda":
        info["device"] = f"cuda ({torch.cuda.get_device_name(device)})"
    return info
