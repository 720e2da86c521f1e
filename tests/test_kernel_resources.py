"""benchmarks/kernel_resources.py: a kernel's registers and spills read from the cubin that Warp's NVRTC builds on a
machine without a GPU. A kernel that indexes a local array by a run-time value must keep it in local memory (a
frame > 0), a plain one must not; both use registers. Skipped where this Warp build has no NVRTC."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from kernel_resources import block_waves, module_resources, parse_cubin  # noqa: E402

vec16 = wp.types.vector(length=16, dtype=float)


@wp.kernel(module="unique")
def plain_add(a: wp.array(dtype=float), b: wp.array(dtype=float)):
    i = wp.tid()
    b[i] = a[i] + 1.0


@wp.kernel(module="unique")
def indexed_local(a: wp.array(dtype=float), k: wp.array(dtype=wp.int32), b: wp.array(dtype=float)):
    i = wp.tid()
    v = vec16()
    for j in range(16):
        v[j] = a[i * 16 + j]
    b[i] = v[k[i]]  # a run-time index: the vector lives in local memory


def test_registers_and_frames_from_the_cubin():
    try:
        plain = module_resources(plain_add.module)
        indexed = module_resources(indexed_local.module)
    except Exception as exc:  # no NVRTC in this Warp build
        pytest.skip(f"no CUDA compilation here: {exc}")
    (p,), (q,) = plain.values(), indexed.values()
    assert p["registers"] > 0 and q["registers"] > 0
    assert p["frame_bytes"] == 0
    assert q["frame_bytes"] >= 64  # the 16 floats
    assert 0 < p["instructions"] < q["instructions"]  # the 16 loads and stores of the local vector


def test_cli_counts_blocks_of_any_width(tmp_path, monkeypatch):
    """``--blocks N --lanes L``: each kernel's blocks per SM and waves for a grid of N blocks of L threads, as
    ``block_waves`` counts them."""
    import json

    import kernel_resources

    (tmp_path / "tiny_kernels_for_resources.py").write_text(
        "import warp as wp\n\n\n@wp.kernel\ndef tiny(a: wp.array(dtype=float)):\n    a[wp.tid()] += 1.0\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    out = tmp_path / "res.json"
    try:
        kernel_resources.main(["--modules", "tiny_kernels_for_resources", "--blocks", "4096", "--lanes", "256",
                               "--out", str(out)])
    except Exception as exc:  # no NVRTC in this Warp build
        pytest.skip(f"no CUDA compilation here: {exc}")
    (row,) = json.loads(out.read_text())["kernels"]
    assert row["instructions"] > 0
    assert (row["blocks_per_sm"], row["waves"]) == block_waves(row["registers"], 4096, lanes=256)
    assert row["blocks_per_sm"] == 8  # a few registers: the SM's 64 warps, 8 blocks of 8


def test_parse_refuses_a_non_elf(tmp_path):
    path = tmp_path / "x.cubin"
    path.write_bytes(b"not an elf")
    with pytest.raises(ValueError, match="not an ELF64"):
        parse_cubin(path)


def test_block_waves_by_registers():
    """One-warp blocks, 4,096 of them (a block per env) on 132 SMs: a warp's registers allocated in units of 256 in one
    of the SM's four 16,384-register sub-partitions, at most 32 blocks per SM (cuda_occupancy.h's count). <= 64
    registers: one wave; 65-72: 28 blocks per SM, 1.11 waves (solve_rods_fused's 71 once); 80: 24, 1.29 (ThreadInHole's
    uncapped vertex sweep); 128: 16, 1.94. RopeCutting's split chain solve (1,280 one-warp blocks): 12 per SM at 168
    registers (one wave), 8 at 169-200 and 240 (1.21 waves), which a division of the whole SM's 65,536 registers
    (11 at 176, 10 at 200: one wave) would miss; it ran 568.7k env-steps/s at 168 against 479k-489k at 176-235 (H200).
    Wider blocks hold whole warps."""
    assert block_waves(64, 4096) == (32, pytest.approx(4096 / (32 * 132)))
    assert block_waves(71, 4096)[0] == 28 and block_waves(72, 4096)[0] == 28
    assert block_waves(71, 4096)[1] == pytest.approx(1.108, abs=1e-3)
    assert block_waves(80, 4096)[0] == 24 and block_waves(80, 4096)[1] == pytest.approx(1.293, abs=1e-3)
    assert block_waves(128, 4096)[0] == 16
    assert block_waves(168, 1280) == (12, pytest.approx(1280 / (12 * 132)))
    for registers in (169, 176, 184, 200, 235):
        assert block_waves(registers, 1280)[0] == 8, registers
    assert block_waves(200, 1280)[1] == pytest.approx(1.212, abs=1e-3)
    # blocks of 256 threads: 1 per SM above 128 registers, 2 at 81-128, 3 at 65-80, 4 at 49-64, ... 8 at <= 32 (64
    # warps, the SM's most)
    assert [block_waves(r, 1000, lanes=256)[0] for r in (129, 128, 81, 80, 65, 64, 49, 48, 32, 16)] == \
        [1, 2, 2, 3, 3, 4, 4, 5, 8, 8]
    assert block_waves(64, 4096, lanes=40)[0] == 16  # two warps a block
    assert block_waves(32, 100, lanes=64, sms=1)[0] == 32
    with pytest.raises(ValueError, match="does not fit"):
        block_waves(255, 1, lanes=1024)


def test_rasteriser_kernels_hold_their_register_cap():
    """The rasteriser's and the shader's kernels are declared with ``RASTER_MAX_REGISTERS`` (48: 5 blocks of 256
    threads per SM instead of 4, sm_90); compiled, each uses at most that many registers."""
    from lapwarp.kernels import raster

    try:
        res = module_resources(raster.shade_visibility.module, 90, 256)
    except Exception as exc:  # no NVRTC in this Warp build
        pytest.skip(f"no CUDA compilation here: {exc}")
    capped = ("rasterize_rigid", "rasterize_deformable", "rasterize_deformable_u8", "shade_visibility")
    found = {name: v for name, v in res.items() for k in capped if name.rsplit("_", 1)[0] == k}
    assert sorted(n.rsplit("_", 1)[0] for n in found) == sorted(capped)
    assert all(0 < v["registers"] <= raster.RASTER_MAX_REGISTERS for v in found.values()), found
