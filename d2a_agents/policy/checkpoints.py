"""A policy checkpoint of ``d2a train-policy``: load it, act with it, evaluate it in its env.

The checkpoint carries the EMA and raw weights (the normalizers' statistics among them), the
policy's configuration, the env settings of every training task and the world model's path
and hash, so the env a policy is evaluated in is the one it was trained with.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from collectors.dataset import Normalizer
from collectors.envs import EXPERT_FUTURE_KEY
from collectors.episode_journal import EpisodeJournal
from collectors.evaluation import EvaluationResult, evaluate
from collectors.experts import Student
from d2a_agents.checkpoint import CheckpointError, file_sha256, load_checkpoint
from d2a_agents.policy.agent import (
    Policy,
    PolicyConfig,
    TorchRLPolicy,
    normalizer_keys,
    reads_images,
)
from d2a_agents.policy.diffusion import Diffusion
from d2a_envs.defaults import DEFAULT_MAX_EPISODE_STEPS
from d2a_envs.tasks import get_task
from d2a_envs.wrappers import IMAGINED_KEY

CHECKPOINT_KIND = "policy"
CHECKPOINT_NAME = "policy.pt"


def policy_file(path: str | Path) -> Path:
    """The checkpoint a path names: the file itself, or a run directory's ``policy.pt``."""
    path = Path(path)
    return path / CHECKPOINT_NAME if path.is_dir() else path


@dataclass(frozen=True)
class Acting:
    """How a loaded policy acts; the network and its training windows stay the checkpoint's.

    Attributes:
        n_action_steps: actions of each planned chunk executed before planning again (None:
            the checkpoint's; 1 plans after every action).
        action_draws: chunks drawn from independent noise per plan, acted on as their mean (1:
            one draw, as the policy was trained and checked). On Adroit Door a DART-trained
            ``mp1-state`` policy went from 38/100 to 51/100 with 8 (docs/environments.md).
        sample_steps: network evaluations per drawn chunk (None: the expert's own, one for the
            one-step experts); a one-step expert given more integrates its flow in smaller jumps,
            which tells the sampler's share of an imitation error from the network's.
    """

    n_action_steps: int | None = None
    action_draws: int = 1
    sample_steps: int | None = None

    def __post_init__(self) -> None:
        if self.n_action_steps is not None and self.n_action_steps < 1:
            raise ValueError(f"n_action_steps must be at least 1, not {self.n_action_steps}")
        if self.action_draws < 1:
            raise ValueError(f"action_draws must be at least 1, not {self.action_draws}")
        if self.sample_steps is not None and self.sample_steps < 1:
            raise ValueError(f"sample_steps must be at least 1, not {self.sample_steps}")


def load_policy(path: str | Path, ema: bool = True, acting: Acting = Acting()) -> tuple[Policy, dict[str, Any]]:
    """The policy of a checkpoint (a file or a run directory; EMA weights by default) and its
    metadata, acting as ``acting`` says."""
    path = policy_file(path)
    payload = load_checkpoint(path, CHECKPOINT_KIND)
    try:
        config = PolicyConfig.from_dict(payload["policy_config"])
    except (KeyError, TypeError) as error:  # a field added or removed since the checkpoint was written
        raise CheckpointError(f"{path} holds a policy configuration this version cannot read ({error!r}); "
                              "train the policy again") from error
    if acting.n_action_steps is not None:
        config = dataclasses.replace(config, n_action_steps=acting.n_action_steps)
    dims = {"action": payload["action_dim"], config.encoder.state_key: payload["state_dim"], "point_cloud": 3}
    normalizers = {key: Normalizer.placeholder(dims[key]) for key in normalizer_keys(config)}
    try:  # the normalizers' statistics come with the weights
        policy = Policy(config, payload["action_dim"], payload["state_dim"], normalizers)
        policy.load_state_dict(payload["ema" if ema else "model"])
    except (ValueError, RuntimeError) as error:  # normalizers or weights of an older version
        raise CheckpointError(f"{path} was written by another version of the policy ({error}); "
                              "train the policy again") from error
    if acting.sample_steps is not None and isinstance(policy.expert, Diffusion):
        policy.expert.inference_timesteps(acting.sample_steps)  # refuses more steps than its schedule has, here
        # rather than inside every evaluation worker
    policy.action_draws, policy.sample_steps = acting.action_draws, acting.sample_steps
    return policy.eval(), payload


def load_torchrl_policy(path: str | Path, acting: Acting = Acting()) -> TorchRLPolicy:
    """A checkpoint's EMA policy as a TorchRL policy (a picklable factory for eval workers)."""
    return TorchRLPolicy(load_policy(path, acting=acting)[0])


def _trained_task(path: str | Path, payload: dict[str, Any], task: str) -> str:
    """The short name of ``task``; ValueError where the checkpoint was not trained on it."""
    name = get_task(task).name
    if name not in payload["env_kwargs"]:
        raise ValueError(f"{path} was trained on {payload['tasks']}, not on {name}")
    return name


