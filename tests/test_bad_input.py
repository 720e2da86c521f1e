"""Bad input never reaches a traceback: property-based fuzzing (hypothesis) of configs, actions and seeds for every
registered task, plus the edges one by one (devices, env counts, image memory, output paths, contact overflows).

The contract: an input is either accepted, and then a step runs and returns finite values, or rejected with a
``ValueError`` / ``TypeError`` whose message names what was wrong (the config field, ``seed``, the action shape).
"""

from __future__ import annotations

import dataclasses
import typing

import numpy as np
import pytest
import torch
import warp as wp
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lapwarp
from lapwarp.config import check_seed, rng_seed32
from lapwarp.registry import task_class

TASKS = lapwarp.list_tasks()
FUZZ = settings(max_examples=30, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])

# Values of every kind a user (or a command line) may pass; magnitudes bounded so an accepted config stays small
# enough to step on the CPU (a valid num_spheres=10**9 is not a bug, just slow).
SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(-5, 40), st.floats(-1e3, 1e3), st.sampled_from(
        [float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1e-12, 2**31, -(2**63)]),
    st.text(max_size=6), st.sampled_from(["true", "no", "1", "0.5", "1e-3", "RGB", "DISCRETE", "zero", "abc", ""]),
    st.just(np.int64(3)), st.just(np.float32(0.25)))
VALUES = st.one_of(SCALARS, st.lists(SCALARS, max_size=5), st.lists(SCALARS, max_size=5).map(tuple),
                   st.dictionaries(st.text(max_size=4), SCALARS, max_size=2))


def config_fields(task: str) -> list[str]:
    return [f.name for f in dataclasses.fields(task_class(task).config_class) if f.init]


def _literal_choices(tp) -> tuple | None:
    if typing.get_origin(tp) is typing.Literal:
        return typing.get_args(tp)
    for arg in typing.get_args(tp):
        found = _literal_choices(arg)
        if found:
            return found
    return None


def near_default(value) -> st.SearchStrategy:
    """Plausible values of a field: its default perturbed (scaled, sign-flipped, as a string, as a numpy number),
    so that many draws are accepted and the accepted space is explored, not only the rejections."""
    if isinstance(value, bool):
        return st.one_of(st.booleans(), st.sampled_from(["true", "False", "yes", "0"]))
    if isinstance(value, int):
        return st.one_of(st.integers(-2, 3 * max(value, 4)), st.integers(1, 3 * max(value, 4)).map(str),
                         st.integers(1, 9).map(np.int32))
    if isinstance(value, float):
        scaled = st.floats(-2.0, 8.0).map(lambda k: value * k if value else k * 0.01)
        return st.one_of(scaled, scaled, scaled.map(repr), scaled.map(np.float32))
    if isinstance(value, tuple):
        same_length = st.tuples(*(near_default(v) for v in value))
        return st.one_of(same_length, same_length, same_length.map(list), st.lists(near_default(value[0]),
                                                                                 max_size=len(value) + 1))
    if isinstance(value, dict):
        return st.dictionaries(st.sampled_from(list(value) or ["x"]), st.floats(-100, 100), max_size=2)
    return SCALARS


def field_values(task: str) -> dict[str, st.SearchStrategy]:
    """Per config field: mostly plausible values (choices of a Literal, perturbed defaults), sometimes junk."""
    cls = task_class(task).config_class
    hints = typing.get_type_hints(cls, include_extras=True)
    default = cls()
    out = {}
    for name in config_fields(task):
        choices = _literal_choices(hints[name])
        if name == "observation_type":
            choices = ("STATE", *[o for o in task_class(task).supported_observations if o != "STATE"], "XYZ")
        if name == "reward_weights":
            plausible = st.dictionaries(st.sampled_from(list(task_class(task).rewards.names)), st.floats(-100, 100),
                                        max_size=2)
        elif name == "image_shape":
            plausible = st.tuples(st.integers(-1, 48), st.integers(-1, 48))
        else:
            plausible = st.sampled_from(choices) if choices else near_default(getattr(default, name))
        out[name] = st.one_of(plausible, plausible, plausible, VALUES)
    out["not_a_field"] = VALUES
    return out


def step_once(env) -> None:
    """One step with valid zero (or no-op) actions; everything returned must be finite."""
    if env.is_discrete:
        actions = torch.full((env.num_envs,), 2 * env.action_dim, dtype=torch.long, device=env.device)
    else:
        actions = torch.zeros(env.num_envs, env.num_actions, device=env.device)
    obs, reward, done, extras = env.step(actions)
    for name, value in obs.items():
        assert torch.isfinite(value).all(), f"non-finite observation group {name}"
    assert torch.isfinite(reward).all() and done.dtype == torch.bool
    assert all(torch.isfinite(v) for v in extras["log"].values())


