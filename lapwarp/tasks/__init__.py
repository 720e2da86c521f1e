"""Task envs, one module per task under its track, and the parts they are built from.

Layout::

    tasks/spec.py          declarations: RewardSpec (features, weights, deltas, success/failure), ObservationSpec,
                           ActionLayout; the env base (lapwarp.env.BatchedEnv) derives the rest from them
    tasks/rig.py           InstrumentRig: pivotized instruments, their bodies, colliders, jaws, activation, grasping,
                           one action path for continuous and discrete actions
    tasks/deformable.py    DeformableObject: a deformable's builder call, anchors / body attachments, reset placement
    tasks/targets.py       target sampling on the device (separated points, candidate tables, active-target draws)
    tasks/camera.py        fixed cameras, the oblique endoscope (poses, inverse kinematics, sight lines)
    tasks/spatial/                  Reach, DeflectSpheres, SearchForPoint
    tasks/deformable_manipulation/  TissueManipulation, PickAndPlace, GraspLiftAndTouch
    tasks/dissection/               RopeCutting, PrecisionCutting, TissueDissection
    tasks/thread_manipulation/      ThreadInHole, RopeThreading, LigatingLoop

docs/adding-a-task.md walks through writing a task on these parts.
"""
