"""Why tests/test_chains_registers.py::test_env_config_selects_the_register_solve failed on an H200 (thirty-fourth
session's lease): RopeCutting plucked by ~2 mm, one env step with the hook still, the thomas and register chain solves
3.3 cm apart on the GPU (bit-identical on the CPU over three steps). Runs each solve twice on the device and prints
the pairwise largest differences, to tell a solve that differs from one whose runs differ from each other."""

import sys

import numpy as np

import lapwarp

sys.path.insert(0, "tests")
from test_chains_registers import _perturb  # noqa: E402

device = sys.argv[1] if len(sys.argv) > 1 else "cpu"
runs = {}
for solver, rep in (("thomas", 0), ("thomas", 1), ("registers", 0), ("registers", 1)):
    env = lapwarp.make("RopeCutting", num_envs=2, device=device, chain_solver=solver)
    env.reset(seed=3)
    _perturb(env.world, 2e-3, seed=5)
    env.step(np.zeros((2, env.action_dim), dtype=np.float32))
    runs[(solver, rep)] = env.world.positions()
    print(solver, rep, "rope 0, first nodes' x:", np.round(runs[(solver, rep)][0, :5, 0], 5))
keys = list(runs)
for i, a in enumerate(keys):
    for b in keys[i + 1:]:
        print(a, b, "max |difference| (m):", float(np.abs(runs[a] - runs[b]).max()))
