"""The shared-memory chain solve (kernels/chains_shared.py, ``World.chain_solver = "shared"``) against the serial one
(kernels/chains.py): the cloth and rod scenes of tests/test_chains_partitioned.py stepped both ways must end at the
same positions.

Both solve the same linear systems exactly; the shared solve eliminates each chain's transverse filter from its far
end instead of its first node, so the positions differ by float32 round-off. Tolerance: max |dx| <= 1e-5 x the
object's length, as for the other chain solves.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_chains_partitioned import TOL, _cloth_world, _rod_world, _worst

from lapwarp.assets import cloth_grid
from lapwarp.builder import SceneBuilder


def _count_kernels(monkeypatch) -> list:
    """The shared kernels a world records (their keys): the solve really ran."""
    from lapwarp.kernels import chains_shared

    keys = []
    original = chains_shared.shared_chain_kernel
    monkeypatch.setattr(chains_shared, "shared_chain_kernel",
                        lambda *args, **flags: keys.append((*args, flags)) or original(*args, **flags))
    return keys


@pytest.mark.parametrize("newton_steps, iterations, cuttable", [(1, 1, False), (2, 1, True), (2, 2, True)])
def test_shared_cloth_edge_chains_match_serial(device, newton_steps, iterations, cuttable, monkeypatch):
    # a 6 x 5 cloth pinned at two corners: rows, columns and diagonals in 3 families; env 1 with every fourth edge
    # removed; 1 or 2 Newton steps, 1 sweep or 2 (the multipliers carried)
    keys = _count_kernels(monkeypatch)
    out = []
    for solver in ("thomas", "shared"):
        world, objects = _cloth_world(device, 0, newton_steps, cuttable)
        world.set_iterations(iterations)
        world.chain_solver = solver
        start = world.positions()
        world.simulate(0.04, 0.02)
        assert world.unstable.numpy().sum() == 0
        out.append(world.positions())
    assert _worst(start, out[1], objects) > 100 * TOL  # the solves had work to do
    assert _worst(out[0], out[1], objects) <= TOL
    assert keys and keys[0][3] == {"masked": cuttable}


@pytest.mark.parametrize("lanes", [1, 2, 64])
def test_shared_rounds_match_serial(device, lanes):
    # a 9 x 7 sheet whose families hold 6 to 13 chains: 1 or 2 lanes take each family in many rounds (rounds of
    # chains of several lengths, a lane idle in the last); 64 lanes take each in one (on the CPU a block has one lane
    # whatever is asked: the same rounds)
    out = []
    for solver in ("thomas", "shared"):
        v, t = cloth_grid(9, 7, 0.08, 0.06, plane="xz", origin=(0.0, 0.0, -0.06))
        b = SceneBuilder()
        obj = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, damping=1.0,
                          fixed=np.nonzero(v[:, 2] > -1e-9)[0], cuttable=True)
        world = b.finalize(2, device, substeps=4)
        world.chain_solver = solver
        world.chain_shared_lanes = lanes
        mask = world.state.edge_active.numpy()
        mask[1, 3::7] = 0
        world.state.edge_active.assign(mask)
        world.simulate(0.1, 0.05)
        out.append(world.positions())
    assert _worst(out[0], out[1], [(obj, 0.08)]) <= TOL


def test_shared_takes_a_window_past_other_particles(device):
    # a rod's particles come first and the cloth's after them: the cloth's window starts past particle 0; the rods
    # (a loop among them) keep the serial walk, the cloth takes the shared solve; both the same as the serial solve
    out = []
    for solver in ("thomas", "shared"):
        b = SceneBuilder()
        pts = np.stack([np.linspace(0.0, 0.05, 11), np.full(11, 0.1), np.zeros(11)], axis=1)
        rod = b.add_rod(pts, radius=5e-4, youngs_modulus=1e6, damping=0.5, fixed=[0])
        loop = b.add_rod(np.array([[0.0, 0.2, 0.0], [0.01, 0.2, 0.0], [0.01, 0.21, 0.0], [0.0, 0.21, 0.0]]),
                         radius=5e-4, youngs_modulus=1e5, closed=True, damping=0.5, fixed=[0])
        v, t = cloth_grid(5, 4, 0.04, 0.03, plane="xz", origin=(0.0, 0.0, -0.03))
        cloth = b.add_cloth(v, t, areal_density=0.2, stretch_stiffness=1e3, damping=1.0,
                            fixed=np.nonzero(v[:, 2] > -1e-9)[0][:2])
        world = b.finalize(2, device, substeps=5)
        world.chain_solver = solver
        lay = world._shared_chains[id(world.model.edge_chains)]
        window = cloth.particles
        assert lay.node_start == window.start > 0 and lay.num_nodes == window.stop - window.start
        assert world._shared_chains[id(world.model.rod_chains)] is None  # the loop: the serial walk
        world.simulate(0.1, 0.05)
        out.append(world.positions())
    assert _worst(out[0], out[1], [(cloth, 0.04), (rod, 0.05), (loop, 0.04)]) <= TOL


def test_shared_falls_back_beyond_its_shared_memory(device, monkeypatch):
    # a chain set whose window and scratch need more than SHARED_CHAIN_MAX_BYTES keeps the serial walk: no shared
    # kernel recorded, the serial positions exactly
    import lapwarp.world as world_module

    keys = _count_kernels(monkeypatch)
    monkeypatch.setattr(world_module, "SHARED_CHAIN_MAX_BYTES", 16 * 20)
    out = []
    for solver in ("thomas", "shared"):
        world, objects = _cloth_world(device, 0, 1, False)
        world.chain_solver = solver
        world.simulate(0.04, 0.02)
        out.append(world.positions())
    assert not keys
    assert np.array_equal(out[0], out[1])


def test_shared_setting_is_checked(device):
    world, _ = _rod_world(device, 0, 1, 1, False, False)
    world.chain_solver = "shared"
    for lanes in (0, 2000, 2.5, True):
        world.chain_shared_lanes = lanes
        with pytest.raises(ValueError, match="chain_shared_lanes"):
            world.step(0.02)


def test_shared_layout_needs_longest_first():
    # the rounds' loop bound is a round's first chain's length: a family stored otherwise is refused
    from lapwarp.chains import shared_chain_layout

    world, _ = _cloth_world("cpu", 0, 1, False)
    cs = world.model.edge_chains
    # the diagonals' family: chains of several lengths
    first, count = next(f[:2] for f in cs.families if cs.lengths[f[0]] > cs.lengths[f[0] + f[1] - 1])
    cs.lengths = cs.lengths.copy()
    cs.lengths[first:first + count] = cs.lengths[first:first + count][::-1]
    with pytest.raises(ValueError, match="longest first"):
        shared_chain_layout(cs, "cpu")


def test_env_config_selects_the_shared_solve(device):
    import lapwarp

    env = lapwarp.make("PrecisionCutting", num_envs=1, device=device, chain_solver="shared")
    assert env.world.chain_solver == "shared"
    lay = env.world._shared_chains[id(env.world.model.edge_chains)]
    assert lay is not None and lay.num_nodes == 1600 and lay.max_links == 39
    env.step(np.zeros((1, env.action_dim), dtype=np.float32))
    assert env.world.unstable.numpy().sum() == 0


def test_rod_frames_turn_a_right_angled_corner():
    # a square loop: at each corner the first director lay along the next tangent, and projecting it off left nothing
    # (NaN frames). Now every frame is finite and orthonormal with d3 along its segment
    b = SceneBuilder()
    corners = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.01, 0.01, 0.0], [0.0, 0.01, 0.0]])
    loop = b.add_rod(corners, radius=5e-4, youngs_modulus=1e5, closed=True)
    world = b.finalize(1, "cpu")
    q = world.state.segment_q.numpy()[0, loop.segments]
    assert np.isfinite(q).all()
    for s, quat in enumerate(q):
        x, y, z, w = quat
        d3 = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
        tangent = corners[(s + 1) % 4] - corners[s]
        assert np.allclose(d3, tangent / np.linalg.norm(tangent), atol=1e-6)
