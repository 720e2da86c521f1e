"""Task-independent env kernels: action checks, reward sums, episode bookkeeping, frame stacking.

Every kernel runs over ``(num_envs, ...)`` and touches preallocated buffers only, so the whole env
step can be captured into one CUDA graph.
"""

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def sanitize_continuous_actions(
    actions_in: wp.array2d(dtype=wp.float32),
    clip: int,
    actions_out: wp.array2d(dtype=wp.float32),
    nonfinite_out: wp.array(dtype=wp.int32),
    clipped_out: wp.array(dtype=wp.int32),
):
    """Zero non-finite components and clip to [-1, 1], counting both per env (one thread per env)."""
    env = wp.tid()
    n_bad = int(0)
    n_clip = int(0)
    for j in range(actions_in.shape[1]):
        a = actions_in[env, j]
        if not wp.isfinite(a):
            a = 0.0
            n_bad += 1
        if clip != 0:
            if a > 1.0:
                a = 1.0
                n_clip += 1
            elif a < -1.0:
                a = -1.0
                n_clip += 1
        actions_out[env, j] = a
    nonfinite_out[env] = n_bad
    clipped_out[env] = n_clip


@wp.kernel
def lookup_discrete_actions(
    indices_in: wp.array(dtype=wp.int64),
    table: wp.array2d(dtype=wp.float32),
    actions_out: wp.array2d(dtype=wp.float32),
    invalid_out: wp.array(dtype=wp.int32),
):
    """Turn ``Discrete(2d+1)`` indices into rows of the action table; an out-of-range index is a no-op."""
    env, j = wp.tid()
    idx = indices_in[env]
    noop = table.shape[0] - 1
    bad = int(0)
    if idx < wp.int64(0) or idx > wp.int64(noop):
        bad = 1
        idx = wp.int64(noop)
    actions_out[env, j] = table[int(idx), j]
    if j == 0:
        invalid_out[env] = bad


@wp.kernel
def finish_env_step(
    delta_columns: wp.array(dtype=wp.int32),
    delta_bases: wp.array(dtype=wp.int32),
    success_column: int,
    failure_column: int,
    weights: wp.array(dtype=wp.float32),
    unstable: wp.array(dtype=wp.int32),
    max_episode_length: int,
    episode_length: wp.array(dtype=wp.int32),
    episode_return: wp.array(dtype=wp.float32),
    features: wp.array2d(dtype=wp.float32),
    baselines: wp.array2d(dtype=wp.float32),
    success_out: wp.array(dtype=wp.int32),
    failure_out: wp.array(dtype=wp.int32),
    reward_out: wp.array(dtype=wp.float32),
    terminated_out: wp.array(dtype=wp.int32),
    truncated_out: wp.array(dtype=wp.int32),
    done_out: wp.array(dtype=wp.int32),
    reset_mask_out: wp.array(dtype=wp.int32),
    last_episode_success: wp.array(dtype=wp.int32),
    finished_episodes: wp.array(dtype=wp.int32),
    last_episode_return: wp.array(dtype=wp.float32),
    last_episode_length: wp.array(dtype=wp.int32),
):
    """Delta features, done flags, weighted reward sum, termination and truncation of one env step.

    Delta feature ``delta_columns[k]`` = feature ``delta_bases[k]`` minus its baseline, which then becomes the
    feature's value. Success and failure are the declared feature columns (failure -1: none) and terminate as in
    sofa_env; an unstable env is terminated too, since its state is garbage and must not be bootstrapped (an env with a
    non-finite feature is flagged unstable here, its features logged as 0). Truncation
    is reported only when the episode did not terminate, so ``time_outs`` marks exactly the envs PPO should bootstrap.
    """
    env = wp.tid()
    for k in range(delta_columns.shape[0]):
        b = delta_bases[k]
        value = features[env, b]
        features[env, delta_columns[k]] = value - baselines[env, b]
        baselines[env, b] = value
    # a non-finite feature means the env's task state went bad (the World flags bad particles itself): flag the env
    # like an unstable one, so it ends and is reset alone, and log zeros instead of spreading NaN into the means
    bad = int(0)
    for f in range(features.shape[1]):
        if not wp.isfinite(features[env, f]):
            bad = 1
    if bad != 0:
        unstable[env] = 1
        for f in range(features.shape[1]):
            features[env, f] = 0.0
    succeeded = int(0)
    if features[env, success_column] > 0.0:
        succeeded = 1
    failed = int(0)
    if failure_column >= 0:
        if features[env, failure_column] > 0.0:
            failed = 1
    success_out[env] = succeeded
    failure_out[env] = failed
    r = float(0.0)
    for f in range(features.shape[1]):
        r += weights[f] * features[env, f]
    if unstable[env] != 0:
        r = 0.0
    length = episode_length[env] + 1
    episode_length[env] = length
    ret = episode_return[env] + r
    episode_return[env] = ret
    term = int(0)
    if succeeded != 0 or failed != 0 or unstable[env] != 0:
        term = 1
    trunc = int(0)
    if term == 0 and length >= max_episode_length:
        trunc = 1
    done = term | trunc
    reward_out[env] = r
    terminated_out[env] = term
    truncated_out[env] = trunc
    done_out[env] = done
    reset_mask_out[env] = done
    if done != 0:
        last_episode_success[env] = succeeded
        finished_episodes[env] = finished_episodes[env] + 1
        last_episode_return[env] = ret
        last_episode_length[env] = length


