"""Registers, spills and static shared memory of Warp kernels compiled for a GPU architecture on any machine.

Warp's CPU wheels carry NVRTC, so ``wp.compile_aot_module`` builds a module's CUDA binary (cubin) without a GPU or a
driver. This tool reads what ``ptxas`` decided from the cubin's ELF attributes (``.nv.info``: ``REGCOUNT`` and
``FRAME_SIZE``, the per-thread local memory that spills and dynamically indexed arrays take) and the size of each
kernel's ``.nv.shared`` section. Occupancy follows from them (65,536 registers per SM on sm_80 .. sm_90): a kernel at
255 registers fits 256 threads per SM. No speed claim comes from here; it tells, before a GPU lease, whether a change
spilled or doubled a kernel's registers.

    python benchmarks/kernel_resources.py --modules lapwarp.kernels.chains lapwarp.kernels.xpbd
    python benchmarks/kernel_resources.py --hybrid 128:4 128:2 --max-registers 128
    python benchmarks/kernel_resources.py --registers 19 19:exact 39
    python benchmarks/kernel_resources.py --modules lapwarp.kernels.xpbd --blocks 4096   # waves of a block per env
    python benchmarks/kernel_resources.py --modules lapwarp.kernels.contact --blocks 8192 --lanes 256

Each kernel's static SASS instruction count (its code section / 16 bytes) comes with its registers: a change's code
size, not its run time (ThreadInHole's vertex sweep with half its arithmetic ran slower: it waits on its loads).
"""

from __future__ import annotations

import argparse
import importlib
import json
import struct
import tempfile
from pathlib import Path

import warp as wp

# .nv.info attributes (EIFMT_SVAL payloads: a symbol index, then the value)
_ATTRS = {0x2F: "registers", 0x11: "frame_bytes"}