def checkpoint_student(path: str | Path, task: str, acting: Acting = Acting(), skip_unread: bool = True) -> Student:
    """A checkpoint's EMA policy as the acting student of a DAgger collection on ``task``
    (:class:`~collectors.experts.Student`), in the env it was trained with. Its second cloud
    (imagined, or the simulator's look-ahead) is made only at the steps the policy reads it, as
    in :func:`evaluate_checkpoint` (``skip_unread=False``: at every step); the present cloud,
    which the data set stores, at every step."""
    policy, payload = load_policy(path, acting=acting)
    name = _trained_task(path, payload, task)
    path = policy_file(path).resolve()
    env_kwargs = eval_env_kwargs(payload, name)
    imagined = policy.config.read_steps().get(IMAGINED_KEY)  # None: the policy reads no second cloud
    if skip_unread and imagined is not None:
        env_kwargs["read_steps"] = {IMAGINED_KEY: imagined}
    return Student(str(path), functools.partial(load_torchrl_policy, path, acting), env_kwargs)


def trained_env_kwargs(path: str | Path, task: str) -> dict[str, Any]:
    """The env settings of the data the policy trained on for ``task``, as its data set stores
    them (``max_episode_steps`` included): a collection of the policy's own rollouts in these
    joins that data set."""
    payload = load_checkpoint(policy_file(path), CHECKPOINT_KIND)
    return dict(payload["env_kwargs"][_trained_task(path, payload, task)])


def eval_env_kwargs(payload: dict[str, Any], task: str) -> dict[str, Any]:
    """The env settings the policy was trained with (less the colour image where the policy reads
    none: drawing it would only cost time), plus its world model when it imagines, or the
    simulator's look-ahead (:data:`~collectors.envs.EXPERT_FUTURE_KEY`) for ``d2a-oracle``."""
    unread = ("max_episode_steps",) + (() if reads_images(payload["policy_config"]["algo"]) else ("rgb_image_size",))
    kwargs = {k: v for k, v in payload["env_kwargs"][task].items() if k not in unread}
    policy = PolicyConfig.from_dict(payload["policy_config"])
    if policy.variant.imagination == "oracle":
        kwargs[EXPERT_FUTURE_KEY] = {"horizon": policy.oracle_horizon, "num_points": policy.imagined_point_count}
        if policy.stacked_horizons:
            kwargs[EXPERT_FUTURE_KEY]["stacked_horizons"] = list(policy.stacked_horizons)
    world_model = payload["world_model"]
    if world_model is not None:
        if not Path(world_model).is_file():
            raise CheckpointError(f"the policy's world model {world_model} is missing")
        if file_sha256(world_model) != payload.get("world_model_sha256"):
            raise CheckpointError(f"the policy's world model {world_model} has changed since the policy was trained")
        kwargs["world_model"] = str(Path(world_model).resolve())
        kwargs["imagined_points"] = policy.imagined_point_count
        if policy.variant.imagined != "future":
            kwargs["imagined_output"] = policy.variant.imagined
    return kwargs


def evaluate_checkpoint(
    path: str | Path, task: str, episodes: int, seed: int, workers: int = 1, progress: bool = True,
    end_on_success: bool = False, ray_address: str | None = None, acting: Acting = Acting(),
    skip_unread: bool = True, journal: str | Path | None = None,
) -> EvaluationResult:
    """Evaluate a checkpoint's EMA policy on ``task`` in the env it was trained with (its
    point-cloud settings, its world model when it imagines, the episode length of its
    demonstrations), which renders and imagines only the steps whose clouds the policy reads
    (:meth:`~d2a_agents.policy.agent.PolicyConfig.read_steps`; ``skip_unread=False`` makes every
    step's, for the same outcomes more slowly); a task it was not trained on,
    or a checkpoint it cannot read, is refused before any worker starts. ``end_on_success``,
    ``ray_address``: see :func:`~collectors.evaluation.evaluate` (on Ray, the checkpoint and
    its world model must be readable on every node); ``acting``: see :class:`Acting`.
    ``journal``: a file that keeps the finished episodes, so that calling again after an
    interruption runs only the missing ones; it holds the checkpoint's digest and the settings,
    and is started over when they differ."""
    policy, payload = load_policy(path, acting=acting)
    name = _trained_task(path, payload, task)
    path = policy_file(path).resolve()  # a worker on Ray may start elsewhere
    max_steps = payload["env_kwargs"][name].get("max_episode_steps", DEFAULT_MAX_EPISODE_STEPS)
    env_kwargs = eval_env_kwargs(payload, name)
    if skip_unread:
        env_kwargs["read_steps"] = policy.config.read_steps()
    kept = None
    if journal is not None:
        kept = EpisodeJournal(journal, {"policy_sha256": file_sha256(path), "task": name, "env_kwargs": env_kwargs,
                                        "acting": dataclasses.asdict(acting), "max_steps": max_steps,
                                        "end_on_success": end_on_success})
    return evaluate(functools.partial(load_torchrl_policy, path, acting), name, episodes, seed,
                    env_kwargs=env_kwargs, workers=workers, progress=progress,
                    end_on_success=end_on_success, ray_address=ray_address, max_steps=max_steps, journal=kept)


def imaginer_tasks(world_model: str | Path) -> list[str]:
    """Tasks a world-model checkpoint was trained on."""
    from d2a_agents.world_model.imagine import CHECKPOINT_KIND as WORLD_MODEL_KIND

    return load_checkpoint(world_model, WORLD_MODEL_KIND)["tasks"]
