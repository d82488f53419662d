"""The env step overlapped with the update (``overlap_env_step=True``): send the actions, update, then receive.

In SB3's order a vector step acts, steps the envs, stores the transition, and every ``train_freq`` steps updates.
With ``overlap_env_step`` the updates SB3 would run after a step run while the envs take it:

1. act on the last observations;
2. send the actions (``VecEnv.step_async``);
3. run the step's updates, as SB3 schedules them (``train_freq``, ``gradient_steps``, ``learning_starts``);
4. receive the observations (``VecEnv.step_wait``), call the callbacks, store the transition.

The updates of vector step k then sample the transitions of steps 1 to k - 1: the newest is not stored yet. That
changes the algorithm, so it is off by default. What runs while the updates run depends on the VecEnv:

=====================  ===========================================================================================
VecEnv                 what the updates overlap
=====================  ===========================================================================================
``SubprocVecEnv``      the env processes stepping
``EnvPoolVecEnv``      EnvPool's pools stepping in their threads
``DummyVecEnv``        nothing on the CPU: its ``step_async`` only stores the actions, so only the order changes;
                       on CUDA the host steps the envs while the GPU runs the queued update
=====================  ===========================================================================================

A callback's ``on_step`` sees each step after its updates. A step is whole before the next begins, so a model saved
between two ``learn`` calls resumes exactly, the setting included (it is saved with the model).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from stable_baselines3.common.buffers import ReplayBuffer
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import ActionNoise
from stable_baselines3.common.type_aliases import MaybeCallback, RolloutReturn, TrainFreq, TrainFrequencyUnit
from stable_baselines3.common.vec_env import VecEnv

if TYPE_CHECKING:
    from stable_baselines3.common.off_policy_algorithm import OffPolicyAlgorithm as MultiTaskOffPolicyAlgorithm


def check_overlapped_schedule(algorithm: MultiTaskOffPolicyAlgorithm, reset_num_timesteps: bool) -> None:
    """Refuse what the overlapped order cannot run: a ``train_freq`` in episodes (an episode's end is known only
    after its step), and a first update that would find the replay buffer empty."""
    train_freq = algorithm.train_freq
    if isinstance(train_freq, TrainFreq) and train_freq.unit != TrainFrequencyUnit.STEP:
        raise ValueError(
            "overlap_env_step=True updates while the envs step, before an episode's end is known: pass train_freq in "
            "steps, e.g. train_freq=1 or (1, 'step')."
        )
    n_envs = algorithm.n_envs
    timesteps = 0 if reset_num_timesteps else algorithm.num_timesteps
    stored = 0 if algorithm.replay_buffer is None else algorithm.replay_buffer.size()
    first_step_updates = train_freq.frequency == 1 and timesteps + n_envs > algorithm.learning_starts  # type: ignore[union-attr]
    if stored == 0 and first_step_updates and algorithm.gradient_steps != 0:
        raise ValueError(
            "overlap_env_step=True: the first update would sample an empty replay buffer (an update sees the "
            f"transitions before its step); set learning_starts >= {n_envs}, the number of sub-envs, or load the "
            "replay buffer first."
        )


def learn_overlapped(
    algorithm: MultiTaskOffPolicyAlgorithm,
    total_timesteps: int,
    callback: MaybeCallback,
    log_interval: int,
    tb_log_name: str,
    reset_num_timesteps: bool,
    progress_bar: bool,
) -> MultiTaskOffPolicyAlgorithm:
    """SB3's ``learn`` loop with the updates inside the rollouts (:func:`collect_overlapped`), none after them."""
    check_overlapped_schedule(algorithm, reset_num_timesteps)
    total_timesteps, callback = algorithm._setup_learn(
        total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar
    )
    callback.on_training_start(locals(), globals())
    while algorithm.num_timesteps < total_timesteps:
        rollout = algorithm.collect_rollouts(
            algorithm.env,  # type: ignore[arg-type]
            callback=callback,
            train_freq=algorithm.train_freq,  # type: ignore[arg-type]
            replay_buffer=algorithm.replay_buffer,  # type: ignore[arg-type]
            action_noise=algorithm.action_noise,
            learning_starts=algorithm.learning_starts,
            log_interval=log_interval,
        )
        if not rollout.continue_training:
            break
    callback.on_training_end()
    return algorithm


def collect_overlapped(
    algorithm: MultiTaskOffPolicyAlgorithm,
    env: VecEnv,
    callback: BaseCallback,
    train_freq: TrainFreq,
    replay_buffer: ReplayBuffer,
    action_noise: ActionNoise | None = None,
    learning_starts: int = 0,
    log_interval: int | None = None,
) -> RolloutReturn:
    """SB3's ``collect_rollouts`` of ``train_freq`` vector steps, the last one's updates run between sending its
    actions and receiving its observations."""
    algorithm.policy.set_training_mode(False)
    num_collected_steps, num_collected_episodes = 0, 0
    continue_training = True
    callback.on_rollout_start()
    while num_collected_steps < train_freq.frequency:
        actions, buffer_actions = algorithm._sample_action(learning_starts, action_noise, env.num_envs)
        env.step_async(actions)
        algorithm.num_timesteps += env.num_envs
        num_collected_steps += 1
        algorithm._update_current_progress_remaining(algorithm.num_timesteps, algorithm._total_timesteps)
        if num_collected_steps == train_freq.frequency:
            run_updates(algorithm, rollout_timesteps=num_collected_steps * env.num_envs)
        new_obs, rewards, dones, infos = env.step_wait()
        callback.update_locals(locals())  # SB3's names: actions, new_obs, rewards, dones, infos, ...
        if not callback.on_step():
            return RolloutReturn(num_collected_steps * env.num_envs, num_collected_episodes, continue_training=False)
        algorithm._update_info_buffer(infos, dones)
        algorithm._store_transition(replay_buffer, buffer_actions, new_obs, rewards, dones, infos)  # type: ignore[arg-type]
        algorithm._on_step()
        num_collected_episodes += end_episodes(algorithm, dones, action_noise, log_interval)
    callback.on_rollout_end()
    return RolloutReturn(num_collected_steps * env.num_envs, num_collected_episodes, continue_training)


def run_updates(algorithm: MultiTaskOffPolicyAlgorithm, rollout_timesteps: int) -> None:
    """The updates SB3's ``learn`` runs after a rollout: none before ``learning_starts``, ``gradient_steps`` of them
    (-1: as many as the rollout's env steps), then acting mode again."""
    if algorithm.num_timesteps <= max(algorithm.learning_starts, 0):
        return
    gradient_steps = algorithm.gradient_steps if algorithm.gradient_steps >= 0 else rollout_timesteps
    if gradient_steps > 0:
        algorithm.train(batch_size=algorithm.batch_size, gradient_steps=gradient_steps)
        algorithm.policy.set_training_mode(False)


def end_episodes(
    algorithm: MultiTaskOffPolicyAlgorithm,
    dones: np.ndarray,
    action_noise: ActionNoise | None,
    log_interval: int | None,
) -> int:
    """SB3's bookkeeping of the episodes that ended at this step; how many did."""
    for index in np.flatnonzero(dones):
        algorithm._episode_num += 1
        if action_noise is not None:
            action_noise.reset(**({"indices": [index]} if len(dones) > 1 else {}))
        if log_interval is not None and algorithm._episode_num % log_interval == 0:
            algorithm.dump_logs()
    return int(np.count_nonzero(dones))
