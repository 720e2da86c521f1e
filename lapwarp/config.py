"""Env configuration: the keyword-only dataclass every task config derives from, and its checks.

Fields carry their units in the config's docstring and their type (with an allowed range) in their annotation;
defaults are the paper's values (Tables B and C). ``EnvConfig.validate`` checks every field against its annotation
and coerces where the meaning is unambiguous: numbers from strings (``"0.01"``), numpy numbers, lists for tuples,
``"true"/"false"/"1"/"0"/"yes"/"no"`` for booleans (the command line passes strings). Anything else raises
``ValueError`` naming the field, the value, the expected type and the allowed range. Unknown override keys, unknown
reward feature names and invalid choices raise ``ValueError`` listing the valid ones: nothing is silently ignored.

Annotations understood: ``bool``, ``int``, ``float`` (finite), ``str``, ``Literal[...]`` (choices), ``X | None``,
``tuple[T, ...]`` / ``tuple[T1, T2]`` (lists and arrays accepted), ``dict[str, float]``, and
``Annotated[T, Range(...)]`` for a range (applied to every element of a tuple). Shorthands: :data:`Positive`,
:data:`NonNegative`, :data:`Fraction`, :data:`PositiveInt`, :func:`Count`, :data:`Vec2`, :data:`Vec3`, :data:`PTSD`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import numbers
import types
import typing
from dataclasses import dataclass, field
from typing import Annotated, Any, Literal, TypeVar

import numpy as np

OBSERVATION_TYPES = ("STATE", "RGB", "RGBD", "DEPTH")
ACTION_TYPES = ("CONTINUOUS", "DISCRETE")
INVALID_ACTION_MODES = ("raise", "zero")
#: Largest image side (pixels) an image observation may ask for.
MAX_IMAGE_SIDE = 2048

C = TypeVar("C", bound="EnvConfig")


@dataclass(frozen=True)
class Range:
    """Allowed interval of a number (of every element of a tuple): ``gt`` / ``ge`` / ``lt`` / ``le`` bounds."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None

    def contains(self, x: float) -> bool:
        return ((self.gt is None or x > self.gt) and (self.ge is None or x >= self.ge)
                and (self.lt is None or x < self.lt) and (self.le is None or x <= self.le))

    def __str__(self) -> str:
        parts = [f"{op} {v:g}" for op, v in ((">", self.gt), (">=", self.ge), ("<", self.lt), ("<=", self.le))
                 if v is not None]
        return " and ".join(parts)


Positive = Annotated[float, Range(gt=0.0)]
NonNegative = Annotated[float, Range(ge=0.0)]
Fraction = Annotated[float, Range(ge=0.0, le=1.0)]
#: A count the device holds in int32 (episode lengths, steps).
PositiveInt = Annotated[int, Range(ge=1, le=2**31 - 1)]


def Count(most: int):  # noqa: N802 (reads like the other type shorthands)
    """A positive integer of at most ``most`` (sizes that allocate: frames stacked, spheres, buffer capacities)."""
    return Annotated[int, Range(ge=1, le=most)]

Vec2 = tuple[float, float]
Vec3 = tuple[float, float, float]
#: Pan, tilt, spin in degrees and depth in metres.
PTSD = tuple[float, float, float, float]

_TRUE, _FALSE = ("true", "1", "yes", "on"), ("false", "0", "no", "off")
_FLOAT32_TINY = float(np.finfo(np.float32).tiny)
_FLOAT32_MAX = float(np.finfo(np.float32).max)


class _Invalid(ValueError):
    pass


def _type_name(tp) -> str:
    origin = typing.get_origin(tp)
    if origin is Annotated:
        base, *marks = typing.get_args(tp)
        ranges = [str(m) for m in marks if isinstance(m, Range)]
        return _type_name(base) + (f" ({', '.join(ranges)})" if ranges else "")
    if origin is Literal:
        return "one of " + repr(list(typing.get_args(tp)))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a sequence of {_type_name(args[0])}"
        return f"{len(args)} values ({', '.join(_type_name(a) for a in args)})"
    if origin is dict:
        return "a dict " + " -> ".join(_type_name(a) for a in typing.get_args(tp))
    if tp is type(None):
        return "None"
    return getattr(tp, "__name__", str(tp))


