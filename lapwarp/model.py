"""Model / State / Control: the struct-of-arrays data of a batch of scenes.

* ``Model`` is static after ``SceneBuilder.finalize``: topology in *local* indices shared by all envs,
  rest shapes and material parameters. A per-env parameter has leading dimension 1 (shared) or
  ``num_envs`` (randomised) and kernels read it as ``p[env % p.shape[0]]``.
* ``State`` is dynamic and env-major: every array is ``(num_envs, count)``.
* ``Control`` holds the per-env commands after action scaling.

Physics fields start empty (count 0) so a purely kinematic scene such as Reach carries no cost.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import warp as wp


@dataclass
class Model:
    """Static description of one scene, shared by all ``num_envs`` copies."""

    num_envs: int
    device: str
    gravity: wp.vec3 = field(default_factory=lambda: wp.vec3(0.0, 0.0, 0.0))
    particle_count: int = 0


@dataclass
class State:
    """Dynamic per-env arrays, shape ``(num_envs, count)``."""

    particle_q: wp.array2d | None = None
    particle_qd: wp.array2d | None = None


@dataclass
class Control:
    """Per-env commands after action scaling."""

    pass
