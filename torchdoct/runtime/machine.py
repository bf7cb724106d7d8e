"""What a measurement ran on: the machine record every benchmark writes beside its numbers."""

from __future__ import annotations

import os
import platform
from typing import Any

__all__ = ["machine_info"]


def machine_info() -> dict[str, Any]:
    """Cores, torch's thread pools and versions, Python and the platform (JSON-ready)."""
    import torch

    return {
        "cpu_count": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "torch_interop_threads": torch.get_num_interop_threads(),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
    }