def coerce(value: Any, tp) -> Any:
    """``value`` converted to the annotation ``tp`` (see the module docstring); raises ``ValueError`` if it is not
    unambiguously one."""
    origin = typing.get_origin(tp)
    if origin is Annotated:
        base, *marks = typing.get_args(tp)
        out = coerce(value, base)
        for mark in marks:
            if isinstance(mark, Range):
                for x in (out if isinstance(out, tuple) else (out,)):
                    if x is not None and not mark.contains(x):
                        raise _Invalid(f"outside the allowed range {mark}")
        return out
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        for arg in args:
            if arg is type(None):
                continue
            try:
                return coerce(value, arg)
            except _Invalid:
                continue
        raise _Invalid("of the wrong type")
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise _Invalid("not one of the choices")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if isinstance(value, (str, bytes)) or not isinstance(value, (tuple, list, np.ndarray)):
            raise _Invalid("not a sequence")
        seq = list(np.asarray(value).tolist()) if isinstance(value, np.ndarray) else list(value)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(coerce(v, args[0]) for v in seq)
        if len(seq) != len(args):
            raise _Invalid(f"has {len(seq)} values")
        return tuple(coerce(v, a) for v, a in zip(seq, args, strict=True))
    if origin is dict:
        key_tp, val_tp = typing.get_args(tp)
        if not isinstance(value, dict):
            raise _Invalid("not a dict")
        return {coerce(k, key_tp): coerce(v, val_tp) for k, v in value.items()}
    if tp is bool:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        if isinstance(value, str) and value.strip().lower() in _TRUE + _FALSE:
            return value.strip().lower() in _TRUE
        raise _Invalid("not a boolean")
    if tp is int:
        if isinstance(value, (bool, np.bool_)):
            raise _Invalid("a boolean, not an integer")
        if isinstance(value, numbers.Integral):
            return int(value)
        if isinstance(value, str):
            try:
                return int(value.strip())
            except ValueError:
                raise _Invalid("not an integer") from None
        raise _Invalid("not an integer")
    if tp is float:
        if isinstance(value, (bool, np.bool_)):
            raise _Invalid("a boolean, not a number")
        if isinstance(value, str):
            try:
                value = float(value.strip())
            except ValueError:
                raise _Invalid("not a number") from None
        if not isinstance(value, numbers.Real):
            raise _Invalid("not a number")
        if not math.isfinite(float(value)):
            raise _Invalid("not finite")
        if value != 0.0 and not _FLOAT32_TINY <= abs(float(value)) <= _FLOAT32_MAX:
            # the device computes in float32: such a value would become 0 or inf there (a mass of 1e-265 kg gave an
            # infinite inverse mass and compliance, silently)
            raise _Invalid(f"outside float32's normal range ({_FLOAT32_TINY:.3g} .. {_FLOAT32_MAX:.3g} in magnitude), "
                           f"in which the device computes")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise _Invalid("not a string")
        return value
    return value  # an annotation this module does not check


def check_fields(cfg) -> None:
    """Check and coerce every init field of the dataclass ``cfg`` against its annotation, in place."""
    hints = typing.get_type_hints(type(cfg), include_extras=True)
    for f in dataclasses.fields(cfg):
        if not f.init or f.name not in hints:
            continue
        value = getattr(cfg, f.name)
        try:
            setattr(cfg, f.name, coerce(value, hints[f.name]))
        except _Invalid as err:
            raise ValueError(f"{type(cfg).__name__}.{f.name}={value!r} is invalid ({err}): expected "
                             f"{_type_name(hints[f.name])}") from None


def check_low_high(cfg, low_name: str, high_name: str, strict: bool = True) -> None:
    """Raise ``ValueError`` unless the tuples ``low_name`` < ``high_name`` element-wise (``<=`` when not strict)."""
    low, high = np.asarray(getattr(cfg, low_name), float), np.asarray(getattr(cfg, high_name), float)
    if np.any(low >= high) if strict else np.any(low > high):
        raise ValueError(f"{type(cfg).__name__}: {low_name}={tuple(low)} must be {'<' if strict else '<='} "
                         f"{high_name}={tuple(high)} in every component")


