"""Pivotized (TPSD) instruments, batched over envs: configuration, state arrays, actions and reset.

This module owns the host side of instruments that move about a remote centre of motion (RCM), as in
sofa_env's ``PivotizedRigidObject``: the user-facing configuration in degrees and metres
(:class:`TPSDConfig`), the preallocated per-env arrays and the launches that update them
(:class:`TPSDInstruments`), and the generic discrete-action table (:func:`discrete_action_table`).
The math lives in :mod:`lapwarp.kernels.kinematics` (radians and metres).

State ``ptsd = (pan, tilt, spin, depth)``; tip pose ``T = T(rcm_position) R_xyz(rcm_euler)
R_xyz(tilt, pan, spin) T(0, 0, depth)`` with intrinsic XYZ Euler angles; the shaft is the tip's local +Z.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import warp as wp

from lapwarp import launching
from lapwarp.kernels import kinematics

#: Bit of :attr:`TPSDInstruments.flags`: a component of the last update was outside the state limits.
STATE_LIMITS_VIOLATED = 1
#: Bit of :attr:`TPSDInstruments.flags`: the last update was rejected because the tip left the workspace.
WORKSPACE_VIOLATED = 2

_DEG = math.pi / 180.0
# Angles are converted deg -> rad, depth stays in metres.
_PTSD_TO_INTERNAL = np.array([_DEG, _DEG, _DEG, 1.0])


def discrete_action_table(magnitudes: Sequence[float], dtype: type = np.float32) -> np.ndarray:
    """Lookup table of a ``Discrete(2d + 1)`` action space over ``d`` continuous dimensions.

    Row ``2i`` is ``+magnitudes[i] * e_i``, row ``2i + 1`` is ``-magnitudes[i] * e_i`` and the last row
    (index ``2d``) is the no-op, matching sofa_env's discrete actions. Units are those of ``magnitudes``.

    Args:
        magnitudes: one non-negative, finite magnitude per dimension (length ``d >= 1``).
        dtype: NumPy dtype of the result.

    Returns:
        Array of shape ``(2d + 1, d)``.

    Raises:
        ValueError: if ``magnitudes`` is empty, not 1-D, negative or not finite.
    """
    m = np.asarray(magnitudes, dtype=np.float64)
    if m.ndim != 1 or m.size == 0:
        raise ValueError(f"magnitudes must be a non-empty 1-D sequence, got shape {m.shape}")
    if not np.all(np.isfinite(m)) or np.any(m < 0.0):
        raise ValueError(f"magnitudes must be finite and >= 0, got {m.tolist()}")
    d = m.size
    table = np.zeros((2 * d + 1, d), dtype=np.float64)
    for i in range(d):
        table[2 * i, i] = m[i]
        table[2 * i + 1, i] = -m[i]
    return table.astype(dtype)


def _as_vector(name: str, value: Sequence[float], size: int, *, allow_inf: bool = False) -> tuple[float, ...]:
    array = np.asarray(value, dtype=np.float64)
    if array.shape != (size,):
        raise ValueError(f"{name} must have {size} components, got shape {array.shape} ({value!r})")
    if np.any(np.isnan(array)) or (not allow_inf and not np.all(np.isfinite(array))):
        raise ValueError(f"{name} must be {'non-NaN' if allow_inf else 'finite'}, got {array.tolist()}")
    return tuple(float(x) for x in array)


@dataclass(kw_only=True)
class TPSDConfig:
    """One pivotized instrument, in degrees and metres (defaults: sofa_env's ``PivotizedRigidObject``).

    Every field is a 3- or 4-vector; ``__post_init__`` converts them to tuples of floats and raises
    ``ValueError`` on wrong shapes, NaNs, inverted limits, negative noise or velocities, or a start state
    outside the state limits.

    Attributes:
        rcm_position: RCM position (m).
        rcm_euler_deg: RCM orientation as intrinsic XYZ Euler angles (deg).
        start_ptsd: initial (pan, tilt, spin) in deg and depth in m.
        state_low: lower state limits (deg, deg, deg, m).
        state_high: upper state limits (deg, deg, deg, m).
        workspace_low: lower corner of the Cartesian box the tip must stay in (m; -inf allowed).
        workspace_high: upper corner of that box (m; +inf allowed).
        max_velocity: speed of a continuous action of 1 (deg/s, deg/s, deg/s, m/s).
        discrete_magnitude: speed of a discrete action (deg/s, deg/s, deg/s, m/s).
        ptsd_noise: reset noise, uniform in +-noise around ``start_ptsd`` (deg, deg, deg, m).
        rcm_position_noise: reset noise of the RCM position, uniform in +-noise (m).
        rcm_euler_noise_deg: reset noise of the RCM Euler angles, uniform in +-noise (deg).
        source: the task config field each field above was set from (``{"start_ptsd": "right_start_ptsd"}``), so a
            rejection names what the user wrote; fields not listed keep their own names.
    """

    rcm_position: Sequence[float] = (0.0, 0.0, 0.0)
    rcm_euler_deg: Sequence[float] = (0.0, 0.0, 0.0)
    start_ptsd: Sequence[float] = (0.0, 0.0, 0.0, 0.0)
    state_low: Sequence[float] = (-90.0, -90.0, -90.0, 0.0)
    state_high: Sequence[float] = (90.0, 90.0, 90.0, 0.2)
    workspace_low: Sequence[float] = (-math.inf, -math.inf, -math.inf)
    workspace_high: Sequence[float] = (math.inf, math.inf, math.inf)
    max_velocity: Sequence[float] = (20.0, 20.0, 20.0, 0.02)
    discrete_magnitude: Sequence[float] = (20.0, 20.0, 20.0, 0.02)
    ptsd_noise: Sequence[float] = (0.0, 0.0, 0.0, 0.0)
    rcm_position_noise: Sequence[float] = (0.0, 0.0, 0.0)
    rcm_euler_noise_deg: Sequence[float] = (0.0, 0.0, 0.0)
    source: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        name = self.source.get
        for key, size, allow_inf in (("rcm_position", 3, False), ("rcm_euler_deg", 3, False), ("start_ptsd", 4, False),
                                     ("state_low", 4, True), ("state_high", 4, True), ("workspace_low", 3, True),
                                     ("workspace_high", 3, True), ("max_velocity", 4, False),
                                     ("discrete_magnitude", 4, False), ("ptsd_noise", 4, False),
                                     ("rcm_position_noise", 3, False), ("rcm_euler_noise_deg", 3, False)):
            setattr(self, key, _as_vector(name(key, key), getattr(self, key), size, allow_inf=allow_inf))

        for low_name, high_name in (("state_low", "state_high"), ("workspace_low", "workspace_high")):
            low, high = np.array(getattr(self, low_name)), np.array(getattr(self, high_name))
            if np.any(low > high):
                raise ValueError(f"{name(low_name, low_name)} must be <= {name(high_name, high_name)}, got "
                                 f"{low.tolist()} > {high.tolist()}")
        for key in ("max_velocity", "discrete_magnitude", "ptsd_noise", "rcm_position_noise", "rcm_euler_noise_deg"):
            if np.any(np.array(getattr(self, key)) < 0.0):
                raise ValueError(f"{name(key, key)} must be >= 0, got {list(getattr(self, key))}")
        start = np.array(self.start_ptsd)
        if np.any(start < np.array(self.state_low)) or np.any(start > np.array(self.state_high)):
            raise ValueError(
                f"{name('start_ptsd', 'start_ptsd')} {list(self.start_ptsd)} is outside the state limits "
                f"{name('state_low', 'state_low')}..{name('state_high', 'state_high')} = "
                f"[{list(self.state_low)}, {list(self.state_high)}]"
            )


def tpsd_from_config(cfg, **fields) -> TPSDConfig:
    """A ``TPSDConfig`` whose fields come from a task config: a string value names the task config field to read
    (and is what errors then name), any other value is used as it is (derived geometry)."""
    values = {k: getattr(cfg, v) if isinstance(v, str) else v for k, v in fields.items()}
    return TPSDConfig(**values, source={k: v for k, v in fields.items() if isinstance(v, str)})


class TPSDInstruments:
    """A batch of pivotized instruments: ``num_instruments`` per env, ``num_envs`` envs.

    All arrays are allocated once in the constructor and are env-major, shape
    ``(num_envs, num_instruments)``; inside they hold radians and metres.

    Attributes:
        ptsd: ``wp.vec4`` state (pan, tilt, spin rad; depth m).
        pose: ``wp.transform`` tip pose in the env frame (local +Z = shaft).
        flags: ``int32`` bits of the last update (:data:`STATE_LIMITS_VIOLATED`, :data:`WORKSPACE_VIOLATED`).
        rcm: ``wp.transform`` RCM frame of each env's instrument (re-drawn at reset when noise is set).
        delta: ``wp.vec4`` per-sub-step increment (rad, m) that :meth:`step` applies.

    The ``apply_*``, ``set_*_actions``, ``step`` and ``reset`` methods only launch kernels on these
    arrays (no allocation, no host synchronisation, no Python loop over envs), so they can be captured
    in a CUDA graph.

    Args:
        configs: one :class:`TPSDConfig` per instrument.
        num_envs: number of envs.
        device: Warp device (default: Warp's current default device).
        action_columns: first column of each instrument's four PTSD entries in a continuous action row;
            default ``4 * k`` (actions ``(num_envs, 4 * num_instruments)``). Use it when the action row
            interleaves other entries, e.g. ``[0, 5]`` for two PTSDA instruments.
        max_reset_tries: rejection-sampling draws per instrument at reset before falling back to the start state.
    """

    def __init__(
        self,
        configs: Sequence[TPSDConfig],
        num_envs: int,
        device: str | None = None,
        action_columns: Sequence[int] | None = None,
        max_reset_tries: int = 100,
    ):
        configs = list(configs)
        if not configs:
            raise ValueError("configs must hold at least one TPSDConfig")
        if not all(isinstance(c, TPSDConfig) for c in configs):
            raise ValueError("configs must be TPSDConfig instances")
        if int(num_envs) < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        if int(max_reset_tries) < 1:
            raise ValueError(f"max_reset_tries must be >= 1, got {max_reset_tries}")
        self.configs = configs
        self.num_envs = int(num_envs)
        self.num_instruments = len(configs)
        self.device = wp.get_device(device)
        self.max_reset_tries = int(max_reset_tries)

        n, num = self.num_envs, self.num_instruments
        if action_columns is None:
            action_columns = [4 * k for k in range(num)]
        columns = np.asarray(action_columns, dtype=np.int64)
        if columns.shape != (num,) or np.any(columns < 0):
            raise ValueError(f"action_columns must hold {num} non-negative ints, got {list(action_columns)}")
        #: Minimum number of columns of a continuous action array.
        self.action_dim = int(columns.max()) + 4

        def shared(values: list, dtype: type) -> wp.array:
            return wp.array(np.asarray(values, dtype=np.float32), dtype=dtype, device=self.device)

        scale = _PTSD_TO_INTERNAL
        self.rcm_position = shared([c.rcm_position for c in configs], wp.vec3)
        self.rcm_euler = shared([np.radians(c.rcm_euler_deg) for c in configs], wp.vec3)
        self.rcm_position_noise = shared([c.rcm_position_noise for c in configs], wp.vec3)
        self.rcm_euler_noise = shared([np.radians(c.rcm_euler_noise_deg) for c in configs], wp.vec3)
        self.start_ptsd = shared([np.array(c.start_ptsd) * scale for c in configs], wp.vec4)
        self.ptsd_noise = shared([np.array(c.ptsd_noise) * scale for c in configs], wp.vec4)
        self.state_low = shared([np.array(c.state_low) * scale for c in configs], wp.vec4)
        self.state_high = shared([np.array(c.state_high) * scale for c in configs], wp.vec4)
        self.workspace_low = shared([c.workspace_low for c in configs], wp.vec3)
        self.workspace_high = shared([c.workspace_high for c in configs], wp.vec3)
        self.max_velocity = shared([np.array(c.max_velocity) * scale for c in configs], wp.vec4)
        self.discrete_table = wp.array(
            np.stack([discrete_action_table(np.array(c.discrete_magnitude) * scale) for c in configs]),
            dtype=wp.vec4,
            device=self.device,
        )
        self.action_columns = wp.array(columns.astype(np.int32), dtype=wp.int32, device=self.device)

        self.ptsd = wp.zeros((n, num), dtype=wp.vec4, device=self.device)
        self.pose = wp.zeros((n, num), dtype=wp.transform, device=self.device)
        self.flags = wp.zeros((n, num), dtype=wp.int32, device=self.device)
        self.rcm = wp.zeros((n, num), dtype=wp.transform, device=self.device)
        self.delta = wp.zeros((n, num), dtype=wp.vec4, device=self.device)
        # Used by reset(env_mask=None) and as a never-read placeholder when no RNG is given.
        self._all_envs = wp.full(n, 1, dtype=wp.int32, device=self.device)
        self._no_rng = wp.zeros(n, dtype=wp.uint32, device=self.device)

        self.reset()

    # -- actions --------------------------------------------------------------------------------

    def set_actions(self, actions: wp.array, dt: float) -> None:
        """Fill :attr:`delta` from continuous actions: ``delta = clip(a, -1, 1) * max_velocity * dt``.

        Args:
            actions: ``wp.array2d(dtype=float32)`` of shape ``(num_envs, >= action_dim)``, in [-1, 1];
                values outside are clipped, NaN counts as 0.
            dt: sub-step length (s).
        """
        self._check_rows(actions, "actions")
        if actions.ndim != 2 or actions.shape[1] < self.action_dim:
            raise ValueError(f"actions must have shape ({self.num_envs}, >= {self.action_dim}), got {actions.shape}")
        launching.launch(
            kinematics.compute_continuous_deltas,
            dim=(self.num_envs, self.num_instruments),
            inputs=[actions, self.action_columns, self.max_velocity, float(self._check_dt(dt))],
            outputs=[self.delta],
            device=self.device,
        )

    def set_discrete_actions(self, indices: wp.array, dt: float) -> None:
        """Fill :attr:`delta` from discrete actions: ``delta = discrete_action_table(magnitude)[index] * dt``.

        Index ``2i`` moves component ``i`` (pan, tilt, spin, depth) up, ``2i + 1`` down, ``8`` is the
        no-op; an index outside ``[0, 8]`` also acts as the no-op.

        Args:
            indices: ``int32`` array of shape ``(num_envs, num_instruments)`` (or ``(num_envs,)`` for one instrument).
            dt: sub-step length (s).
        """
        self._check_rows(indices, "indices")
        if indices.ndim == 1 and self.num_instruments == 1:
            indices = indices.reshape((self.num_envs, 1))
        if indices.shape != (self.num_envs, self.num_instruments):
            raise ValueError(f"indices must have shape ({self.num_envs}, {self.num_instruments}), got {indices.shape}")
        launching.launch(
            kinematics.compute_discrete_deltas,
            dim=(self.num_envs, self.num_instruments),
            inputs=[indices, self.discrete_table, float(self._check_dt(dt))],
            outputs=[self.delta],
            device=self.device,
        )

    def step(self) -> None:
        """Advance every instrument by :attr:`delta` (one sub-step) with sofa_env's limit semantics.

        Components outside the state limits keep their old value; a tip outside the workspace rejects the
        whole update. :attr:`flags` is overwritten. Call it once per sub-step: like sofa_env, a frame-skip
        of ``n`` applies the same delta ``n`` times.
        """
        launching.launch(
            kinematics.step_tpsd_instruments,
            dim=(self.num_envs, self.num_instruments),
            inputs=[self.rcm, self.state_low, self.state_high, self.workspace_low, self.workspace_high,
                    self.delta],
            outputs=[self.ptsd, self.pose, self.flags],
            device=self.device,
        )

    def apply_actions(self, actions: wp.array, dt: float) -> None:
        """:meth:`set_actions` then :meth:`step`: one sub-step of continuous actions in [-1, 1]."""
        self.set_actions(actions, dt)
        self.step()

    def apply_discrete(self, indices: wp.array, dt: float) -> None:
        """:meth:`set_discrete_actions` then :meth:`step`: one sub-step of discrete actions."""
        self.set_discrete_actions(indices, dt)
        self.step()

    # -- reset ----------------------------------------------------------------------------------

    def reset(self, env_mask: wp.array | None = None, rng: wp.array | None = None) -> None:
        """Reset the instruments of the masked envs in place; other envs are not touched.

        With ``rng`` the RCM and the state get the configured uniform noise (state redrawn until inside the
        state limits and the workspace, at most ``max_reset_tries`` times, then the start state) and each
        masked env's RNG state advances; without it every masked env gets exactly the configured start
        state and RCM. Flags are cleared.

        Args:
            env_mask: ``int32`` array ``(num_envs,)``, non-zero = reset; ``None`` resets all envs.
            rng: per-env RNG states ``uint32`` ``(num_envs,)`` (e.g. ``World.rng``), or ``None`` for no noise.
        """
        mask = self._all_envs if env_mask is None else env_mask
        self._check_rows(mask, "env_mask")
        if rng is not None:
            self._check_rows(rng, "rng")
        launching.launch(
            kinematics.reset_tpsd_instruments,
            dim=self.num_envs,
            inputs=[
                mask,
                self.rcm_position,
                self.rcm_euler,
                self.rcm_position_noise,
                self.rcm_euler_noise,
                self.start_ptsd,
                self.ptsd_noise,
                self.state_low,
                self.state_high,
                self.workspace_low,
                self.workspace_high,
                0 if rng is None else 1,
                self.max_reset_tries,
                self._no_rng if rng is None else rng,
            ],
            outputs=[self.rcm, self.ptsd, self.pose, self.flags],
            device=self.device,
        )

    # -- host utilities (synchronise; not for the captured step) ----------------------------------

    def set_ptsd(self, ptsd: np.ndarray, env_ids: Sequence[int] | np.ndarray | None = None) -> None:
        """Write states directly, without limit checks, and recompute the poses (tests, scripted experts).

        Args:
            ptsd: (pan, tilt, spin) in deg and depth in m; shape ``(4,)``, ``(num_instruments, 4)`` or
                ``(len(env_ids), num_instruments, 4)`` (broadcast over the selected envs).
            env_ids: envs to write; ``None`` = all.
        """
        values = np.asarray(ptsd, dtype=np.float64)
        if values.ndim == 0 or values.shape[-1] != 4:
            raise ValueError(f"ptsd must end in 4 components (pan, tilt, spin, depth), got shape {values.shape}")
        values = values * _PTSD_TO_INTERNAL
        current = self.ptsd.numpy()
        ids = np.arange(self.num_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64)
        try:
            current[ids] = np.broadcast_to(values, (len(ids), self.num_instruments, 4))
        except ValueError as err:
            raise ValueError(f"cannot write ptsd of shape {values.shape} to {len(ids)} envs: {err}") from err
        self.ptsd.assign(current.astype(np.float32))
        launching.launch(
            kinematics.compute_tip_poses,
            dim=(self.num_envs, self.num_instruments),
            inputs=[self.rcm, self.ptsd],
            outputs=[self.pose, self.flags],
            device=self.device,
        )

    def ptsd_numpy(self) -> np.ndarray:
        """States as ``(num_envs, num_instruments, 4)`` float64: (pan, tilt, spin) in deg, depth in m."""
        return self.ptsd.numpy().astype(np.float64) / _PTSD_TO_INTERNAL

    def tip_positions_numpy(self) -> np.ndarray:
        """Tip positions as ``(num_envs, num_instruments, 3)`` in m."""
        return self.pose.numpy()[..., :3].copy()

    def flags_numpy(self) -> np.ndarray:
        """Flags of the last update as ``(num_envs, num_instruments)`` int32."""
        return self.flags.numpy()

    # -- checks ---------------------------------------------------------------------------------

    def _check_rows(self, array: wp.array, name: str) -> None:
        if array.shape[0] != self.num_envs:
            raise ValueError(f"{name} must have {self.num_envs} rows (one per env), got shape {array.shape}")

    @staticmethod
    def _check_dt(dt: float) -> float:
        if not dt > 0.0 or not math.isfinite(dt):
            raise ValueError(f"dt must be finite and > 0, got {dt}")
        return dt


def start_tip(config: TPSDConfig) -> wp.transform:
    """The tip pose of one instrument at its noise-free start state (host, at build: tasks that lay an object into
    the jaws, e.g. a grasped thread or rope)."""
    ins = TPSDInstruments([config], 1, device="cpu")
    ins.reset(None, None)
    return wp.transform(*ins.pose.numpy()[0, 0])
