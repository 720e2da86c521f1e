"""lapwarp: LapGym's surgical RL environments as a batched simulator in NVIDIA Warp.

Light imports only: ``import lapwarp`` does not compile kernels or initialise devices.
"""

from __future__ import annotations

__version__ = "0.1.0"

from lapwarp.registry import check_config, list_tasks, make  # noqa: E402


def _register_gymnasium() -> None:
    # gymnasium.make("lapwarp/Reach-v0") works once lapwarp is imported; the adapters load lazily.
    import gymnasium as gym

    for task in list_tasks():
        env_id = f"lapwarp/{task}-v0"
        if env_id not in gym.registry:
            gym.register(env_id, entry_point="lapwarp.vecenv:LapwarpGymEnv", kwargs={"task": task},
                         vector_entry_point="lapwarp.vecenv:LapwarpVectorEnv")


_register_gymnasium()



def __getattr__(name: str):
    # SceneBuilder imports the physics kernels' Python modules; load it only when asked for.
    if name == "SceneBuilder":
        from lapwarp.builder import SceneBuilder

        return SceneBuilder
    raise AttributeError(f"module 'lapwarp' has no attribute {name!r}")


__all__ = ["SceneBuilder", "__version__", "check_config", "list_tasks", "make"]
