"""World: owns one batch of scenes (model, state, control, per-env RNG) and advances its physics.

The World is what ``SceneBuilder.finalize`` returns and what every task env steps. It never imports
task code. ``step()`` and ``reset(env_mask)`` only launch kernels on preallocated arrays, so they
can be captured into a CUDA graph by the env that owns the World.
"""

from __future__ import annotations

import warp as wp

from lapwarp.kernels import world_kernels
from lapwarp.model import Control, Model, State


class World:
    """A batch of ``num_envs`` independent scenes on one Warp device.

    Args:
        model: static scene description (topology shared by all envs).
        state: initial dynamic state; a copy is kept so ``reset`` can restore masked envs in place.
        control: per-env commands written by the env's action kernels.
        seed: seed of the per-env device RNG streams (env ``i`` uses stream ``rand_init(seed, i)``).
    """

    def __init__(self, model: Model, state: State | None = None, control: Control | None = None, seed: int = 0):
        self.model = model
        self.num_envs = model.num_envs
        self.device = wp.get_device(model.device)
        self.state = state if state is not None else State()
        self.control = control if control is not None else Control()
        self.seed = int(seed)
        self.rng = wp.empty(self.num_envs, dtype=wp.uint32, device=self.device)
        self.unstable = wp.zeros(self.num_envs, dtype=wp.int32, device=self.device)
        self.seed_rng(self.seed)

    def seed_rng(self, seed: int) -> None:
        """Re-seed every env's RNG stream (host-side call, not part of the captured step)."""
        self.seed = int(seed)
        wp.launch(world_kernels.init_env_rng, dim=self.num_envs, inputs=[self.seed], outputs=[self.rng],
                  device=self.device)

    def step(self, dt: float) -> None:
        """Advance the physics of every env by ``dt`` seconds. A kinematic scene has nothing to do."""

    def reset(self, env_mask: wp.array) -> None:
        """Restore the initial physical state of the envs whose ``env_mask`` entry is non-zero, in place."""
        wp.launch(world_kernels.clear_masked_flags, dim=self.num_envs, inputs=[env_mask], outputs=[self.unstable],
                  device=self.device)