def parse_cubin(path: str | Path) -> dict[str, dict[str, int]]:
    """Per kernel symbol of a cubin (ELF64): ``registers``, ``frame_bytes``, ``shared_bytes`` (static) and
    ``instructions`` (the static SASS count of its code section)."""
    data = Path(path).read_bytes()
    if data[:4] != b"\x7fELF" or data[4] != 2:
        raise ValueError(f"{path} is not an ELF64 cubin")
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    sections = [struct.unpack_from("<IIQQQQ", data, shoff + i * shentsize) for i in range(shnum)]

    def name_at(table_offset: int, offset: int) -> str:
        return data[table_offset + offset:data.index(b"\0", table_offset + offset)].decode()

    by_name = {name_at(sections[shstrndx][4], sec[0]): sec for sec in sections}
    symtab, strtab = by_name[".symtab"], by_name[".strtab"][4]
    symbols = [name_at(strtab, struct.unpack_from("<I", data, symtab[4] + 24 * i)[0])
               for i in range(symtab[5] // 24)]
    out: dict[str, dict[str, int]] = {}
    info = by_name.get(".nv.info")
    pos, end = (info[4], info[4] + info[5]) if info else (0, 0)
    while pos < end:
        fmt, attr = data[pos], data[pos + 1]
        if fmt == 0x04:  # EIFMT_SVAL: a 16-bit size, then the payload
            size, = struct.unpack_from("<H", data, pos + 2)
            if attr in _ATTRS:
                symbol, value = struct.unpack_from("<II", data, pos + 4)
                out.setdefault(symbols[symbol], {})[_ATTRS[attr]] = value
            pos += 4 + size
        else:  # EIFMT_NVAL: 2 bytes; EIFMT_BVAL, EIFMT_HVAL: 4
            pos += 2 if fmt == 0x01 else 4
    for name, sec in by_name.items():
        if name.startswith(".nv.shared.") and name[len(".nv.shared."):] in out:
            out[name[len(".nv.shared."):]]["shared_bytes"] = sec[5]
        if name.startswith(".text.") and name[len(".text."):] in out:
            # static SASS instructions (16 bytes each from sm_70 on): a change's code size, not its run time
            out[name[len(".text."):]]["instructions"] = sec[5] // 16
    return out


def block_waves(registers: int, num_blocks: int, lanes: int = 32, sms: int = 132, registers_per_sm: int = 65536,
                max_blocks_per_sm: int = 32, sub_partitions: int = 4, max_warps_per_sm: int = 64) -> tuple[int, float]:
    """``(blocks per SM, waves)`` of a grid of ``num_blocks`` blocks of ``lanes`` threads at ``registers`` per thread,
    as far as registers limit it (shared memory may limit it further), as CUDA's occupancy calculator counts
    (``cuda_occupancy.h``, ``cudaOccMaxBlocksPerSMRegsLimit``): a warp's registers are allocated in units of 256 within
    one of the SM's ``sub_partitions`` register files (4 x 16,384 on sm_80 .. sm_90), a block holds whole warps, and
    an SM holds at most ``max_blocks_per_sm`` blocks and ``max_warps_per_sm`` warps (32 and 64 on sm_80 .. sm_90; 132
    SMs: an H100 SXM or H200). A
    latency-bound kernel with one block per env at 4,096 envs takes 1.11 waves at 65-72 registers (28 blocks per SM)
    and one at <= 64 (32): ThreadInHole's per-vertex sweep capped from 80 to 64 (1.29 -> one wave) ran +6.3 %
    (thirty-fifth session). The sub-partitions make steps a whole-SM division misses: 168 registers hold 3 warps per
    sub-partition (12 per SM), 169-200 only 2 (8): RopeCutting's split chain solve's 1,280 warps ran in one wave at
    168 (568.7k env-steps/s) and in 1.2 at 176, 184, 200 and uncapped (479k-489k; H200, forty-fourth and forty-fifth
    sessions)."""
    per_warp = 256 * -(-int(registers) * 32 // 256)
    warps = -(-int(lanes) // 32)
    parts = int(sub_partitions)
    if per_warp * -(-warps // parts) * parts > registers_per_sm:
        raise ValueError(f"a block of {lanes} lanes at {registers} registers does not fit an SM")
    per_sm = min(max_blocks_per_sm, max_warps_per_sm // warps, (registers_per_sm // parts // per_warp) * parts // warps)
    if per_sm < 1:
        raise ValueError(f"a block of {lanes} lanes at {registers} registers does not fit an SM")
    return per_sm, num_blocks / (per_sm * sms)


def module_resources(module, arch: int = 90, block_dim: int | None = None) -> dict[str, dict[str, int]]:
    """Compile a Warp module (a ``wp.Module``, or a Python module holding kernels) for ``sm_{arch}`` and return each
    forward kernel's resources by kernel name (``block_dim``: the module's block size for tile kernels)."""
    if not isinstance(module, wp.Module):
        module = wp.get_module(module.__name__)
    if block_dim is not None:
        module.options["block_dim"] = int(block_dim)
    with tempfile.TemporaryDirectory() as tmp:
        paths = wp.compile_aot_module(module, arch=arch, module_dir=tmp, use_ptx=False)
        found = {}
        for path in paths:
            for symbol, res in parse_cubin(path).items():
                if symbol.endswith("_cuda_kernel_forward"):
                    found[symbol[: -len("_cuda_kernel_forward")]] = res
    return found


def main(argv: list[str] | None = None) -> int:
    from lapwarp import launching
    from lapwarp.kernels import chains_block, chains_hybrid, chains_registers

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--modules", nargs="*", default=[], help="Python modules of Warp kernels, e.g. lapwarp.kernels.xpbd")
    p.add_argument("--hybrid", nargs="*", default=[], metavar="ROWS:PER_LANE[:open][:unmasked]",
                   help="the hybrid chain kernel for packs of ROWS rows at PER_LANE rows per lane (open: the variant "
                        "without closed loops, unmasked: without cutting masks)")
    p.add_argument("--block", nargs="*", default=[], metavar="ROWS[:open][:unmasked]",
                   help="the block (PCR) chain kernel for packs of ROWS rows (flags as for --hybrid)")
    p.add_argument("--registers", nargs="*", default=[], metavar="LINKS[:exact]",
                   help="the register-resident chain kernel for chains of at most LINKS links (exact: all of LINKS "
                        "links, the variant a family of equal chains takes; kernels/chains_registers.py)")
    p.add_argument("--max-registers", type=int, default=None, help="compile the --hybrid kernels with this cap too")
    p.add_argument("--arch", type=int, default=90)
    p.add_argument("--blocks", type=int, default=None, metavar="N",
                   help="also print blocks per SM and waves for a grid of N one-warp blocks (e.g. 4096: a block per "
                        "env) on --sms SMs, as far as registers limit it")
    p.add_argument("--lanes", type=int, default=32,
                   help="threads per block for --blocks (32: a block per env of one warp; 256: Warp's default block)")
    p.add_argument("--sms", type=int, default=132)
    p.add_argument("--out", default=None, help="JSON output path")
    args = p.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    rows = []
    for name in args.modules:
        for kernel, res in module_resources(importlib.import_module(name), args.arch).items():
            rows.append({"module": name, "kernel": kernel, **res})
    for spec in args.hybrid:
        n, per_lane, *flags = spec.split(":")
        n, per_lane = int(n), int(per_lane)
        # ROWS:PER_LANE[:open][:unmasked]: the variant without loops / cutting masks
        kernel = chains_hybrid.hybrid_chain_kernel(n, per_lane, loops="open" not in flags,
                                                   masked="unmasked" not in flags)
        lanes = chains_hybrid.lanes_for(n, per_lane)
        block = 32 * ((lanes + 31) // 32)
        caps = [None] + ([args.max_registers] if args.max_registers else [])
        for cap in caps:
            k = launching.register_capped(kernel, cap) if cap else kernel
            for name, res in module_resources(k.module, args.arch, block).items():
                rows.append({"module": f"hybrid {n}:{per_lane}", "kernel": name, "block_dim": block,
                             "max_registers": cap, **res})
    for spec in args.block:
        n, *flags = spec.split(":")
        kernel = chains_block.block_chain_kernel(int(n), loops="open" not in flags, masked="unmasked" not in flags)
        for name, res in module_resources(kernel.module, args.arch).items():
            rows.append({"module": f"block {spec}", "kernel": name, **res})
    for spec in args.registers:
        links, *flags = spec.split(":")
        kernel = chains_registers.register_chain_kernel(int(links), exact="exact" in flags)
        for name, res in module_resources(kernel.module, args.arch).items():
            rows.append({"module": f"registers {spec}", "kernel": name, **res})
    for r in rows:
        waves = ""
        if args.blocks and "registers" in r:
            r["blocks_per_sm"], r["waves"] = block_waves(r["registers"], args.blocks, lanes=args.lanes, sms=args.sms)
            waves = f" {r['blocks_per_sm']:>2} blocks/SM {r['waves']:.2f} waves"
        print(f"{r['module'][:28]:28s} {r['kernel'][:60]:60s} regs={r.get('registers', '?'):>3} "
              f"frame={r.get('frame_bytes', 0):>4} B shared={r.get('shared_bytes', 0):>5} B "
              f"instructions={r.get('instructions', '?'):>5}{waves}")
    if args.out:
        Path(args.out).write_text(json.dumps({"arch": args.arch, "warp": wp.__version__, "kernels": rows}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
