"""The block (PCR) chain solve (kernels/chains_block.py, ``World.chain_solver = "pcr"``) against the serial one
(kernels/chains.py): the scenes of tests/test_chains_partitioned.py stepped both ways must end at the same positions.

Both solve the same linear systems exactly (a loop in the same Sherman-Morrison form); only the elimination order
differs, so the positions differ by float32 round-off. Tolerance: max |dx| <= 1e-5 x the chain's length, as for the
partitioned solve.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_chains_partitioned import TOL, _cloth_world, _rod_world, _worst


@pytest.mark.parametrize("newton_steps, iterations, rigid", [(1, 1, False), (2, 1, True), (2, 2, False)])
@pytest.mark.parametrize("cuttable", [False, True])
def test_pcr_rods_match_serial(device, newton_steps, iterations, rigid, cuttable, monkeypatch):
    # open rods of 1-17 links and loops of 3-30, pinned first, last, inside, two adjacent nodes (an empty row when
    # rigid); 3 envs of different positions (and cuts: loops cut at either corner or inside); 1 or 2 Newton steps,
    # 1 sweep or 2 (the multipliers carried)
    from lapwarp.kernels import chains_block

    lengths = []  # the block kernels the "pcr" world records (by their tile length): the solve really ran
    original = chains_block.block_chain_kernel
    monkeypatch.setattr(chains_block, "block_chain_kernel",
                        lambda links, **flags: lengths.append(links) or original(links, **flags))
    out = []
    for solver in ("thomas", "pcr"):
        world, rods = _rod_world(device, 0, newton_steps, iterations, rigid, cuttable)
        world.chain_solver = solver
        start = world.positions()
        world.simulate(0.04, 0.02)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    assert _worst(start, out[1], rods) > 100 * TOL  # the solves had work to do
    assert _worst(out[0], out[1], rods) <= TOL
    assert lengths and max(lengths) >= 30  # the block kernels ran (the loop of 30 links is a pack of 30 rows)


@pytest.mark.parametrize("rows", [1, 12, 64])
def test_pcr_pack_sizes_match_serial(device, rows):
    # a chain per block (1), packs of a few short rods (12: longer chains alone), most open rods in one pack (64);
    # cut rods, so that cuts fall inside packs, 2 Newton steps
    out = []
    for solver in ("thomas", "pcr"):
        world, rods = _rod_world(device, 0, 2, 1, False, True)
        world.chain_solver = solver
        world.chain_pcr_rows = rows
        world.simulate(0.04, 0.02)
        out.append(world.positions())
    assert _worst(out[0], out[1], rods) <= TOL


def test_pack_layout():
    # every chain's nodes and links in exactly one pack, in order; loops alone; packs within the budget unless one
    # chain is longer; the rows of a pack follow each other
    from lapwarp.chains import pack_chains

    world, _ = _rod_world("cpu", 0, 1, 1, False, False)
    cs = world.model.rod_chains
    for capacity in (1, 12, 64):
        packs = pack_chains(cs, capacity, "cpu")
        rows, start, count = packs.rows.numpy(), packs.pack_start.numpy(), packs.pack_rows.numpy()
        closed = packs.pack_closed.numpy()
        assert start[0] == 0 and np.array_equal(start[1:], np.cumsum(count)[:-1]) and count.sum() == len(rows)
        assert sum(c for _, c in packs.families) == len(start)
        seen = []
        for p in range(len(start)):
            block = rows[start[p]: start[p] + count[p]]
            chains_in = np.split(block, np.nonzero(block[:, 2])[0][1:])
            assert block[0, 2] == 1
            if closed[p]:
                assert len(chains_in) == 1 and (block[:, 1] >= 0).all()
            else:
                assert all(c[-1, 1] == -1 and (c[:-1, 1] >= 0).all() for c in chains_in)
                assert count[p] <= capacity or len(chains_in) == 1
                if capacity == 1:
                    assert len(chains_in) == 1
            seen += [tuple(c[:, 1][c[:, 1] >= 0]) for c in chains_in]
        assert sorted(k for c in seen for k in c) == list(range(cs.edges))  # each link once
        assert len(seen) == cs.count
        chains_per_pack = np.add.reduceat(rows[:, 2], start)
        assert chains_per_pack.max() == 1 if capacity == 1 else chains_per_pack.max() > 1


@pytest.mark.parametrize("newton_steps, cuttable", [(1, False), (2, True)])
def test_pcr_cloth_edge_chains_match_serial(device, newton_steps, cuttable):
    # a 6 x 5 cloth: rows, columns and diagonals in 3 families; env 1 with every fourth edge removed
    out = []
    for solver in ("thomas", "pcr"):
        world, objects = _cloth_world(device, 0, newton_steps, cuttable)
        world.chain_solver = solver
        world.simulate(0.04, 0.02)
        out.append(world.positions())
    assert _worst(out[0], out[1], objects) <= TOL


def test_pcr_lanes_fewer_than_links(device):
    # a block of 32 lanes over chains of up to 30 links and 31 nodes is the common case; 1 lane per block takes every
    # row of each PCR round in turn (the CPU's case, forced here on any device): the same positions
    out = []
    for lanes in (0, 1):
        world, rods = _rod_world(device, 0, 2, 1, False, True)
        world.chain_solver = "pcr"
        world.chain_pcr_threads = lanes
        world.simulate(0.04, 0.02)
        out.append(world.positions())
    assert _worst(out[0], out[1], rods) <= TOL


def test_pcr_setting_is_checked(device):
    world, _ = _rod_world(device, 0, 1, 1, False, False)
    world.chain_solver = "cholesky"
    with pytest.raises(ValueError, match="chain_solver must be one of"):
        world.step(0.02)
    world.chain_solver = "pcr"
    world.chain_pcr_threads = -1
    with pytest.raises(ValueError, match="chain_pcr_threads"):
        world.step(0.02)
    for rows in (-1, 4096, 2.5, True):
        with pytest.raises(ValueError, match="chain_pcr_rows"):
            world.chain_pcr_rows = rows


def test_pcr_packs_are_laid_out_outside_the_step(monkeypatch):
    # the packs' device arrays are copied from the host, which a step recorded inside a CUDA graph capture (an env's
    # first step on a GPU) must not do: the World lays them out when built and when chain_pcr_rows is set, and a step
    # only reads them (a layout during the captured step replayed garbage rows on the GPU: PrecisionCutting's expert
    # failed every episode, RopeCutting at 64 rows accessed memory out of bounds)
    import lapwarp.world as world_module

    world, _ = _rod_world("cpu", 0, 1, 1, False, False)
    world.chain_solver = "pcr"
    world.chain_pcr_rows = 12
    monkeypatch.setattr(world_module, "pack_chains", lambda *a, **k: pytest.fail("packs laid out inside a step"))
    world.simulate(0.04, 0.02)
    assert world.unstable.numpy().sum() == 0


def test_pcr_refuses_a_chain_beyond_shared_memory(device, monkeypatch):
    import lapwarp.world as world_module

    monkeypatch.setattr(world_module, "PCR_MAX_LINKS", 10)
    world, _ = _rod_world(device, 0, 1, 1, False, False)
    world.chain_solver = "pcr"
    with pytest.raises(ValueError, match="longest chain has 30 links, more than 10"):
        world.step(0.02)


def test_env_config_selects_the_pcr_solve():
    import lapwarp

    env = lapwarp.make("RopeCutting", num_envs=1, device="cpu")
    assert env.cfg.chain_solver == "auto" and env.world.chain_solver == "thomas"  # "auto": the serial solve on a CPU
    env = lapwarp.make("RopeCutting", num_envs=1, device="cpu", chain_solver="pcr")
    assert env.world.chain_solver == "pcr"
    env.step(np.zeros((1, env.action_dim), dtype=np.float32))
    with pytest.raises(ValueError, match="chain_solver"):
        lapwarp.make("Reach", num_envs=1, device="cpu", chain_solver="jacobi")


def test_pcr_long_rope_matches_serial(device, monkeypatch):
    # a hanging rope of 200 links swinging from horizontal for 0.5 s (2 Newton steps, 20 substeps): more nodes than a
    # block's 128 lanes, so on the GPU every lane takes two rows per round; the same path as the serial solve to 1e-5
    # of its length (measured 1.8e-6, CPU). An open, uncut rope: the kernel variant compiled without the loop and cut
    # branches ran
    from lapwarp.builder import SceneBuilder
    from lapwarp.kernels import chains_block

    variants = []
    original = chains_block.block_chain_kernel
    monkeypatch.setattr(chains_block, "block_chain_kernel",
                        lambda links, **flags: variants.append(flags) or original(links, **flags))
    out = []
    for solver in ("thomas", "pcr"):
        b = SceneBuilder()
        pts = np.stack([np.linspace(0.0, 0.2, 201), np.zeros(201), np.zeros(201)], axis=1)
        rod = b.add_rod(pts, radius=5e-4, youngs_modulus=1e6, damping=0.5, fixed=[0])
        world = b.finalize(2, device, substeps=20)
        world.chain_solver = solver
        world.simulate(0.5, 0.1)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions(rod))
    assert out[1][0, -1, 2] < -0.05  # the tip fell and swings
    assert np.abs(out[0] - out[1]).max() <= TOL * 0.2
    assert variants and all(v == {"loops": False, "masked": False, "newton_tolerance": 0.0} for v in variants), \
        variants
