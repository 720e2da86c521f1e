"""How far each Newton step of a task's rod chain solve corrects its links, along the scripted expert's episodes
(forty-second session's record of the measurement behind ``World.rod_newton_tolerance``; CPU, the serial walk).

    python benchmarks/results/session42/instrumented/newton_corrections.py RopeThreading 60 1e-5 3e-5 1e-4
    python benchmarks/results/session42/instrumented/newton_corrections.py ThreadInHole 60 3e-4 1e-3 3e-3 \\
        configuration=flexible

A copy of ``chains.solve_chains`` (its source patched at run time, written to a temporary module) measures each
Newton step's largest link correction ``|dl_k| (w_k + w_{k+1})`` and accumulates, per open chain, in the scratch
column the serial walk leaves unused for open chains (``scratch_e``; the chain needs >= 10 links): for each of the
three thresholds T, the Newton steps an exit after the first step correcting less than T would run, how often the
first step corrected less than T, and the largest correction of the second step in those sweeps.
"""

import importlib
import inspect
import sys
import tempfile
from pathlib import Path

import numpy as np

import lapwarp
from lapwarp.experts import make_expert
from lapwarp.kernels import chains

MEASURE = """        largest = float(0.0)
        for k in range(m):
            k1 = k + 1
            if k1 >= nodes:
                k1 = k1 - nodes
            w_pair = inv_mass[pe, chain_node[nb + k * stride]] + inv_mass[pe, chain_node[nb + k1 * stride]]
            largest = wp.max(largest, wp.abs(scratch_d[env, s0 + k * stride]) * w_pair)
        for t in range(3):
            if ran[t] == 0 and (largest < thresholds[t] or it == newton_steps - 1):
                ran[t] = it + 1
            if it == 0 and largest < thresholds[t]:
                first_below[t] = 1
            if it == 1 and first_below[t] != 0:
                slot = s0 + (7 + t) * stride
                scratch_e[env, slot] = wp.max(scratch_e[env, slot], largest)
"""
SUMMARY = """    if chain_closed[r] == 0:
        for t in range(3):
            scratch_e[env, s0 + t * stride] = scratch_e[env, s0 + t * stride] + float(ran[t])
            scratch_e[env, s0 + (4 + t) * stride] = scratch_e[env, s0 + (4 + t) * stride] + float(first_below[t])
        scratch_e[env, s0 + 3 * stride] = scratch_e[env, s0 + 3 * stride] + 1.0
"""


def instrumented_kernel(thresholds: list[float]):
    """``chains.solve_chains`` with the measurement above (thresholds compiled in)."""
    src = inspect.getsource(chains.solve_chains.func)
    src = src.replace("def solve_chains(", "def solve_chains_measured(")
    src = src.replace("    for it in range(newton_steps):\n", "    ran = wp.vec3i()\n    first_below = wp.vec3i()\n"
                      "    thresholds = wp.vec3(" + ", ".join(repr(float(t)) for t in thresholds) + ")\n"
                      "    for it in range(newton_steps):\n", 1)
    marker = "        # ---- corrections dx_j"
    src = src.replace(marker, MEASURE + marker, 1) + SUMMARY
    folder = tempfile.mkdtemp()
    Path(folder, "newton_measured.py").write_text(
        "import warp as wp\nfrom lapwarp.kernels.chains import node_row, segment_dir  # noqa: F401\n\n" + src)
    sys.path.insert(0, folder)
    return importlib.import_module("newton_measured").solve_chains_measured


def main(argv: list[str]) -> None:
    task, steps, thresholds = argv[0], int(argv[1]), [float(t) for t in argv[2:5]]
    overrides = dict(item.split("=", 1) for item in argv[5:])
    chains.solve_chains = instrumented_kernel(thresholds)  # what the World launches for the serial walk
    env = lapwarp.make(task, num_envs=8, device="cpu", seed=0, chain_solver="thomas", **overrides)
    expert = make_expert(env)
    env.reset()
    for _ in range(steps):
        env.step(expert())
    e = env.world._rod_scratch[3].numpy()
    cs = env.world.model.rod_chains
    print(f"{task} {overrides}: {steps} expert steps, 8 envs, {env.world.rod_newton_steps} Newton steps per sweep")
    for first, count, link_base, _ in cs.families:
        open_chains = ~cs.closed_host[first:first + count]
        if not open_chains.any():
            continue

        def column(c, base=link_base, n=count, keep=open_chains):
            return e[:, base + c * n: base + (c + 1) * n][:, keep]

        launches = column(3)
        for t, threshold in enumerate(thresholds):
            print(f"  T = {threshold:g} m: steps run {np.mean(column(t) / launches):.3f}, first step below T in "
                  f"{np.mean(column(4 + t) / launches):.1%} of sweeps, the second step's largest correction there "
                  f"{column(7 + t).max():.2e} m")


if __name__ == "__main__":
    main(sys.argv[1:])
