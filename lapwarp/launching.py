"""Kernel launches sized to the GPU: every lapwarp launch goes through :func:`launch` (or, inside the World's recorded
step, :func:`block_dim_for`), which picks the threads per block from the grid's size; :func:`make_struct` builds the
``wp.struct`` bundles that launches take.

Warp launches 256 threads per block unless told otherwise. Most of lapwarp's kernels run one thread per env, per
rope or per instrument, i.e. 4,096 to 20,000 threads at a typical batch size: 16 to 80 blocks of 256 on an H100 with
132 SMs, so most SMs sit idle while a latency-bound kernel (a serial chain solve, a per-env reward) runs. Smaller
blocks spread such grids over every SM (measured on the H100, 4,096 envs: a 100-segment rod solved by one thread per
rod ran 2.07x faster, PickAndPlace's whole env step 1.26x; benchmarks/RESULTS.md, "Launch block sizes"). Large grids
keep 256. On the CPU the block size is ignored.
"""

from __future__ import annotations

import numpy as np
import warp as wp


def block_dim_for(dim, sm_count: int, cap: int = 256) -> int:
    """Threads per block for a launch of ``dim`` threads (an int or a shape): the largest power of two from ``cap``
    down to 32 that still gives each of the ``sm_count`` SMs about four blocks. ``cap`` below 256 is for
    register-heavy kernels (more small blocks fit an SM's register file than large ones). With ``sm_count`` 0 (the
    CPU) the result is ``cap``."""
    threads = int(np.prod(dim)) if isinstance(dim, tuple | list) else int(dim)
    block = cap
    while block > 32 and threads < 4 * sm_count * block:
        block //= 2
    return block


def block_lanes(device, lanes: int) -> int:
    """Threads of a thread-block-per-env launch (launch ``(num_envs, lanes)`` with ``block_dim=lanes``): ``lanes`` on
    CUDA, one on the CPU, where Warp runs a tiled block as a single lane (the block's loops then take every element
    in order and its barriers are no-ops)."""
    return int(lanes) if wp.get_device(device).is_cuda else 1


def launch(kernel, dim, inputs=(), outputs=(), device=None, block_dim: int | None = None, **kwargs):
    """``wp.launch`` with the block size from :func:`block_dim_for` on CUDA devices (an explicit ``block_dim`` wins);
    other keyword arguments are passed through."""
    dev = wp.get_device(device)
    if block_dim is None and dev.is_cuda:
        block_dim = block_dim_for(dim, dev.sm_count)
    return wp.launch(kernel, dim=dim, inputs=inputs, outputs=outputs, device=dev, block_dim=block_dim, **kwargs)


# kernels recompiled with a register cap, by (kernel, cap): each is its own module, compiled once per process
_CAPPED: dict[tuple[wp.Kernel, int], wp.Kernel] = {}
MAX_REGISTERS_RANGE = (16, 255)  # what nvcc's and NVRTC's maxrregcount accept


def check_register_cap(max_registers) -> None:
    """A ``ValueError`` unless ``max_registers`` is an int that CUDA's compilers take as a register cap."""
    low, high = MAX_REGISTERS_RANGE
    if isinstance(max_registers, bool) or not isinstance(max_registers, int) or not low <= max_registers <= high:
        raise ValueError(f"a register cap must be an int in [{low}, {high}], got {max_registers!r}")


def register_capped(kernel: wp.Kernel, max_registers: int | None) -> wp.Kernel:
    """``kernel`` compiled with at most ``max_registers`` registers per thread on CUDA (a copy in its own module, made
    once per cap; the CPU ignores the cap), or ``kernel`` itself for ``None``. A latency-bound kernel whose register
    count limits how many warps an SM holds can run faster capped, spilling on its rarely taken paths
    (``chains.solve_cloth_chains``: 96 registers from 148, 2.77 -> 2.26 ms per substep on the H100)."""
    if max_registers is None:
        return kernel
    check_register_cap(max_registers)
    key = (kernel, max_registers)
    if key not in _CAPPED:
        # the kernel's own module options carried over where it has them (an unrolled kernel's max_unroll: without it
        # the copy's loops past Warp's default 16 stay loops, their vectors in local memory)
        options = {k: v for k, v in kernel.module.options.items() if k == "max_unroll"} if kernel.module else {}
        _CAPPED[key] = wp.kernel(kernel.func, cuda_max_registers=max_registers, module="unique",
                                 enable_backward=False, module_options=options or None)
    return _CAPPED[key]


def make_struct(cls, **fields):
    """An instance of the ``wp.struct`` ``cls`` with ``fields`` set (kernel bundles are built once on the host and
    never changed afterwards: a recorded launch reads the struct it was recorded with)."""
    out = cls()
    for name, value in fields.items():
        setattr(out, name, value)
    return out
