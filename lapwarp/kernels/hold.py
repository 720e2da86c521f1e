"""Resting tets held (``World.tet_hold_speed``): the per-env state the prediction, the per-vertex tet sweep, the
rotation refresh and the contact kernels share (docs/physics.md, "Resting tets held"). Its own module: the XPBD
kernels import the contact kernels, and both read it."""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.struct
class TetHold:
    """The per-vertex tet solve's resting envs (``World.tet_hold_speed``): an env whose tet vertices all moved slower
    than ``sqrt(speed2)`` (m/s) at the start of ``after`` substeps in a row is *held*: its tet vertices start the next
    substep exactly where they are, with no velocity, and its sweep (``vbd.fused_vertex_kernel``), rotation refresh
    and its surfaces' contact boxes (``contact.surface_leaf_bounds``) are skipped, so a resting body costs little until
    something moves it. The prediction sets ``moving[env]`` where a tet vertex is faster (a push, the deltas applied
    there) and so does any contact correction of a pair that moves tet vertices (``contact.add_pair_force``); the
    sweep then runs and its last one of the substep counts ``quiet[env]`` (reset to 0 by that, saturating at
    ``after``) and clears ``moving``; a sweep that skips a held env marks it ``after + 1``, which the contact boxes
    read (:func:`tets_held_now`: the count alone would also call held an env whose sweep has just moved it, in the
    substep its count reaches ``after``). ``after`` 0: off (the arrays may then be empty)."""

    quiet: wp.array(dtype=wp.int32)
    moving: wp.array(dtype=wp.int32)
    after: int
    speed2: float


@wp.func
def tets_held(hold: TetHold, env: int) -> bool:
    """Whether ``env``'s tet vertices are held this substep: quiet for ``hold.after`` substeps and none moving now."""
    if hold.after == 0:
        return False
    return hold.quiet[env] >= hold.after and hold.moving[env] == 0


@wp.func
def tets_held_now(hold: TetHold, env: int) -> bool:
    """After this substep's tet sweep: whether it skipped ``env`` (held) and nothing has touched its tets since, so
    they are where they were when the sweep last solved them."""
    if hold.after == 0:
        return False
    return hold.quiet[env] > hold.after and hold.moving[env] == 0