@pytest.mark.parametrize("task", TASKS)
def test_fuzzed_config_values_are_accepted_or_rejected_by_name(device, task):
    values = field_values(task)
    drawn = st.lists(st.sampled_from(sorted(values)), min_size=1, max_size=3, unique=True).flatmap(
        lambda keys: st.fixed_dictionaries({k: values[k] for k in keys}))

    @settings(FUZZ, max_examples=80)
    @given(overrides=drawn)
    def check(overrides):
        try:
            env = lapwarp.make(task, num_envs=2, device=device, **overrides)
        except (ValueError, TypeError) as exc:
            message = str(exc)
            assert any(key in message for key in overrides), f"{overrides}: {message!r} names no field"
            return
        step_once(env)

    check()


@pytest.mark.parametrize("task", TASKS)
def test_fuzzed_actions_step_or_raise(device, task):
    envs = {a: lapwarp.make(task, num_envs=3, device=device, action_type=a, seed=4) for a in ("CONTINUOUS", "DISCRETE")}
    zeroing = {a: lapwarp.make(task, num_envs=3, device=device, action_type=a, invalid_actions="zero", seed=4)
               for a in ("CONTINUOUS", "DISCRETE")}
    cont = envs["CONTINUOUS"]
    elements = st.one_of(st.floats(allow_nan=True, allow_infinity=True, width=32), st.integers(-(2**40), 2**40))
    shapes = st.sampled_from([(3, cont.num_actions), (3,), (3, 1), (2, cont.num_actions), (3, cont.num_actions + 1),
                              (1,), ()])
    dtypes = st.sampled_from([torch.float32, torch.float64, torch.int64, torch.int32, torch.bool])

    @FUZZ
    @given(action_type=st.sampled_from(["CONTINUOUS", "DISCRETE"]), shape=shapes, dtype=dtypes, data=st.data())
    def check(action_type, shape, dtype, data):
        values = data.draw(st.lists(elements, min_size=int(np.prod(shape)), max_size=int(np.prod(shape))))
        raw = torch.tensor(values, dtype=torch.float64).reshape(shape)
        if dtype == torch.bool:
            actions = raw != 0
        elif dtype.is_floating_point:
            actions = raw.to(dtype)
        else:
            actions = torch.nan_to_num(raw, nan=0.0, posinf=2**40, neginf=-(2**40)).to(dtype)
        for env in (envs[action_type], zeroing[action_type]):
            try:
                env.step(actions.to(env.device))
            except (ValueError, TypeError) as exc:
                assert any(w in str(exc) for w in ("shape", "dtype", "integer", "non-finite", "outside")), str(exc)
                continue
            step_once(env)  # an accepted action leaves the env in a state that steps on

    check()


@FUZZ
@given(seed=st.integers())
def test_any_integer_seed_gives_its_own_streams(seed):
    """Any Python integer is accepted; seeds that the old int32 conversion wrapped onto each other (s, s + 2**32,
    -1 and 2**32 - 1) get different streams, and small seeds keep their recorded streams."""
    key = rng_seed32(seed)
    assert -(2**31) <= key < 2**31
    assert rng_seed32(seed + 2**32) != key or seed + 2**32 == seed
    if 0 <= seed < 2**31:
        assert key == seed
    else:
        assert key < 0  # hashed seeds never share a small seed's streams


def test_seed_edges(device):
    env = lapwarp.make("Reach", num_envs=2, device=device)
    first = {}
    for seed in (0, 2**32, -1, 2**32 - 1, 10**30):
        env.reset(seed=seed)
        first[seed] = env.privileged_state()["target_position"].cpu().clone()
    keys = list(first)
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            assert not torch.equal(first[a], first[b]), f"seeds {a} and {b} gave the same episode"
    for bad in (1.5, True, "x", None, [1]):
        with pytest.raises(ValueError, match="seed"):
            check_seed(bad)
    with pytest.raises(ValueError, match="seed"):
        env.reset(seed=2.5)
    with pytest.raises(ValueError, match="seed"):
        lapwarp.make("Reach", num_envs=1, device=device, seed=0.5)


def test_devices_and_env_counts_mean_the_obvious(device):
    env = lapwarp.make("Reach", num_envs=np.int64(2), device=torch.device(device))
    assert env.num_envs == 2 and isinstance(env.num_envs, int) and env.device == device
    env = lapwarp.make("Reach", num_envs=1, device=wp.get_device(device))
    assert env.device == device
    for bad in (0, -3, 2.0, True, "4", None):
        with pytest.raises(ValueError, match="num_envs"):
            lapwarp.make("Reach", num_envs=bad, device=device)
    for bad in ("gpu", "cuda:99", 7):
        with pytest.raises(ValueError, match="device"):
            lapwarp.make("Reach", num_envs=1, device=bad)


