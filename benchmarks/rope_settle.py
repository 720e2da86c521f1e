"""Whether RopeCutting's pre-tensioned rope settles after a bump, per solver setting (substeps x Newton steps of the
rope's stretch solve), as JSON lines.

    python benchmarks/rope_settle.py --device cpu --settings 40x6 40x4 40x3 --pushes 0.005 0.02 --out settle.jsonl

One rope of the task (19 segments stretched to 5x their rest length between two fixed ends, 42 N of tension) starts
with its middle third displaced by PUSH along y (sideways) or z (down), tapering to the walls, at rest, and is
simulated for ``--seconds``. A setting that holds the rope settles on the taut-string closed form (29 micrometres of
mid-span sag, the rope in its vertical plane); one that does not keeps swinging (the tension's transverse response
overshoots: docs/physics.md). Reported: the mid-span sag over the closed form and the largest sideways offset at the
end.
"""

from __future__ import annotations

import argparse

import numpy as np
import warp as wp
from cloth_sag import parse_setting, write_rows

from lapwarp.builder import SceneBuilder
from lapwarp.cli import default_device
from lapwarp.tasks.dissection.rope_cutting import NODES, SEGMENTS, RopeCuttingConfig

SPRING, CONTRACTION, MASS, SPAN = 1.0e4, 0.8, 0.01, 0.1  # N/m per segment spring, rest-length ratio, kg, m


def taut_string_sag() -> float:
    """Mid-span sag of the nodes either side of the middle: P x (L - x) / (2 H h) at x = L/2 -+ h/2."""
    h = SPAN / SEGMENTS
    tension = SPRING * (h - (1.0 - CONTRACTION) * h)
    load = MASS / SEGMENTS * 9.81
    return load / h * (SPAN / 2 - h / 2) * (SPAN / 2 + h / 2) / (2.0 * tension)


def task_rope(device: str, substeps: int, newton: int, cuttable: bool = False):
    """One rope of the task, stretched straight between (-50, 0, 0) and (50, 0, 0) mm at rest: (world, rope)."""
    cfg = RopeCuttingConfig()
    b = SceneBuilder()
    x = np.stack([np.linspace(-SPAN / 2, SPAN / 2, NODES), np.zeros(NODES), np.zeros(NODES)], axis=1)
    area = np.pi * cfg.rope_radius**2
    rope = b.add_rod(x, radius=cfg.rope_radius, density=MASS / (area * SPAN),
                     youngs_modulus=SPRING * (SPAN / SEGMENTS) / area, fixed=[0, NODES - 1], damping=cfg.rope_damping,
                     cuttable=cuttable, stretch_rest_scale=1.0 - CONTRACTION)
    world = b.finalize(num_envs=1, device=device, substeps=substeps)
    world.rod_newton_steps = newton
    return world, rope


def bumped_rope(device: str, substeps: int, newton: int, push: float, axis: int):
    """``task_rope`` with its middle third displaced by ``push`` along ``axis``, tapering to the walls."""
    world, rope = task_rope(device, substeps, newton)
    q = world.state.particle_q.numpy()
    x = q[0, :NODES, 0]
    q[0, :NODES, axis] += push * np.clip(1.5 * (1.0 - np.abs(x) / (SPAN / 2)), 0.0, 1.0)
    world.state.particle_q.assign(q)
    return world, rope


def settle(device: str, substeps: int, newton: int, push: float, axis: int, seconds: float,
           tolerance: float = 0.0) -> dict:
    """The bumped rope after ``seconds``; ``tolerance`` > 0 runs the register-resident chain solve with that Newton
    tolerance (m; ``World.rod_newton_tolerance``, RopeCutting's GPU setting) instead of the serial walk."""
    world, rope = bumped_rope(device, substeps, newton, push, axis)
    if tolerance > 0.0:
        world.chain_solver = "registers"
        world.rod_newton_tolerance = tolerance
    world.simulate(seconds, dt=0.1)
    p = world.positions(rope)[0]
    sag = -p[NODES // 2 - 1:NODES // 2 + 1, 2].mean()
    return {"substeps": substeps, "newton_steps": newton, "newton_tolerance_m": tolerance, "push_m": push,
            "axis": "xyz"[axis], "seconds": seconds,
            "sag_over_closed_form": float(sag / taut_string_sag()), "max_sideways_m": float(np.abs(p[:, 1]).max()),
            "unstable": bool(world.unstable.numpy().any())}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--settings", nargs="+", type=parse_setting, default=[(40, 6)], metavar="SxN")
    parser.add_argument("--pushes", nargs="+", type=float, default=[0.005, 0.01, 0.02], help="bump heights (m)")
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--newton-tolerance", type=float, default=0.0,
                        help="m; > 0: the register-resident solve stopping its Newton steps there (0: every step)")
    parser.add_argument("--out", default=None, help="JSON lines output")
    args = parser.parse_args(argv)
    if not args.seconds > 0 or not all(0 < p < 0.05 for p in args.pushes):
        parser.error("--seconds must be positive and every push in (0, 0.05) m")
    if not 0.0 <= args.newton_tolerance < 1.0:
        parser.error("--newton-tolerance must be in [0, 1) m")
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    rows = []
    for substeps, newton in args.settings:
        cells = []
        for push in args.pushes:
            for axis in (1, 2):
                row = settle(args.device, substeps, newton, push, axis, args.seconds, args.newton_tolerance)
                rows.append(row)
                cells.append(f"{1e3 * push:g} mm {row['axis']}: {row['sag_over_closed_form']:.3f}")
        print(f"{substeps:3d} x {newton:2d}: sag / closed form after {args.seconds:g} s  " + "  ".join(cells),
              flush=True)
    if args.out:
        write_rows(args.out, args.device, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
