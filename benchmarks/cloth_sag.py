"""PrecisionCutting's cloth sag against its solver settings (physics_substeps x cloth_newton_steps), as JSON lines.

    python benchmarks/cloth_sag.py --device cpu --settings 64x4 8x2 8x1 16x1 --seconds 5 --out sag.jsonl

The task's cloth (75 mm, 40 x 40, 90 N/m edge springs, fixed along its far edge and at its near corners) hangs under
gravity from its flat rest state; the scissors stay where the reset puts them (zero actions, no reset noise), clear of
the cloth. The chain solver converges on the sheet's sag as substeps and Newton steps grow (64 x 4 and 128 x 4 agree to
0.1 mm), so the sag at a cheaper setting against the converged one is that setting's error. Reported once per simulated
second: the centre vertex's height and the lowest vertex's (m; negative is down). The speed of each setting is
measured on the GPU with ``bench_env.py --set physics_substeps=S cloth_newton_steps=N``.
"""

from __future__ import annotations

import argparse
import json

import torch
import warp as wp

import lapwarp
from lapwarp.cli import default_device

GRID = 40


def parse_setting(text: str) -> tuple[int, int]:
    try:
        substeps, newton = (int(part) for part in text.split("x"))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(f"expected SUBSTEPSxNEWTON, e.g. 8x2; got {text!r}") from exc
    if substeps < 1 or newton < 1:
        raise argparse.ArgumentTypeError(f"substeps and Newton steps must be positive; got {text!r}")
    return substeps, newton


def write_rows(path: str, device: str, rows: list[dict]) -> None:
    """``rows`` as JSON lines, each with the device it ran on."""
    with open(path, "w") as f:
        for row in rows:
            f.write(json.dumps({"device": device, **row}) + "\n")


def sag_series(substeps: int, newton: int, seconds: int, device: str) -> dict:
    env = lapwarp.make("PrecisionCutting", num_envs=1, device=device, physics_substeps=substeps,
                       cloth_newton_steps=newton, ptsd_noise=[0.0, 0.0, 0.0, 0.0])
    env.reset()
    first = env.cloth_obj.particle_start
    steps_per_second = round(1.0 / (env.cfg.time_step * env.cfg.frame_skip))
    action = torch.zeros(1, env.num_actions, device=env.device)
    centre, lowest = [], []
    for step in range(seconds * steps_per_second):
        env.step(action)
        if (step + 1) % steps_per_second == 0:
            z = wp.to_torch(env.world.state.particle_q)[0, first:first + GRID * GRID, 2]
            centre.append(float(z[GRID // 2 + GRID * (GRID // 2)]))
            lowest.append(float(z.min()))
    env.close()
    return {"physics_substeps": substeps, "cloth_newton_steps": newton, "centre_z_m": centre, "lowest_z_m": lowest}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default=default_device())
    parser.add_argument("--settings", nargs="+", type=parse_setting, default=[(64, 4), (8, 2)],
                        metavar="SxN", help="physics_substeps x cloth_newton_steps")
    parser.add_argument("--seconds", type=int, default=5, help="simulated seconds (one record per second)")
    parser.add_argument("--out", default=None, help="JSON lines output")
    args = parser.parse_args(argv)
    if args.seconds < 1:
        parser.error("--seconds must be at least 1")
    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    rows = []
    for substeps, newton in args.settings:
        row = sag_series(substeps, newton, args.seconds, args.device)
        rows.append(row)
        print(f"{substeps:4d} x {newton}: centre z (mm) per second "
              + " ".join(f"{1e3 * z:6.2f}" for z in row["centre_z_m"])
              + f"; lowest {1e3 * row['lowest_z_m'][-1]:.2f}", flush=True)
    if args.out:
        write_rows(args.out, args.device, rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