#: Envs summed by one thread of ``sum_log_terms`` (few atomic additions per address instead of one per env).
LOG_CHUNK = wp.constant(32)


@wp.kernel
def sum_log_terms(
    features: wp.array2d(dtype=wp.float32),
    weights: wp.array(dtype=wp.float32),
    finished_episodes: wp.array(dtype=wp.int32),
    last_episode_success: wp.array(dtype=wp.int32),
    last_episode_return: wp.array(dtype=wp.float32),
    last_episode_length: wp.array(dtype=wp.int32),
    unstable: wp.array(dtype=wp.int32),
    nonfinite: wp.array(dtype=wp.int32),
    clipped: wp.array(dtype=wp.int32),
    discrete: int,
    overflow: wp.array(dtype=wp.int32),
    overflow_term: int,
    sums: wp.array(dtype=wp.float32),
):
    """Thread (chunk, term): the sum of one term of ``extras["log"]`` over ``LOG_CHUNK`` envs, added to ``sums``
    (layout of ``BatchedEnv._log_keys``, then the number of envs with a finished episode): weighted features, raw
    features, the last finished episodes' success, return and length, instability, action counts and (at
    ``overflow_term``, -1 = none) envs whose contact records overflowed."""
    chunk, term = wp.tid()
    F = features.shape[1]
    first = chunk * LOG_CHUNK
    last = wp.min(first + LOG_CHUNK, features.shape[0])
    acc = float(0.0)
    for env in range(first, last):
        v = float(0.0)
        if term < F:
            v = features[env, term] * weights[term]
        elif term < 2 * F:
            v = features[env, term - F]
        elif term < 2 * F + 3 or term == sums.shape[0] - 1:
            if finished_episodes[env] > 0:
                if term == 2 * F:
                    v = float(last_episode_success[env])
                elif term == 2 * F + 1:
                    v = last_episode_return[env]
                elif term == 2 * F + 2:
                    v = float(last_episode_length[env])
                else:
                    v = 1.0
        elif term == 2 * F + 3:
            v = float(unstable[env] != 0)
        elif term == 2 * F + 4:
            v = float(nonfinite[env])
        elif term == overflow_term:
            v = float(overflow[env] != 0)
        elif term == 2 * F + 5 and discrete == 0:
            v = float(clipped[env])
        acc += v
    if acc != 0.0:
        wp.atomic_add(sums, term, acc)


@wp.kernel
def flag_nonfinite_rows(values: wp.array2d(dtype=wp.float32), flags: wp.array(dtype=wp.int32)):
    """``flags[env] = 1`` when row ``env`` of ``values`` (a float view of a per-env state array) holds a NaN/inf."""
    env = wp.tid()
    for k in range(values.shape[1]):
        if not wp.isfinite(values[env, k]):
            flags[env] = 1
            return