@dataclass(kw_only=True)
class EnvConfig:
    """Fields shared by every task.

    Attributes:
        observation_type: "STATE" (default), or "RGB", "RGBD", "DEPTH" once a task has a camera.
        action_type: "CONTINUOUS" (Box [-1, 1]^d scaled by the maximum velocities) or "DISCRETE"
            (``Discrete(2d+1)``, see ``env.discrete_actions``).
        time_step: simulated seconds per physics step (sofa_env's ``time_step``).
        frame_skip: physics steps per env step (at most 1000); the action is applied at every one of them.
        max_episode_steps: time limit in env steps (Table C); reaching it truncates the episode.
        frame_stack: number of stacked observation frames, newest last (the paper stacks 4; at most 64).
        reward_weights: weights by feature name; given names replace the task's defaults (Table A).
        invalid_actions: "raise" (default) raises ``ValueError`` on NaN/inf actions and out-of-range discrete indices,
            which costs one device-to-host sync per step; "zero" replaces non-finite components by 0 (an invalid
            discrete index by the no-op) on the device and counts them under ``extras["log"]["/action/..."]``.
        clip_actions: clip continuous actions to [-1, 1] (the action space's bounds); the fraction of
            clipped components is logged under ``/action/clipped_fraction``.
        privileged_critic: also return a ``critic`` observation group with privileged state.
        proprioception: with image observations, also return a ``proprio`` observation group: each instrument's pan,
            tilt, spin and depth, mapped from its state limits to [-1, 1] (the robot's own joint readings beside the
            camera, which the paper's image observation does not include). Tasks with an instrument rig only; the
            gymnasium adapters return the policy group only and refuse it.
        image_shape: (height, width) of image observations in pixels, each at most ``MAX_IMAGE_SIDE``.
        seed: seed of the per-env device RNG streams.
        chain_block_links: how the direct chain solve (rods' stretch, cloth edge chains) runs: 0 = one thread walks
            each chain (``kernels/chains.py``); ``B >= 2`` = chains split into blocks of ``B`` links solved side by
            side (``kernels/chains_partitioned.py``; same results up to round-off, more parallel work for few long
            chains per env on a GPU); -1 (default) = the task's measured best on CUDA devices
            (``BatchedEnv.gpu_chain_block_links``) and 0 on the CPU (one thread runs every kernel there anyway).
        chain_solver: ``"thomas"`` (the chain solve above), ``"pcr"`` (thread blocks solve packs of a family's
            chains by parallel cyclic reduction in shared memory, every Newton step in one launch per family;
            ``kernels/chains_block.py``, the same systems, round-off aside), ``"hybrid"`` (the same packs, a few rows
            per lane eliminated in registers and PCR over one row per lane, ``kernels/chains_hybrid.py``; on the CPU
            it needs ``wp.config.enable_cpu_blocks``), ``"registers"`` (the thread per chain of ``"thomas"`` with the
            whole chain in registers, its loops unrolled: families of open chains of at most 64 links,
            ``kernels/chains_registers.py``; bit-identical to "thomas" on the CPU), ``"open_walk"`` (the thread per
            chain of ``"thomas"`` in three walks per Newton step for families without a loop,
            ``chains.solve_open_chains``; the same systems, round-off aside) or ``"auto"`` (default): the task's
            measured best on CUDA devices (``BatchedEnv.gpu_chain_solver``: "pcr" for LigatingLoop and PickAndPlace,
            "hybrid" for RopeThreading, "registers" for RopeCutting and ThreadInHole, both with two threads per chain,
            ``World.chain_register_split``, "open_walk" for PrecisionCutting) and "thomas" on the CPU.
    """

    observation_type: str = "STATE"
    action_type: Literal["CONTINUOUS", "DISCRETE"] = "CONTINUOUS"
    time_step: Positive = 0.1
    frame_skip: Count(1000) = 1
    max_episode_steps: PositiveInt = 500
    frame_stack: Count(64) = 1
    reward_weights: dict[str, float] = field(default_factory=dict)
    invalid_actions: Literal["raise", "zero"] = "raise"
    clip_actions: bool = True
    privileged_critic: bool = False
    proprioception: bool = False
    image_shape: tuple[Annotated[int, Range(ge=1, le=MAX_IMAGE_SIDE)], Annotated[int, Range(ge=1, le=MAX_IMAGE_SIDE)]] \
        = (64, 64)
    seed: int = 0
    chain_block_links: Annotated[int, Range(ge=-1, le=4096)] = -1
    chain_solver: Literal["auto", "thomas", "pcr", "hybrid", "registers", "open_walk"] = "auto"

    def validate(self, reward_features: tuple[str, ...], supported_observations: tuple[str, ...]) -> None:
        """Check (and coerce) every field; raise ``ValueError`` naming the offending field. Task configs extend it
        with checks that relate fields to each other."""
        check_fields(self)
        _check_choice("observation_type", self.observation_type, supported_observations)
        if self.proprioception and self.observation_type == "STATE":  # before anything is built
            raise ValueError("proprioception=True adds the instruments' PTSD beside image observations; the STATE "
                             "observation already holds it")
        unknown = sorted(set(self.reward_weights) - set(reward_features))
        if unknown:
            raise ValueError(f"reward_weights names unknown feature(s) {unknown}; valid features: "
                             f"{list(reward_features)}")


