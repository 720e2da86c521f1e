"""Task declarations: reward features, observation blocks and action blocks.

A task states *what* it computes in one place and the env base (``lapwarp.env.BatchedEnv``) derives the rest:

* :class:`RewardSpec` -- the reward features in order, each with its default weight (Table A) and, for a delta
  feature, the feature it is the change of. Its :attr:`RewardSpec.F` holds one Warp constant per feature, so a
  kernel writes ``features[env, F.DISTANCE_TO_TARGET]``, never a bare column number. The success (and optional
  failure) term is a named feature; the base reads the done flags from those columns.
* :class:`ObservationSpec` -- the names of the STATE observation blocks in order, and a ``wp.struct`` type
  :attr:`ObservationSpec.Columns` of their first columns; :meth:`ObservationSpec.layout` takes the sizes (and bounds)
  a config gives them and returns an :class:`ObservationLayout` whose ``size`` is the STATE size and whose
  ``columns`` instance a kernel reads as ``obs[env, o.active_sphere + i]``. Sizes may depend on the config (number
  of spheres, one or two hooks), which is why columns of observations are kernel arguments and those of features
  (fixed per task) are constants.
* :class:`ActionLayout` -- named blocks of the continuous action vector and the speed of a discrete step of each
  component in continuous units, from which the ``Discrete(2d + 1)`` table follows: discrete action ``k`` *is* the
  continuous action ``table[k]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import warp as wp

from lapwarp.instruments import discrete_action_table


def _constant_name(name: str) -> str:
    return name.upper().replace("/", "_").replace("-", "_")


# ---------------------------------------------------------------------------------------------------- rewards
@dataclass(frozen=True)
class Feature:
    """One reward feature: its name, default weight and, for a delta feature, the feature it is the change of."""

    name: str
    weight: float = 0.0
    delta_of: str | None = None


class RewardSpec:
    """The reward features of a task, in column order.

    A delta feature ``d`` with ``delta_of = b`` is filled by the env base after the task's feature kernel: ``d =
    features[b] - baseline[b]``, then ``baseline[b] = features[b]``. Baselines start at each env's reset from the
    features of the reset state, and a task may restart one mid-episode (sofa_env does after drawing a new target)
    by writing ``env.baselines[env, F.B]`` in a kernel that runs after the features (``_update_task``).

    Args:
        *features: the features in column order.
        success: the feature whose value > 0 marks success (terminates the episode).
        failure: an optional feature whose value > 0 marks failure (terminates the episode too).
    """

    def __init__(self, *features: Feature, success: str = "successful_task", failure: str | None = None):
        self.features = tuple(features)
        self.names = tuple(f.name for f in self.features)
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"duplicate feature names in {self.names}")
        self.index = {name: i for i, name in enumerate(self.names)}
        for term in (success, failure):
            if term is not None and term not in self.index:
                raise ValueError(f"success/failure term {term!r} is not a feature of {self.names}")
        self.success = self.index[success]
        self.failure = -1 if failure is None else self.index[failure]
        self.deltas: list[tuple[int, int]] = []  # (delta column, base column)
        for i, f in enumerate(self.features):
            if f.delta_of is not None:
                if f.delta_of not in self.index:
                    raise ValueError(f"{f.name!r} is a delta of unknown feature {f.delta_of!r}")
                self.deltas.append((i, self.index[f.delta_of]))
        #: One Warp constant per feature: ``F.<NAME>`` is its column.
        self.F = type("F", (), {_constant_name(n): wp.constant(i) for i, n in enumerate(self.names)})

    @property
    def size(self) -> int:
        return len(self.names)

    def default_weights(self) -> dict[str, float]:
        return {f.name: float(f.weight) for f in self.features}


# ---------------------------------------------------------------------------------------------------- observations
def tracking_nodes(num_nodes: int, count: int) -> np.ndarray:
    """``count`` node indices evenly spread from the first to the last of ``num_nodes`` (sofa_env's
    ``linspace(0, N - 1, T)`` tracking points of a thread or rope), int32; empty for ``count`` 0."""
    return np.linspace(0, num_nodes - 1, count).astype(np.int32) if count > 0 else np.zeros(0, np.int32)


@wp.func
def to_unit(x: float, low: float, high: float) -> float:
    """``x`` in [low, high] mapped to [-1, 1] (how observations normalise positions and instrument states); a range
    of zero width (a component held fixed by equal limits, which configs allow) reads 0, not 0 / 0."""
    if high <= low:
        return 0.0
    return 2.0 * (x - low) / (high - low) - 1.0


@wp.func
def write_transform(obs: wp.array2d(dtype=wp.float32), env: int, start: int, xf: wp.transform):
    """Position then quaternion (xyzw), sign chosen so that w >= 0 (q and -q are the same rotation)."""
    t = wp.transform_get_translation(xf)
    q = wp.transform_get_rotation(xf)
    if q[3] < 0.0:
        q = wp.quat(-q[0], -q[1], -q[2], -q[3])
    for k in range(3):
        obs[env, start + k] = t[k]
    for k in range(4):
        obs[env, start + 3 + k] = q[k]


@dataclass(frozen=True)
class ObservationLayout:
    """The STATE observation of one env instance: block sizes, offsets and bounds.

    Attributes:
        names, sizes: blocks in order (a block of size 0 is absent in this configuration).
        size: total number of values (the STATE size).
        columns: ``ObservationSpec.Columns`` instance with each block's first column (kernel argument).
        low, high: ``(size,)`` float32 bounds of every value (gymnasium spaces, contract tests).
    """

    names: tuple[str, ...]
    sizes: tuple[int, ...]
    columns: object
    low: np.ndarray
    high: np.ndarray

    @property
    def size(self) -> int:
        return int(sum(self.sizes))

    def extend(self, spec: ObservationSpec, **blocks) -> ObservationLayout:
        """The layout of ``spec`` (an :meth:`ObservationSpec.extend` of this layout's spec) with this layout's blocks
        first, then ``blocks``: a privileged critic that sees the policy's values and more. The env base copies the
        policy's values into the leading columns, so the task's kernel writes only the added blocks."""
        own = {n: (size, self.low[self.slice(n)], self.high[self.slice(n)]) for n, size in zip(self.names, self.sizes,
                                                                                                strict=True)}
        return spec.layout(**own, **blocks)

    def slice(self, name: str) -> slice:
        """Columns of block ``name``."""
        k = self.names.index(name)
        start = int(sum(self.sizes[:k]))
        return slice(start, start + self.sizes[k])


class ObservationSpec:
    """Names of a task's observation blocks in order; :attr:`Columns` is the ``wp.struct`` of their offsets.

    Args:
        *names: block names (valid Python identifiers), in the order the values appear.
    """

    def __init__(self, *names: str):
        for n in names:
            if not n.isidentifier():
                raise ValueError(f"block name {n!r} is not an identifier")
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate block names in {names}")
        self.names = tuple(names)
        cls = type("Columns", (), {"__annotations__": {n: int for n in names}, "__module__": __name__,
                                    "__qualname__": "Columns_" + "_".join(names)})
        #: ``wp.struct`` with one int field per block (its first column).
        self.Columns = wp.struct(cls)

    def extend(self, *names: str) -> ObservationSpec:
        """A spec with these blocks after this spec's (see :meth:`ObservationLayout.extend`)."""
        return ObservationSpec(*self.names, *names)

    def layout(self, **blocks) -> ObservationLayout:
        """The layout for one configuration: ``name=size`` or ``name=(size, low, high)`` for every block (bounds
        default to unbounded; ``low``/``high`` may be scalars or per-value sequences)."""
        missing = [n for n in self.names if n not in blocks]
        unknown = sorted(set(blocks) - set(self.names))
        if missing or unknown:
            raise ValueError(f"observation blocks: missing {missing}, unknown {unknown} (declared {self.names})")
        cols = self.Columns()
        sizes, lows, highs = [], [], []
        offset = 0
        for n in self.names:
            spec = blocks[n]
            size, low, high = (spec, -np.inf, np.inf) if np.isscalar(spec) else spec
            size = int(size)
            if size == 0:
                low, high = np.zeros(0), np.zeros(0)
            if size < 0:
                raise ValueError(f"block {n!r} has negative size {size}")
            setattr(cols, n, offset)
            sizes.append(size)
            lows.append(np.broadcast_to(np.asarray(low, np.float32), (size,)))
            highs.append(np.broadcast_to(np.asarray(high, np.float32), (size,)))
            offset += size
        low_all = np.concatenate(lows) if lows else np.zeros(0, np.float32)
        high_all = np.concatenate(highs) if highs else np.zeros(0, np.float32)
        return ObservationLayout(self.names, tuple(sizes), cols, low_all.astype(np.float32),
                                 high_all.astype(np.float32))


# ---------------------------------------------------------------------------------------------------- actions
@dataclass(frozen=True)
class ActionBlock:
    """Part of the continuous action: ``size`` components in [-1, 1]; ``discrete_step`` is the magnitude of one
    discrete action along each component, in the same normalised units (discrete speed / maximum speed)."""

    name: str
    size: int
    discrete_step: tuple[float, ...]

    def __post_init__(self) -> None:
        if self.size < 1 or len(self.discrete_step) != self.size:
            raise ValueError(f"action block {self.name!r}: {self.size} components need as many discrete steps")


class ActionLayout:
    """The continuous action vector as named blocks, and the discrete table that follows from it."""

    def __init__(self, blocks: Sequence[ActionBlock]):
        self.blocks = tuple(blocks)
        self.columns: dict[str, int] = {}
        offset = 0
        for b in self.blocks:
            self.columns[b.name] = offset
            offset += b.size
        self.size = offset

    def discrete_table(self) -> np.ndarray:
        """``(2d + 1, d)`` float32: rows ``2i``/``2i+1`` move component ``i`` by ``+-discrete_step``, the last row
        is the no-op (sofa_env's discrete scheme), in continuous action units."""
        return discrete_action_table([s for b in self.blocks for s in b.discrete_step])
