"""Per-rank settings and collectives of a ``torchrun`` launch of ``train/ppo.py --distributed`` (issue #20).

``torchrun --nproc_per_node=N train/ppo.py --distributed ...`` starts N processes; each reads ``WORLD_SIZE``, ``RANK``
and ``LOCAL_RANK`` from its environment, builds its own lapwarp envs on ``cuda:<LOCAL_RANK>`` (``--num-envs`` is per
rank) and trains the one policy whose gradients rsl-rl averages over the process group.

What this module owns:
- ``rank_settings``: device, seed and logging role of a rank, computed from the torchrun variables (CPU-testable).
- ``bind_device``: make the rank's GPU current before Warp initialises, so that Warp adopts that context and never
  creates one on another rank's GPU (Warp's ``init`` binds ``cuda:0`` unless a context is already current).
- ``init_process_group``: NCCL on GPUs, gloo on CPUs (the CPU tests run the whole training path in two processes).
- ``DistributedRunner``: rsl-rl's ``OnPolicyRunner`` joining that group instead of creating its own NCCL-only group.
- small collectives for the progress line and the final report (sums over ranks; no-ops in a single process).

Seeds: rank ``r`` uses ``seed + r * 2**32``. Rank 0 therefore reproduces the single-process run of ``seed``, and every
other rank's seed is hashed by ``lapwarp.config.rng_seed32`` into Warp's negative seed range, so no rank of one run
shares its env RNG streams with any rank of a run started with another seed in ``[0, 2**31)``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.distributed as dist
from rsl_rl.runners import OnPolicyRunner

#: Offset between consecutive ranks' seeds (see the module docstring).
RANK_SEED_STRIDE = 2**32

TORCHRUN_VARIABLES = ("WORLD_SIZE", "RANK", "LOCAL_RANK")


@dataclass(frozen=True)
class RankSettings:
    """What one process of a (possibly single-process) training run uses."""

    world_size: int
    rank: int
    local_rank: int
    device: str
    seed: int

    @property
    def is_main(self) -> bool:
        """Whether this rank logs, writes checkpoints and runs the final evaluation."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def rank_seed(seed: int, rank: int) -> int:
    """The env and torch seed of ``rank`` in a run started with ``seed``."""
    return int(seed) + int(rank) * RANK_SEED_STRIDE


def _read_int(environ: Mapping[str, str], name: str) -> int:
    value = environ.get(name)
    try:
        return int(value)
    except (TypeError, ValueError):
        raise ValueError(f"--distributed reads {name} from the environment (torchrun sets it), got {value!r}; "
                         f"launch with: torchrun --nproc_per_node=N train/ppo.py --distributed ...") from None


def rank_settings(environ: Mapping[str, str], seed: int, device: str | None, cuda_available: bool) -> RankSettings:
    """The rank's settings from the torchrun variables in ``environ``.

    ``device``: ``None`` picks ``cuda:<LOCAL_RANK>`` (or ``cpu`` without CUDA); ``"cpu"`` runs every rank on the CPU
    (gloo, for tests); a CUDA device must be ``cuda:<LOCAL_RANK>`` (one GPU per process, as rsl-rl requires).
    Missing or inconsistent variables raise ``ValueError``.
    """
    world_size, rank, local_rank = (_read_int(environ, name) for name in TORCHRUN_VARIABLES)
    if world_size < 1 or not 0 <= rank < world_size or not 0 <= local_rank <= rank:
        raise ValueError(f"inconsistent torchrun variables WORLD_SIZE={world_size}, RANK={rank}, "
                         f"LOCAL_RANK={local_rank}")
    expected = f"cuda:{local_rank}"
    if device is None:
        device = expected if cuda_available else "cpu"
    elif device == "cuda":
        device = expected
    elif device != "cpu" and device != expected:
        raise ValueError(f"--device {device} on local rank {local_rank}: with --distributed each process trains on "
                         f"its own GPU, {expected} (leave --device out, or pass cpu to run every rank on the CPU)")
    return RankSettings(world_size, rank, local_rank, device, rank_seed(seed, rank))


def single_process_settings(seed: int, device: str) -> RankSettings:
    return RankSettings(1, 0, 0, device, int(seed))


def bind_device(device: str) -> None:
    """Make ``device``'s CUDA context current before anything initialises Warp or NCCL on another GPU."""
    if device.startswith("cuda"):
        torch.cuda.set_device(torch.device(device))
        torch.empty(1, device=device)  # creates the primary context now; Warp's init adopts the current one
    import warp as wp

    wp.init()
    wp.set_device(device)


def cuda_contexts() -> list[str]:
    """The CUDA devices on which this process's Warp holds a context (one, the rank's own, when bound correctly)."""
    import warp as wp

    return [d.alias for d in wp.get_cuda_devices() if d.has_context]


def init_process_group(settings: RankSettings) -> None:
    """Join the torchrun group: NCCL when the rank trains on a GPU, gloo on the CPU."""
    if settings.device.startswith("cuda"):
        dist.init_process_group("nccl", rank=settings.rank, world_size=settings.world_size,
                                device_id=torch.device(settings.device))
    else:
        dist.init_process_group("gloo", rank=settings.rank, world_size=settings.world_size)


def sum_over_ranks(values: list[float], device: str) -> list[float]:
    """Element-wise sums of ``values`` over every rank (the values themselves in a single process)."""
    if not (dist.is_available() and dist.is_initialized()):
        return [float(v) for v in values]
    tensor = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(tensor)
    return tensor.tolist()


def gather_objects(value) -> list:
    """``value`` of every rank, in rank order (``[value]`` in a single process)."""
    if not (dist.is_available() and dist.is_initialized()):
        return [value]
    out = [None] * dist.get_world_size()
    dist.all_gather_object(out, value)
    return out


class DistributedRunner(OnPolicyRunner):
    """rsl-rl's ``OnPolicyRunner`` that joins an already initialised process group (NCCL or gloo).

    rsl-rl's own set-up creates an NCCL group and insists on ``cuda:<LOCAL_RANK>``; everything after it (parameter
    broadcast, gradient averaging, the KL-adaptive learning rate, logging on rank 0 only) works on any backend.
    Without a process group it is the plain runner.
    """

    def _configure_multi_gpu(self) -> None:
        if not (dist.is_available() and dist.is_initialized()):
            super()._configure_multi_gpu()
            return
        self.gpu_world_size = dist.get_world_size()
        self.gpu_global_rank = dist.get_rank()
        self.gpu_local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        self.is_distributed = self.gpu_world_size > 1
        self.cfg["multi_gpu"] = {"global_rank": self.gpu_global_rank, "local_rank": self.gpu_local_rank,
                                 "world_size": self.gpu_world_size} if self.is_distributed else None