def _check_choice(name: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{name}={value!r} is not valid; choose one of {list(choices)}")


def check_seed(seed: Any, name: str = "seed") -> int:
    """``seed`` as a Python int: any integer (numpy integers and integer strings too); a bool, a fraction or anything
    else raises ``ValueError`` naming ``name``."""
    try:
        return coerce(seed, int)
    except _Invalid as exc:
        raise ValueError(f"{name}={seed!r} is invalid ({exc}): expected an integer") from None


def numpy_rng(seed: int) -> np.random.Generator:
    """A numpy generator for any integer seed (numpy refuses negative ones): ``default_rng(seed)`` for seeds in
    ``[0, 2**31)`` as before, and the unsigned form of ``rng_seed32(seed)`` for every other integer."""
    return np.random.default_rng(rng_seed32(seed) & 0xFFFFFFFF)


def rng_seed32(seed: int) -> int:
    """The int32 seed of Warp's per-env RNG streams (``wp.rand_init(seed, env)``) for any Python integer.

    Seeds in ``[0, 2**31)`` are used as they are (recorded episodes keep their seeds); every other integer (negative,
    64-bit and beyond) is hashed (BLAKE2b of its bytes) into ``[-2**31, 0)``, so ``2**32`` no longer repeats the
    episodes of seed 0 and no large or negative seed shares the streams of a small one. Distinct hashed seeds
    collide with probability ``2**-31`` per pair (the RNG state of an env has 32 bits)."""
    seed = check_seed(seed)
    if 0 <= seed < 2**31:
        return seed
    raw = seed.to_bytes((seed.bit_length() + 8) // 8, "little", signed=True)
    digest = int.from_bytes(hashlib.blake2b(raw, digest_size=4, person=b"lapwarp-seed").digest(), "little")
    return -1 - (digest & 0x7FFFFFFF)


def check_num_envs(num_envs: Any) -> int:
    """``num_envs`` as a positive Python int (numpy integers accepted); anything else raises ``ValueError``."""
    if isinstance(num_envs, (bool, np.bool_)) or not isinstance(num_envs, numbers.Integral) or num_envs < 1:
        raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
    return int(num_envs)


def resolve_device(device: Any) -> str:
    """A Warp device name for ``device``: a name (``"cpu"``, ``"cuda"``, ``"cuda:N"``), a ``torch.device`` or a Warp
    ``Device``; an unknown or unavailable device raises ``ValueError`` listing the available ones."""
    import warp as wp

    wp.init()
    if device is None:
        return str(wp.get_device())
    if hasattr(device, "alias") and not isinstance(device, str):  # a Warp Device
        return device.alias
    if type(device).__name__ == "device" and hasattr(device, "type"):  # a torch.device
        device = device.type if device.index is None else f"{device.type}:{device.index}"
    if not isinstance(device, str):
        raise ValueError(f"device={device!r} is not a device name, torch.device or Warp device")
    try:
        return str(wp.get_device(device.strip()))
    except (ValueError, RuntimeError) as exc:
        available = [d.alias for d in wp.get_devices()]
        raise ValueError(f"device={device!r} is not available ({exc}); available devices: {available}") from None


def build_config(cfg_class: type[C], overrides: dict[str, Any]) -> C:
    """Instantiate ``cfg_class`` from keyword overrides, rejecting unknown keys with the valid ones listed."""
    valid = [f.name for f in dataclasses.fields(cfg_class) if f.init]
    unknown = sorted(set(overrides) - set(valid))
    if unknown:
        raise ValueError(f"unknown config key(s) {unknown} for {cfg_class.__name__}; valid keys: {sorted(valid)}")
    return cfg_class(**overrides)