def test_image_buffers_that_cannot_fit_are_refused_before_allocation(device):
    free = wp.get_device(device).free_memory if wp.get_device(device).is_cuda else None
    with pytest.raises(ValueError, match=r"GiB of image buffers"):
        # 2048 x 2048 RGB with 8 stacked frames: ~150 MB per env; 100,000 envs exceed any machine here
        lapwarp.make("Reach", num_envs=100_000, device=device, observation_type="RGB", image_shape=(2048, 2048),
                     frame_stack=8)
    if free is not None:
        assert wp.get_device(device).free_memory >= free - 2**28  # nothing big was allocated on the way


def test_contact_overflow_is_counted_and_logged(device):
    """DeflectSpheres with room for one contact record: a hook pressed onto a sphere fills it; the env counts the
    overflow under extras['log'] instead of dropping records silently."""
    from lapwarp.experts import make_expert

    env = lapwarp.make("DeflectSpheres", num_envs=2, device=device, contact_capacity=1, seed=3)
    assert "/contact/overflow_fraction" in env.log_keys
    expert = make_expert(env)
    seen = 0.0
    obs = env.get_observations()
    for _ in range(60):
        obs, _, _, extras = env.step(expert(obs))
        seen = max(seen, float(extras["log"]["/contact/overflow_fraction"]))
        if seen > 0.0:
            break
    assert seen > 0.0, "pressing a sphere with a capacity of 1 record must overflow"
    roomy = lapwarp.make("DeflectSpheres", num_envs=2, device=device, seed=3)
    obs = roomy.get_observations()
    expert = make_expert(roomy)
    for _ in range(60):
        obs, _, _, extras = roomy.step(expert(obs))
        assert float(extras["log"]["/contact/overflow_fraction"]) == 0.0
    assert "/contact/overflow_fraction" not in lapwarp.make("Reach", num_envs=1, device=device).log_keys


def test_usd_paths_are_checked_before_recording(tmp_path, device):
    from lapwarp.usd import UsdRecorder

    env = lapwarp.make("Reach", num_envs=1, device=device)
    with pytest.raises(ValueError, match="does not exist"):
        UsdRecorder(env, tmp_path / "missing" / "x.usda")
    assert not (tmp_path / "missing").exists()  # nothing created unasked
    (tmp_path / "dir.usda").mkdir()
    with pytest.raises(ValueError, match="is a folder"):
        UsdRecorder(env, tmp_path / "dir.usda")
    recorder = UsdRecorder(env, tmp_path / "made" / "x.usda", make_dirs=True)
    recorder.record()
    assert recorder.close().is_file()


def test_any_integer_seed_seeds_the_numpy_streams():
    """Tasks that draw from numpy at build (GraspLiftAndTouch's tracking points, PickAndPlace's layout) take any
    integer seed, as the Warp streams do: numpy refused a negative one with an error naming no field (found by the
    fuzz test above). Seeds in [0, 2**31) draw what ``default_rng(seed)`` drew before."""
    from lapwarp.config import numpy_rng

    assert numpy_rng(7).integers(1 << 30) == np.random.default_rng(7).integers(1 << 30)
    draws = {s: int(numpy_rng(s).integers(1 << 62)) for s in (-1, 1, -(2**63), 2**40)}
    assert len(set(draws.values())) == 4


def test_equal_state_limits_read_zero(device):
    """A PTSD component held fixed by equal state limits (allowed: low <= high) is observed as 0, not 0 / 0 = NaN
    (ThreadInHole with state_high = start = state_low in depth, found by the fuzz test above)."""
    env = lapwarp.make("ThreadInHole", num_envs=2, device=device, start_ptsd=(0.0, 0.0, 0.0, 0.0),
                       state_low=(-90.0, -90.0, -32767.0, 0.0), state_high=(90.0, 90.0, 32767.0, 0.0))
    step_once(env)
    assert np.all(env.get_observations()["policy"].cpu().numpy()[:, 3] == 0.0)


@pytest.mark.parametrize("value", [1.0e-265, 5.0e39, "-1e-300"])
def test_floats_outside_float32_are_refused_by_name(value):
    # the device computes in float32: a mass of 1e-265 kg became an infinite inverse mass there (the fuzz test's
    # GraspLiftAndTouch draws warned of an overflow in a cast and stepped on); zero stays allowed where the field is
    with pytest.raises(ValueError, match="gallbladder_mass.*float32"):
        lapwarp.make("GraspLiftAndTouch", num_envs=1, device="cpu", gallbladder_mass=value)
    with pytest.raises(ValueError, match="anchor_stiffness.*float32"):
        lapwarp.make("GraspLiftAndTouch", num_envs=1, device="cpu", anchor_stiffness=value)
    from lapwarp.config import check_fields

    cfg = task_class("Reach").config_class(sphere_radius=1.0e-30)  # inside float32's normal range: taken
    check_fields(cfg)
    assert cfg.sphere_radius == 1.0e-30
    cfg.sphere_radius = 1.0e-300
    with pytest.raises(ValueError, match="sphere_radius"):
        check_fields(cfg)
