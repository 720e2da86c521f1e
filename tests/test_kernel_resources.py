"""benchmarks/kernel_resources.py: a kernel's registers and spills read from the cubin that Warp's NVRTC builds on a
machine without a GPU. A kernel that indexes a local array by a run-time value must keep it in local memory (a
frame > 0), a plain one must not; both use registers. Skipped where this Warp build has no NVRTC."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from kernel_resources import module_resources, parse_cubin  # noqa: E402

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


def test_parse_refuses_a_non_elf(tmp_path):
    path = tmp_path / "x.cubin"
    path.write_bytes(b"not an elf")
    with pytest.raises(ValueError, match="not an ELF64"):
        parse_cubin(path)
