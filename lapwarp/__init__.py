"""lapwarp: LapGym's surgical RL environments as a batched simulator in NVIDIA Warp.

Light imports only: ``import lapwarp`` does not compile kernels or initialise devices.
"""

from __future__ import annotations

__version__ = "0.1.0"

from lapwarp.registry import list_tasks, make  # noqa: E402

__all__ = ["__version__", "list_tasks", "make"]
