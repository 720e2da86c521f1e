"""TissueManipulationEnv: bring a landmark on a deformable tissue flap to a target point by moving the grasper that
holds the flap (sofa_env's TissueManipulationEnv; task-cards §2).

A yellow silicone "gallbladder" flap stands on a liver: its base band is fixed, a grasper holds a patch at its top
and moves in the flap's plane (x, z; y fixed). A black landmark on the flap's camera-facing side (one of nine
candidate points) has to reach a target point (drawn as a turquoise dot over the images); the landmark moves because
the flap deforms between the fixed band and the moved patch.

Physics (SI, like sofa_env's scene): the flap is sofa_env's outline (the polygon of ``tissue_volumetric.msh`` in the
xz plane, 10 mm thick) as a co-rotated XPBD tet mesh (``ruled_sheet_tets``: 12 x 5 x 2 = 120 nodes, 264 tets; the
original has 145 nodes, 348 tets), E = 80 kPa, nu = 0.47, 47.47 g, gravity 9.81 m/s^2 along -z. Nodes below z = 0.07 m
are fixed (sofa_env's BoxROI; its flange, all fixed, is drawn but not simulated). The nodes in sofa_env's grasp box
(0.01, -0.015, 0.135)..(0.03, 0.005, 0.1525) are attached rigidly (zero compliance) to a kinematic body at their
centroid, the grasper's motion target (sofa_env's ``rigidify`` and its 2e6 N/m, 2e4 N m/rad springs, which are rigid
for a 47 g flap). A landmark is a point of the surface carried barycentrically by the tet that contains it.

Convergence (measured on the CPU, tests/test_tissue_manipulation.py states it): the equilibrium under the moved patch
does not depend on the Young's modulus, only gravity's sag does (0.1 mm converged). XPBD at ``physics_substeps`` = 20
per 0.1 s is softer than the converged material (sag 2.1 mm): over 15 mm moves along x and then along z, which buckle
the flap, its landmarks are up to 3.0 mm (mean 1.1 mm) from the converged answer (XPBD at 1,600 substeps; at 800
within 0.11 mm of it, at 200 within 1.2 mm; the landmarks travel 21 mm); ``physics_substeps=None`` picks the substeps
that resolve the material's waves (hundreds; see ``World.substeps_for``). ``tissue_solver="vbd"`` solves the tets per
vertex (kernels/vbd.py; the band's fixed nodes anchor the flap): at the default 20 substeps within 0.41 mm (mean 0.22
mm) of the converged answer, at 40 within 0.12 mm, and VBD at 400 substeps agrees with XPBD at 1,600 within 0.07 mm.
The default stays XPBD: the converged flap traces narrower reachable regions at low x than sofa_env's (landmarks 4 and
7 reach -15.2 and -11.7 mm where sofa_env's reach -19 mm or less; XPBD's soft flap matches its boxes within 3.1 mm),
our 264 linear tets at nu 0.47 (sofa_env meshes 348) probably lock in bending once converged, and the per-vertex
solve's GPU speed and the PPO rows were not measured for it. Each solver has its own stored polygons.

Targets are sampled as in sofa_env: uniformly in the landmark's *reachable polygon* (the path the landmark traces
while the grasper goes around the workspace's border), at least ``minimum_target_distance`` from the landmark. The
polygons are traced with this physics (``trace_reachable_polygons``; sofa_env ships the ones its scene traced) and
stored in ``lapwarp/assets/data/tissue_manipulation_reachable.npz`` (``..._reachable_vbd.npz`` for the per-vertex
solve).

Reward features (Table A: the paper's weights -1, +10, -5, 0, 0): the landmark-target distance over world x and z
(sofa_env's ``distance_calculation_2d``) over the workspace diagonal, reaching the target (success), being stuck (the
last 50 distances span less than 0.5 mm; the episode ends, sofa_zoo's end criteria), an action that would have left
the workspace (the component keeps its old value), an unstable simulation (a node moved more than 2 mm in the last
physics step). STATE observation (9, Table D): grasper, target and landmark positions, x and z normalised over the
workspace to [-1, 1] at its border, y set to 0 (sofa_env's). Landmark and target lie below the grasper's workspace,
so their values reach about -2.5.

Deliberate differences from sofa_env (task-cards §2, §12):

* sofa_env's ``randomize_grasping_point`` moves only the grasper's visual body (its physics always grasps the patch);
  here too, and the docstring of the field says so.
* Discrete actions: sofa_env's 0.5 mm/s moves 0.05 mm per step (a target 10 mm away needs 200 steps of the 500): the
  default here is the continuous maximum speed (1 mm per step); ``discrete_velocity`` sets sofa_env's.
* The episode always ends when stuck (sofa_zoo's end criteria; sofa_env's constructor default ends only on success).
* Every episode starts from the same settled scene (sofa_env resets SOFA and settles again: the same state).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import torch
import trimesh
import warp as wp

from lapwarp import launching
from lapwarp.assets.meshes import ruled_sheet_tets
from lapwarp.builder import SceneBuilder
from lapwarp.config import Count, EnvConfig, NonNegative, Positive, Range
from lapwarp.env import BatchedEnv
from lapwarp.experts import Expert
from lapwarp.kernels.geometry import horizontal_distance
from lapwarp.kernels.random import rand_uniform
from lapwarp.kernels.raster import world_to_pixel
from lapwarp.tasks.spec import ActionBlock, ActionLayout, Feature, ObservationLayout, ObservationSpec, RewardSpec
from lapwarp.tasks.targets import draw_index
from lapwarp.visuals import CameraSpec, VisualObject, VisualScene, cylinder_mesh, look_at_transform, sphere_mesh
from lapwarp.world import World

wp.set_module_options({"enable_backward": False})

REWARDS = RewardSpec(
    Feature("distance_to_target", -1.0),
    Feature("one_time_reward_goal", 10.0),
    Feature("one_time_penalty_is_stuck", -5.0),
    Feature("one_time_penalty_invalid_action", 0.0),
    Feature("one_time_penalty_unstable_simulation", 0.0),
    success="one_time_reward_goal",
    failure="one_time_penalty_is_stuck",
)
F = REWARDS.F
OBS = ObservationSpec("grasper", "target", "landmark")
CRITIC = OBS.extend("offset_to_target", "grasper_to_landmark")

#: sofa_env's flap outline in mesh millimetres (x, z), from its base to its top: the left and the right side.
OUTLINE_LEFT = ((-50.0, 0.0), (-50.0, 40.0), (-46.76, 51.70), (-4.53, 104.93))
OUTLINE_RIGHT = ((0.0, 0.0), (7.17, 63.35), (8.08, 75.59), (7.77, 100.21), (1.62, 102.57))
MESH_OFFSET = (0.02, 0.0, 0.045)  # sofa_env's translation of the mesh, m
THICKNESS = 0.01
ROWS, COLUMNS = 12, 5  # 6 columns make sliver tets near the narrow top that jitter at 20 substeps
FIXED_BELOW_Z = 0.07
GRASP_BOX = ((0.01, -0.015, 0.135), (0.03, 0.005, 0.1525))
GRASPER_Y = -0.005
#: sofa_env's landmark candidates (vertices 3, 4, 17, 21, 22, 5, 34, 20, 26 of its collision surface), m
LANDMARKS = ((0.0131, -0.01, 0.1197), (0.0140, -0.01, 0.1291), (0.0174, -0.01, 0.1239), (0.0215, -0.01, 0.1277),
             (0.0210, -0.01, 0.1190), (0.0077, -0.01, 0.1278), (0.0274, -0.01, 0.1298), (0.0279, -0.01, 0.1221),
             (0.0065, -0.01, 0.1201))
NUM_LANDMARKS = len(LANDMARKS)
POLYGON_VERTICES = 48
#: the reachable polygons traced with each tissue solve (``tissue_solver``): the landmarks' paths differ by a few mm
POLYGON_FILES = {
    "xpbd": Path(__file__).resolve().parents[2] / "assets" / "data" / "tissue_manipulation_reachable.npz",
    "vbd": Path(__file__).resolve().parents[2] / "assets" / "data" / "tissue_manipulation_reachable_vbd.npz",
}
TISSUE_COLOR, LIVER_COLOR, GRASPER_COLOR, LANDMARK_COLOR = (0.93, 0.8, 0.25), (0.55, 0.12, 0.1), (0.7, 0.72, 0.75), \
    (0.05, 0.05, 0.05)
OVERLAY_COLOR = wp.constant(wp.vec3(51.0, 223.0, 255.0))  # sofa_env's turquoise, RGB
_STUCK_WINDOW = 50


@dataclass(kw_only=True)
class TissueManipulationConfig(EnvConfig):
    """TissueManipulationEnv parameters (Tables B, C: the paper's = sofa_zoo's values); SI units.

    Attributes:
        end_position_threshold: landmark-target distance (x, z) that counts as success, m (paper: 2 or 5 mm).
        randomize_landmark: draw the landmark from the nine candidates at every reset (else ``landmark_index``).
        landmark_index: the fixed landmark (sofa_env's ``target_idx_id``, default 2: its vertex 17).
        randomize_grasping_point: move the grasper's *visual* body by x in [-5, 5] mm, z in [-5, 0] mm at reset
            (sofa_env's: it never changes where the tissue is held).
        minimum_target_distance: a target is at least this far (x, z) from the landmark at reset, m.
        maximum_velocity: grasper speed at action 1, m/s (sofa_zoo's 10 mm/s: 1 mm per env step).
        discrete_velocity: grasper speed of a discrete action, m/s (sofa_env: 0.5 mm/s; see the module docstring).
        workspace_low / workspace_high: the grasper's (x, z) bounds, m (sofa_zoo's, absolute).
        squared_distance: the distance feature squared (sofa_env's ``squared_distance``).
        stuck_range: the episode ends stuck when the last 50 distances span less than this, m.
        stability_threshold: a node moving more than this in a physics step flags an unstable simulation, m.
        youngs_modulus (Pa), poisson_ratio, tissue_mass (kg), gravity (m/s^2 along -z): sofa_env's tissue.
        damping_rate: the flap's velocity damping rate, 1/s (stands in for sofa_env's implicit solver's Rayleigh
            damping 0.1 M + 0.1 K, which lets the flap settle within a step; the equilibrium does not depend on it).
        settle_steps: sofa_zoo's; the scene settles ``max(settle_steps - 1, 1)`` physics steps (sofa_env's count).
        physics_substeps: XPBD substeps per physics step (None: automatic, see the module docstring).
        tissue_solver: the flap's tet solve (``World.tet_method``): ``xpbd`` (default) or ``vbd`` (per vertex, close to
            the converged material at the default substeps; see the module docstring); each has its own reachable
            polygons.
        camera_position / camera_look_at: sofa_zoo's camera, m (vertical FoV 57 degrees, +z up).
        show_target: draw the target over RGB images (sofa_env's overlay; ``deactivate_overlay`` = False).
    """

    time_step: Positive = 0.1
    frame_skip: Count(1000) = 1
    max_episode_steps: Count(1_000_000) = 500
    end_position_threshold: Positive = 0.002
    randomize_landmark: bool = True
    landmark_index: Annotated[int, Range(ge=0, le=NUM_LANDMARKS - 1)] = 2
    randomize_grasping_point: bool = True
    minimum_target_distance: NonNegative = 0.01
    maximum_velocity: Positive = 0.01
    discrete_velocity: Positive = 0.01
    workspace_low: tuple[float, float] = (-0.035, 0.1275)
    workspace_high: tuple[float, float] = (0.065, 0.1675)
    squared_distance: bool = False
    stuck_range: NonNegative = 5.0e-4
    stability_threshold: Positive = 2.0e-3
    youngs_modulus: Positive = 8.0e4
    poisson_ratio: Annotated[float, Range(ge=0.0, lt=0.5)] = 0.47
    tissue_mass: Positive = 0.04747
    gravity: NonNegative = 9.81
    damping_rate: NonNegative = 10.0
    settle_steps: Annotated[int, Range(ge=0, le=10_000)] = 10
    physics_substeps: Count(100_000) | None = 20
    tissue_solver: Literal["xpbd", "vbd"] = "xpbd"
    camera_position: tuple[float, float, float] = (0.0155, -0.2068, 0.1069)
    camera_look_at: tuple[float, float, float] = (0.0155, 0.0, 0.1069)
    show_target: bool = True

    def validate(self, reward_features, supported_observations) -> None:
        super().validate(reward_features, supported_observations)
        low, high = np.asarray(self.workspace_low), np.asarray(self.workspace_high)
        if np.any(low >= high):
            raise ValueError(f"workspace_low={self.workspace_low} must be below workspace_high={self.workspace_high}")
        start = grasp_patch_center()[[0, 2]]
        if np.any(start < low) or np.any(start > high):
            raise ValueError(f"the grasper starts at (x, z) = {tuple(start.round(4))}, outside the workspace "
                             f"{self.workspace_low}..{self.workspace_high}")


def tissue_mesh() -> tuple[np.ndarray, np.ndarray]:
    """The flap's nodes (m, world frame) and tets: sofa_env's outline, 10 mm thick along -y."""
    v, t = ruled_sheet_tets(np.asarray(OUTLINE_LEFT) * 1e-3, np.asarray(OUTLINE_RIGHT) * 1e-3, ROWS, COLUMNS,
                            THICKNESS)
    return v + np.asarray(MESH_OFFSET), t


def grasp_patch(vertices: np.ndarray) -> np.ndarray:
    """Indices of the nodes in sofa_env's grasp box."""
    low, high = (np.asarray(b) for b in GRASP_BOX)
    return np.nonzero(np.all((vertices >= low - 1e-9) & (vertices <= high + 1e-9), axis=1))[0]


def grasp_patch_center() -> np.ndarray:
    """The grasper's start: the centroid of the grasped nodes (sofa_env's rigid frame), m."""
    v, _ = tissue_mesh()
    return v[grasp_patch(v)].mean(axis=0)


def embed_points(points: np.ndarray, vertices: np.ndarray, tets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each point the tet that contains it (the least outside one, for points on the surface) and its barycentric
    weights: ``(k,)`` tet indices and ``(k, 4)`` weights (sofa_env's barycentric mapping)."""
    x0 = vertices[tets[:, 0]]
    basis = np.stack([vertices[tets[:, i]] - x0 for i in (1, 2, 3)], axis=2)  # (T, 3, 3)
    inv = np.linalg.inv(basis)
    index, weights = [], []
    for p in np.asarray(points, dtype=np.float64):
        b = np.einsum("tij,tj->ti", inv, p - x0)
        w = np.concatenate([1.0 - b.sum(axis=1, keepdims=True), b], axis=1)
        best = int(np.argmax(w.min(axis=1)))
        if w[best].min() < -1e-3:
            raise ValueError(f"point {p} is not inside the tissue mesh")
        index.append(best)
        weights.append(np.clip(w[best], 0.0, 1.0) / np.clip(w[best], 0.0, 1.0).sum())
    return np.asarray(index, dtype=np.int32), np.asarray(weights, dtype=np.float32)


def load_reachable_polygons(tissue_solver: str = "xpbd") -> np.ndarray:
    """The landmarks' reachable polygons ``(9, 48, 2)`` (x, z in m) stored by ``trace_reachable_polygons`` for the
    tissue solve ``tissue_solver``."""
    with np.load(POLYGON_FILES[tissue_solver]) as data:
        return data["polygons"].astype(np.float32)


# ---------------------------------------------------------------------------- kernels
@wp.struct
class Task:
    """Per-env task state: the grasper's motion target and its visual offset, the landmark (candidate index), the
    target, the workspace flag of this step, the stuck window and the particle positions at the start of the physics
    step."""

    grasper: wp.array(dtype=wp.vec3)
    visual_offset: wp.array(dtype=wp.vec3)
    landmark: wp.array(dtype=wp.int32)
    target: wp.array(dtype=wp.vec3)
    invalid: wp.array(dtype=wp.int32)
    history: wp.array2d(dtype=float)
    history_count: wp.array(dtype=wp.int32)
    q_start: wp.array2d(dtype=wp.vec3)


@wp.struct
class Params:
    low: wp.vec2  # workspace (x, z)
    high: wp.vec2
    step_length: float  # grasper travel per physics step at action 1, m
    inv_diagonal: float
    threshold: float
    squared: int
    stuck_range: float
    stability: float
    randomize_landmark: int
    fixed_landmark: int
    randomize_grasp: int
    min_target_distance: float
    start: wp.vec3
    tissue_first: int
    tissue_count: int


@wp.func
def landmark_position(q: wp.array2d(dtype=wp.vec3), env: int, k: int, tets: wp.array(dtype=wp.vec4i),
                      embed_tet: wp.array(dtype=wp.int32), embed_w: wp.array(dtype=wp.vec4)) -> wp.vec3:
    n = tets[embed_tet[k]]
    w = embed_w[k]
    return q[env, n[0]] * w[0] + q[env, n[1]] * w[1] + q[env, n[2]] * w[2] + q[env, n[3]] * w[3]


@wp.kernel
def move_grasper(actions: wp.array2d(dtype=wp.float32), p: Params, task: Task,
                 poses_out: wp.array2d(dtype=wp.transform)):
    """Per physics step: the grasper moves by ``action x step_length`` along x and z; a component that would leave
    the workspace keeps its old value and flags the step (sofa_env's ``valid_action``)."""
    env = wp.tid()
    g = task.grasper[env]
    for i in range(2):
        axis = 2 * i  # x, z
        value = g[axis] + actions[env, i] * p.step_length
        if value < p.low[i] or value > p.high[i]:
            task.invalid[env] = 1
        else:
            g[axis] = value
    task.grasper[env] = g
    poses_out[env, 0] = wp.transform(g, wp.quat_identity())


@wp.kernel
def eval_manipulation_features(env_mask: wp.array(dtype=wp.int32), advance: int, q: wp.array2d(dtype=wp.vec3),
                               tets: wp.array(dtype=wp.vec4i), embed_tet: wp.array(dtype=wp.int32),
                               embed_w: wp.array(dtype=wp.vec4), p: Params, task: Task,
                               features_out: wp.array2d(dtype=float)):
    """sofa_env's reward features; with ``advance`` the distance also enters the stuck window (once per step)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    d = horizontal_distance(landmark_position(q, env, task.landmark[env], tets, embed_tet, embed_w), task.target[env])
    stuck = float(0.0)
    if advance != 0:
        count = task.history_count[env]
        task.history[env, count % _STUCK_WINDOW] = d
        count += 1
        task.history_count[env] = count
        if count >= _STUCK_WINDOW:
            lo = float(1.0e9)
            hi = float(-1.0e9)
            for i in range(_STUCK_WINDOW):
                lo = wp.min(lo, task.history[env, i])
                hi = wp.max(hi, task.history[env, i])
            stuck = wp.where(hi - lo < p.stuck_range, 1.0, 0.0)
    moved = float(0.0)
    for k in range(p.tissue_count):
        moved = wp.max(moved, wp.length(q[env, p.tissue_first + k] - task.q_start[env, p.tissue_first + k]))
    feature = d * p.inv_diagonal
    if p.squared != 0:
        feature = d * d * p.inv_diagonal
    features_out[env, F.DISTANCE_TO_TARGET] = feature
    features_out[env, F.ONE_TIME_REWARD_GOAL] = wp.where(d <= p.threshold, 1.0, 0.0)
    features_out[env, F.ONE_TIME_PENALTY_IS_STUCK] = stuck
    features_out[env, F.ONE_TIME_PENALTY_INVALID_ACTION] = float(task.invalid[env])
    features_out[env, F.ONE_TIME_PENALTY_UNSTABLE_SIMULATION] = wp.where(moved > p.stability, 1.0, 0.0)


@wp.func
def inside_polygon(polygons: wp.array2d(dtype=wp.vec2), k: int, x: float, z: float) -> int:
    """Even-odd rule: is (x, z) inside polygon ``k``."""
    inside = int(0)
    m = polygons.shape[1]
    for i in range(m):
        a = polygons[k, i]
        b = polygons[k, (i + 1) % m]
        if (a[1] > z) != (b[1] > z):
            cross_x = a[0] + (z - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
            if x < cross_x:
                inside = 1 - inside
    return inside


@wp.kernel
def reset_manipulation(env_mask: wp.array(dtype=wp.int32), rng: wp.array(dtype=wp.uint32),
                       q: wp.array2d(dtype=wp.vec3), tets: wp.array(dtype=wp.vec4i),
                       embed_tet: wp.array(dtype=wp.int32), embed_w: wp.array(dtype=wp.vec4),
                       polygons: wp.array2d(dtype=wp.vec2), poly_low: wp.array(dtype=wp.vec2),
                       poly_high: wp.array(dtype=wp.vec2), p: Params, task: Task,
                       poses_out: wp.array2d(dtype=wp.transform)):
    """sofa_env's reset: the landmark (drawn or fixed), the visual grasp offset, then a target drawn uniformly in the
    landmark's reachable polygon at least the minimum distance from it (rejection sampling in the polygon's bounding
    box; after 1,000 rejections the last point inside the polygon is kept)."""
    env = wp.tid()
    if env_mask[env] == 0:
        return
    k = p.fixed_landmark
    if p.randomize_landmark != 0:
        k = draw_index(rng, env, embed_tet.shape[0])
    task.landmark[env] = k
    offset = wp.vec3(0.0)
    if p.randomize_grasp != 0:
        offset = wp.vec3(rand_uniform(rng, env, -0.005, 0.005), 0.0, rand_uniform(rng, env, -0.005, 0.0))
    task.visual_offset[env] = offset
    task.grasper[env] = p.start
    poses_out[env, 0] = wp.transform(p.start, wp.quat_identity())
    task.invalid[env] = 0
    task.history_count[env] = 0
    mark = landmark_position(q, env, k, tets, embed_tet, embed_w)
    lo = poly_low[k]
    hi = poly_high[k]
    target = mark
    for _attempt in range(1000):
        x = rand_uniform(rng, env, lo[0], hi[0])
        z = rand_uniform(rng, env, lo[1], hi[1])
        if inside_polygon(polygons, k, x, z) != 0:
            target = wp.vec3(x, mark[1], z)
            if horizontal_distance(target, mark) > p.min_target_distance:
                break
    task.target[env] = target


@wp.func
def unit_xz(x: wp.vec3, p: Params, obs_out: wp.array2d(dtype=float), env: int, col: int):
    """sofa_env's normalisation: 2 (p - low) / (high - low) - 1 on x and z, y set to 0."""
    obs_out[env, col] = 2.0 * (x[0] - p.low[0]) / (p.high[0] - p.low[0]) - 1.0
    obs_out[env, col + 1] = 0.0
    obs_out[env, col + 2] = 2.0 * (x[2] - p.low[1]) / (p.high[1] - p.low[1]) - 1.0


@wp.kernel
def observe_manipulation(q: wp.array2d(dtype=wp.vec3), tets: wp.array(dtype=wp.vec4i),
                         embed_tet: wp.array(dtype=wp.int32), embed_w: wp.array(dtype=wp.vec4), p: Params, task: Task,
                         o: OBS.Columns, c: CRITIC.Columns, privileged: int, obs_out: wp.array2d(dtype=float),
                         critic_out: wp.array2d(dtype=float)):
    """sofa_env's STATE: grasper (TGP), target (IDP), landmark (TTP)."""
    env = wp.tid()
    mark = landmark_position(q, env, task.landmark[env], tets, embed_tet, embed_w)
    g = task.grasper[env]
    unit_xz(g, p, obs_out, env, o.grasper)
    unit_xz(task.target[env], p, obs_out, env, o.target)
    unit_xz(mark, p, obs_out, env, o.landmark)
    if privileged == 0:
        return
    critic_out[env, c.offset_to_target] = (task.target[env][0] - mark[0]) * p.inv_diagonal
    critic_out[env, c.offset_to_target + 1] = (task.target[env][2] - mark[2]) * p.inv_diagonal
    critic_out[env, c.grasper_to_landmark] = (mark[0] - g[0]) * p.inv_diagonal
    critic_out[env, c.grasper_to_landmark + 1] = (mark[2] - g[2]) * p.inv_diagonal


@wp.kernel
def place_visuals(q: wp.array2d(dtype=wp.vec3), tets: wp.array(dtype=wp.vec4i), embed_tet: wp.array(dtype=wp.int32),
                  embed_w: wp.array(dtype=wp.vec4), task: Task, grasper_out: wp.array2d(dtype=wp.transform),
                  landmark_out: wp.array2d(dtype=wp.transform)):
    env = wp.tid()
    grasper_out[env, 0] = wp.transform(task.grasper[env] + task.visual_offset[env] + wp.vec3(0.0, -0.001, 0.0),
                                       wp.quat_identity())
    mark = landmark_position(q, env, task.landmark[env], tets, embed_tet, embed_w)
    landmark_out[env, 0] = wp.transform(mark, wp.quat_identity())


@wp.kernel
def draw_target_dot(cam: wp.array(dtype=wp.transform), task: Task, focal: float, radius: float,
                    rgb: wp.array4d(dtype=wp.uint8)):
    """sofa_env's overlay: a filled turquoise circle of ``radius`` pixels at the target's projection."""
    env, row, col = wp.tid()
    h = float(rgb.shape[2])
    w = float(rgb.shape[3])
    pix = world_to_pixel(cam[env], task.target[env], focal, 0.5 * w, 0.5 * h)
    if pix[2] <= 0.0:
        return
    dr = float(row) + 0.5 - pix[0]
    dc = float(col) + 0.5 - pix[1]
    if dr * dr + dc * dc <= (radius + 0.5) * (radius + 0.5):
        for i in range(3):
            rgb[env, i, row, col] = wp.uint8(int(OVERLAY_COLOR[i]))


# ---------------------------------------------------------------------------- env
class TissueManipulationEnv(BatchedEnv):
    """LapGym's TissueManipulationEnv, batched. See the module docstring and ``TissueManipulationConfig``.

    Actions: 2, the grasper's velocity along x and z over ``maximum_velocity``. Discrete: ``Discrete(5)``.

    Privileged critic observation (``privileged_critic=True``): the policy values, the landmark-to-target offset and
    the grasper-to-landmark offset (x, z over the workspace diagonal; 4).
    """

    config_class = TissueManipulationConfig
    task_name = "TissueManipulation"
    rewards = REWARDS
    supported_observations = ("STATE", "RGB", "RGBD", "DEPTH")
    expert = "lapwarp.tasks.deformable_manipulation.tissue_manipulation:TissueManipulationExpert"
    cfg: TissueManipulationConfig

    def _build(self) -> World:
        cfg, n, dev = self.cfg, self.num_envs, self.wp_device
        builder = SceneBuilder(gravity=(0.0, 0.0, -cfg.gravity))
        v, t = tissue_mesh()
        self.rest_vertices, self.tissue_tets = v, t
        volume = float(np.abs(np.linalg.det(np.stack([v[t[:, i]] - v[t[:, 0]] for i in (1, 2, 3)], axis=2))).sum()
                       / 6.0)
        self.tissue = builder.add_tet_mesh(v, t, density=cfg.tissue_mass / volume, youngs_modulus=cfg.youngs_modulus,
                                           poisson_ratio=cfg.poisson_ratio, damping=cfg.damping_rate,
                                           fixed=np.nonzero(v[:, 2] < FIXED_BELOW_Z)[0], name="tissue")
        start = grasp_patch_center()
        self.grasper_body = builder.add_body("grasper", pose=(*start, 0.0, 0.0, 0.0, 1.0))
        self.patch = grasp_patch(v)
        for k in self.patch:
            builder.add_attachment(self.tissue.particle_start + int(k), body=self.grasper_body, compliance=0.0)
        world = builder.finalize(num_envs=n, device=str(dev), substeps=cfg.physics_substeps, seed=cfg.seed)
        world.tet_method = cfg.tissue_solver
        # sofa_env settles max(settle_steps - 1, 1) times after every reset; the scene is the same every time, so it
        # settles once here and every episode starts from the settled state
        for _ in range(max(cfg.settle_steps - 1, 1)):
            world.step(cfg.time_step)
        world.save_start_state()

        tet_index, weights = embed_points(np.asarray(LANDMARKS), v, t)
        self._tets = wp.array(t.astype(np.int32) + self.tissue.particle_start, dtype=wp.vec4i, device=dev)
        self._embed_tet = wp.array(tet_index, dtype=wp.int32, device=dev)
        self._embed_w = wp.array(weights, dtype=wp.vec4, device=dev)
        polygons = self._reachable_polygons()
        self._polygons = wp.array(polygons, dtype=wp.vec2, device=dev)
        self._poly_low = wp.array(polygons.min(axis=1), dtype=wp.vec2, device=dev)
        self._poly_high = wp.array(polygons.max(axis=1), dtype=wp.vec2, device=dev)
        self._bodies = wp.array([self.grasper_body], dtype=wp.int32, device=dev)
        self._poses = wp.full((n, 1), wp.transform(wp.vec3(*start), wp.quat_identity()), dtype=wp.transform,
                              device=dev)

        self.task = s = Task()
        s.grasper = wp.full(n, wp.vec3(*start), dtype=wp.vec3, device=dev)
        s.visual_offset = wp.zeros(n, dtype=wp.vec3, device=dev)
        s.landmark = wp.full(n, cfg.landmark_index, dtype=wp.int32, device=dev)
        s.target = wp.zeros(n, dtype=wp.vec3, device=dev)
        s.invalid = wp.zeros(n, dtype=wp.int32, device=dev)
        s.history = wp.zeros((n, _STUCK_WINDOW), dtype=float, device=dev)
        s.history_count = wp.zeros(n, dtype=wp.int32, device=dev)
        s.q_start = wp.zeros_like(world.state.particle_q)
        low, high = np.asarray(cfg.workspace_low), np.asarray(cfg.workspace_high)
        self.params = p = Params()
        p.low, p.high = wp.vec2(*low), wp.vec2(*high)
        p.step_length = cfg.maximum_velocity * cfg.time_step
        p.inv_diagonal = 1.0 / float(np.linalg.norm(high - low))
        p.threshold, p.squared, p.stuck_range = cfg.end_position_threshold, int(cfg.squared_distance), cfg.stuck_range
        p.stability = cfg.stability_threshold
        p.randomize_landmark, p.fixed_landmark = int(cfg.randomize_landmark), cfg.landmark_index
        p.randomize_grasp, p.min_target_distance = int(cfg.randomize_grasping_point), cfg.minimum_target_distance
        p.start = wp.vec3(*start)
        p.tissue_first, p.tissue_count = self.tissue.particle_start, self.tissue.particle_count
        return world

    def _reachable_polygons(self) -> np.ndarray:
        return load_reachable_polygons(self.cfg.tissue_solver)

    def _checked_state(self) -> list[wp.array]:
        return [self.task.grasper, self.task.target]

    def _action_layout(self) -> ActionLayout:
        step = self.cfg.discrete_velocity / self.cfg.maximum_velocity
        return ActionLayout([ActionBlock("grasper", 2, (step, step))])

    def _observation_layout(self) -> ObservationLayout:
        # the grasper stays in [-1, 1]; targets and landmarks lie up to ~25 mm below the workspace (about -2.5) and
        # the flap cannot carry a landmark further than the grasper's border plus its ~3 cm hanging below it
        return OBS.layout(grasper=(3, -1.0, 1.0), target=(3, -4.0, 4.0), landmark=(3, -4.0, 4.0))

    def _critic_layout(self) -> ObservationLayout:
        return self.obs_layout.extend(CRITIC, offset_to_target=(2, -2.0, 2.0), grasper_to_landmark=(2, -2.0, 2.0))

    def _apply_actions(self, actions: wp.array2d) -> None:
        self.task.invalid.zero_()  # the workspace flag covers this env step's physics steps

    def _before_physics_step(self) -> None:
        wp.copy(self.task.q_start, self.world.state.particle_q)  # for the stability feature of this physics step
        launching.launch(move_grasper, dim=self.num_envs, inputs=[self.actions, self.params, self.task],
                         outputs=[self._poses], device=self.wp_device)
        self.world.set_body_poses(self._poses, self._bodies)

    def _compute_features(self, env_mask: wp.array, features_out: wp.array2d) -> None:
        # this task has no delta features, so the base evaluates them once per step (never at reset): the stuck
        # window advances here, once per step
        launching.launch(eval_manipulation_features, dim=self.num_envs,
                         inputs=[env_mask, int(features_out is self.features), self.world.state.particle_q, self._tets,
                                 self._embed_tet, self._embed_w, self.params, self.task], outputs=[features_out],
                         device=self.wp_device)

    def _reset_task(self, env_mask: wp.array) -> None:
        w = self.world
        launching.launch(reset_manipulation, dim=self.num_envs,
                         inputs=[env_mask, w.rng, w.state.particle_q, self._tets, self._embed_tet, self._embed_w,
                                 self._polygons, self._poly_low, self._poly_high, self.params, self.task],
                         outputs=[self._poses], device=self.wp_device)
        w.set_body_poses(self._poses, self._bodies, teleport_mask=env_mask)

    def _compute_observations(self) -> None:
        launching.launch(observe_manipulation, dim=self.num_envs,
                         inputs=[self.world.state.particle_q, self._tets, self._embed_tet, self._embed_w, self.params,
                                 self.task, self.obs_layout.columns, self.critic_layout.columns,
                                 int(self.cfg.privileged_critic)], outputs=[self.obs_frame, self.critic_frame],
                         device=self.wp_device)

    # ------------------------------------------------------------------ visuals
    def _build_visual_scene(self) -> VisualScene:
        """The flap (yellow), its landmark (a black 4 mm sphere, sofa_env's), the base flange, a liver (an ellipsoid in
        sofa_env's liver's bounding box), a background wall, the grasper (a shaft from its visual grasp point up);
        sofa_zoo's camera. The target is drawn over the image (``_draw_overlays``)."""
        n, dev, cfg = self.num_envs, self.wp_device, self.cfg
        q = self.world.state.particle_q
        obj = self.tissue
        objects = [VisualObject("tissue", "deformable", TISSUE_COLOR, 1, self.rest_vertices,
                                obj.surface_tris - obj.particle_start,
                                points=q[:, obj.particle_start:obj.particle_start + obj.particle_count])]
        self._grasper_pose = wp.zeros((n, 1), dtype=wp.transform, device=dev)
        self._landmark_pose = wp.zeros((n, 1), dtype=wp.transform, device=dev)
        mv, mf = sphere_mesh(0.004 * 0.5, subdivisions=2)
        objects.append(VisualObject("landmark", "rigid", LANDMARK_COLOR, 2, mv - np.array([0.0, 0.0005, 0.0]), mf,
                                    self._landmark_pose))
        static = wp.full((n, 1), wp.transform_identity(), dtype=wp.transform, device=dev)
        flange = trimesh.creation.box(extents=(0.05, 0.03, 0.006))
        flange.apply_translation((-0.005, -0.005, 0.048))
        liver = trimesh.creation.icosphere(subdivisions=3)
        liver.apply_scale((0.117, 0.1, 0.04))
        liver.apply_translation((0.0, -0.055, 0.05))
        wall = trimesh.creation.box(extents=(0.6, 0.002, 0.4))
        wall.apply_translation((0.0, 0.06, 0.1))
        for name, mesh, color in (("flange", flange, TISSUE_COLOR), ("liver", liver, LIVER_COLOR),
                                  ("background", wall, (0.25, 0.22, 0.2))):
            objects.append(VisualObject(name, "rigid", color, 3 + len(objects), mesh.vertices, mesh.faces, static))
        sv, sf = cylinder_mesh(0.0025, 0.1)
        objects.append(VisualObject("grasper", "rigid", GRASPER_COLOR, 3 + len(objects), sv * np.array([1, 1, -1]),
                                    sf[:, ::-1], self._grasper_pose))
        pose = look_at_transform(cfg.camera_position, cfg.camera_look_at, up=(0.0, 0.0, 1.0))
        camera = CameraSpec(poses=wp.array([pose] * n, dtype=wp.transform, device=dev), fov_deg=57.0, near=0.01,
                            far=0.5)
        return VisualScene(camera=camera, objects=objects, background=(0.05, 0.05, 0.08))

    def update_visuals(self) -> None:
        if self._visual_scene is None:
            return
        launching.launch(place_visuals, dim=self.num_envs,
                         inputs=[self.world.state.particle_q, self._tets, self._embed_tet, self._embed_w, self.task],
                         outputs=[self._grasper_pose, self._landmark_pose], device=self.wp_device)

    def _draw_overlays(self, rgb: wp.array, fov_deg: float) -> None:
        if not self.cfg.show_target:
            return
        height = rgb.shape[2]
        focal = 0.5 * height / np.tan(np.radians(0.5 * fov_deg))
        launching.launch(draw_target_dot, dim=(self.num_envs, height, rgb.shape[3]),
                         inputs=[self.visual_scene().camera.poses, self.task, float(focal), float(round(height / 64))],
                         outputs=[rgb], device=self.wp_device)

    # ------------------------------------------------------------------ privileged access (experts, tests)
    def landmark_positions(self) -> torch.Tensor:
        """Every candidate landmark's position in every env, ``(N, 9, 3)`` (a fresh tensor)."""
        q = wp.to_torch(self.world.state.particle_q)
        tets = wp.to_torch(self._tets).long()[wp.to_torch(self._embed_tet).long()]  # (9, 4)
        w = wp.to_torch(self._embed_w)
        return (q[:, tets] * w[None, :, :, None]).sum(dim=2)

    def privileged_state(self) -> dict[str, torch.Tensor]:
        """Torch views: node positions ``(N, n, 3)``, grasper ``(N, 3)``, target ``(N, 3)``, landmark index ``(N,)``,
        and the landmark's position ``(N, 3)`` (a fresh tensor)."""
        t = self.task
        marks = self.landmark_positions()
        index = wp.to_torch(t.landmark).long()
        landmark = marks[torch.arange(self.num_envs, device=marks.device), index]
        return dict(positions=wp.to_torch(self.world.state.particle_q), grasper=wp.to_torch(t.grasper),
                    target=wp.to_torch(t.target), landmark_index=wp.to_torch(t.landmark), landmark=landmark)


# ---------------------------------------------------------------------------- expert
class TissueManipulationExpert(Expert):
    """Moves the grasper along the landmark-to-target offset (x, z) with ``gain`` (the landmark follows the grasper
    at a bit less than 1:1 and lags the flap's motion, so a gain below 1 avoids overshoot)."""

    def __init__(self, env: TissueManipulationEnv, gain: float = 0.8):
        super().__init__(env)
        self.gain = float(gain)
        self.step_length = env.cfg.maximum_velocity * env.cfg.time_step * env.cfg.frame_skip

    def __call__(self, obs=None) -> torch.Tensor:
        s = self.env.privileged_state()
        offset = (s["target"] - s["landmark"])[:, [0, 2]]
        return self.policy_actions(self.gain * offset / self.step_length)


# ---------------------------------------------------------------------------- reachable polygons
class _TracingEnv(TissueManipulationEnv):
    """The env that traces the polygons: it needs none (its targets are the workspace's corners, never reached)."""

    def _reachable_polygons(self) -> np.ndarray:
        low, high = self.cfg.workspace_low, self.cfg.workspace_high
        box = np.array([low, (high[0], low[1]), high, (low[0], high[1])], dtype=np.float32)
        return np.repeat(box[None], NUM_LANDMARKS, axis=0)


def trace_reachable_polygons(device: str = "cpu", num_vertices: int = POLYGON_VERTICES,
                             **overrides) -> np.ndarray:
    """sofa_env's ``create_valid_sampling_polygons`` with this physics: one env per landmark; the grasper goes from
    its start to the workspace's (low x, low z) corner and once around the workspace's border at full speed; the
    landmark's (x, z) path around the border, resampled to ``num_vertices`` points evenly spaced along it, is that
    landmark's reachable polygon ``(9, num_vertices, 2)``."""
    env = _TracingEnv.from_overrides(num_envs=NUM_LANDMARKS, device=device, randomize_landmark=False,
                                               randomize_grasping_point=False, use_cuda_graph=False,
                                               max_episode_steps=100_000, stuck_range=0.0,
                                               end_position_threshold=1e-9, **overrides)
    wp.copy(env.task.landmark, wp.array(np.arange(NUM_LANDMARKS, dtype=np.int32), device=env.wp_device))
    env.world.save_start_state()
    cfg = env.cfg
    low, high = np.asarray(cfg.workspace_low), np.asarray(cfg.workspace_high)
    corners = [low, (high[0], low[1]), high, (low[0], high[1]), low]
    step = cfg.maximum_velocity * cfg.time_step * cfg.frame_skip
    path = []
    for i, corner in enumerate(corners):
        while True:
            g = env.privileged_state()["grasper"][0, [0, 2]].cpu().numpy()
            delta = np.asarray(corner) - g
            if np.abs(delta).max() < 1e-7:
                break
            action = np.clip(delta / step, -1.0, 1.0)
            env.step(torch.tensor(np.tile(action, (NUM_LANDMARKS, 1)), dtype=torch.float32, device=env.device))
            if i > 0:
                path.append(env.landmark_positions()[torch.arange(NUM_LANDMARKS), torch.arange(NUM_LANDMARKS)]
                            [:, [0, 2]].cpu().numpy())
    path = np.stack(path, axis=1)  # (9, steps, 2)
    polygons = []
    for trace in path:
        closed = np.concatenate([trace, trace[:1]])
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(closed, axis=0), axis=1))])
        t = np.linspace(0.0, s[-1], num_vertices, endpoint=False)
        polygons.append(np.stack([np.interp(t, s, closed[:, a]) for a in range(2)], axis=1))
    return np.asarray(polygons, dtype=np.float32)


if __name__ == "__main__":  # regenerate the stored polygons: python -m lapwarp.tasks.deformable_manipulation.tissue_...
    import argparse

    parser = argparse.ArgumentParser(description=trace_reachable_polygons.__doc__)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--tissue-solver", default="xpbd", choices=sorted(POLYGON_FILES))
    args = parser.parse_args()
    path = POLYGON_FILES[args.tissue_solver]
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, polygons=trace_reachable_polygons(args.device, tissue_solver=args.tissue_solver))
    print(f"wrote {path}")