@wp.kernel
def finish_log_terms(sums: wp.array(dtype=wp.float32), num_features: int, num_envs: int, action_dim: int,
                     discrete: int, overflow_term: int, values: wp.array(dtype=wp.float32)):
    """Sums -> means: features and instability over all envs, episode statistics over the envs that finished one,
    action fractions per action component (continuous) or per env (discrete)."""
    F = num_features
    inv_envs = 1.0 / float(num_envs)
    for k in range(2 * F):
        values[k] = sums[k] * inv_envs
    finished = wp.max(sums[sums.shape[0] - 1], 1.0)
    for k in range(3):
        values[2 * F + k] = sums[2 * F + k] / finished
    values[2 * F + 3] = sums[2 * F + 3] * inv_envs
    if discrete != 0:
        values[2 * F + 4] = sums[2 * F + 4] * inv_envs
    else:
        values[2 * F + 4] = sums[2 * F + 4] * inv_envs / float(action_dim)
        values[2 * F + 5] = sums[2 * F + 5] * inv_envs / float(action_dim)
    if overflow_term >= 0:
        values[overflow_term] = sums[overflow_term] * inv_envs


@wp.kernel
def clear_episode_buffers(
    env_mask: wp.array(dtype=wp.int32),
    episode_length: wp.array(dtype=wp.int32),
    episode_return: wp.array(dtype=wp.float32),
):
    env = wp.tid()
    if env_mask[env] != 0:
        episode_length[env] = 0
        episode_return[env] = 0.0


@wp.kernel
def copy_leading_columns(src: wp.array2d(dtype=wp.float32), dst: wp.array2d(dtype=wp.float32)):
    """``dst[:, :src.shape[1]] = src`` (the policy's values at the start of the critic's frame)."""
    env, i = wp.tid()
    dst[env, i] = src[env, i]


@wp.kernel
def fill_int_array(value: int, out: wp.array(dtype=wp.int32)):
    out[wp.tid()] = value


PUSH_ALL = wp.constant(0)  # shift every env; masked (freshly reset) envs get their frame in every slot
PUSH_SHIFT_ONLY = wp.constant(1)  # shift every env, ignoring the mask (the frame before an auto-reset)
PUSH_MASKED_ONLY = wp.constant(2)  # fill only the masked envs (after pushing the final frame)


@wp.kernel
def push_observation_frame(
    frame: wp.array2d(dtype=wp.float32),
    reset_mask: wp.array(dtype=wp.int32),
    num_frames: int,
    mode: int,
    stack: wp.array2d(dtype=wp.float32),
):
    """Append the newest frame (last slot) to a ``(num_envs, num_frames * D)`` stack.

    One thread owns one feature column of one env, so shifting in place has no races. A freshly reset
    env gets its first frame repeated in every slot, as gymnasium's FrameStack does.
    """
    env, d = wp.tid()
    dim = frame.shape[1]
    value = frame[env, d]
    fill = reset_mask[env] != 0 and mode != PUSH_SHIFT_ONLY
    if mode == PUSH_MASKED_ONLY and not fill:
        return
    if fill:
        for s in range(num_frames):
            stack[env, s * dim + d] = value
    else:
        for s in range(num_frames - 1):
            stack[env, s * dim + d] = stack[env, (s + 1) * dim + d]
        stack[env, (num_frames - 1) * dim + d] = value


@wp.kernel
def gather_transform_columns(
    src: wp.array2d(dtype=wp.transform), column_offset: int, dst: wp.array2d(dtype=wp.transform)
):
    """Copy an object's per-env instance transforms into its columns of the renderer's instance array."""
    env, k = wp.tid()
    dst[env, column_offset + k] = src[env, k]


@wp.kernel
def write_image_frame(
    rgb: wp.array4d(dtype=wp.uint8),
    depth: wp.array4d(dtype=wp.float32),
    use_rgb: int,
    use_depth: int,
    inv_far: float,
    frame_out: wp.array4d(dtype=wp.float32),
):
    """Renderer outputs -> observation frame (num_envs, C, H, W) in [0, 1]: RGB / 255, then depth / far."""
    env, r, c = wp.tid()
    ch = int(0)
    if use_rgb != 0:
        for k in range(3):
            frame_out[env, k, r, c] = float(rgb[env, k, r, c]) / 255.0
        ch = 3
    if use_depth != 0:
        frame_out[env, ch, r, c] = wp.min(depth[env, 0, r, c] * inv_far, 1.0)
