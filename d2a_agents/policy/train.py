"""Train a policy on stored demonstrations (``d2a train-policy``).

AdamW with a warm-up + cosine learning-rate schedule, an exponential moving average of the
weights (the EMA weights are what gets evaluated and deployed), periodic evaluation in
the environment, atomic checkpoints that carry the normalizers, the configs and the world
model's path, and resumption from the last checkpoint after a kill. At every evaluation
and at the end, the perception check (:mod:`d2a_agents.policy.perception`) measures how much
the policy relies on its clouds and on its low-dimensional observation, on held-out
episodes when some are held out (``holdout_episodes``), else on training windows.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict
from torchrl.record.loggers import get_logger
from tqdm import tqdm

from collectors.atomic import exclusive_writer
from collectors.dataset import DemoWindows, Normalizer, WindowConfig, episode_bounds, future_rows
from collectors.storage import DemoDataset
from d2a_agents.checkpoint import CheckpointError, file_sha256, load_for_resume, save_checkpoint
from d2a_agents.policy.agent import (
    CPU_POLICY_PRESET,
    IMAGINED_KEY,
    Policy,
    PolicyConfig,
    normalizer_keys,
    subsample_cloud,
    uses_imagination,
)
from d2a_agents.policy.checkpoints import (
    CHECKPOINT_KIND,
    CHECKPOINT_NAME,
    Acting,
    evaluate_checkpoint,
    imaginer_tasks,
    load_policy,
    policy_file,
)
from d2a_agents.policy.perception import Reliance, reliance
from d2a_agents.world_model.data import WorldModelTransitions
from d2a_agents.world_model.imagine import Imaginer
from d2a_envs.gl import software_render_threads
from d2a_envs.tasks import get_task
from d2a_envs.wrappers import IMAGE_KEY

# TrainPolicyConfig fields a resumed run may change (how long, how often, where it runs);
# every other field must match the checkpoint's, or the resume would mix two runs.
RESUMABLE_CHANGES = ("out", "steps", "eval_every", "eval_episodes", "eval_workers", "eval_end_on_success",
                     "eval_action_draws", "checkpoint_every", "device", "threads", "logger", "progress")
# Per-step training figures kept in the checkpoint (``metrics``): the unweighted MSE and, with
# adaptive CFG, the batch means of the gate w and of rho (eq. 7) and the fraction of the batch
# whose target the gate changes (w < 1), to see what the gate does.
LOGGED_METRICS = ("mse", "cfg_weight", "cfg_rho", "cfg_active")
# First env seed of the periodic evaluations (the final evaluations of the benches start at 100000).
EVALUATION_SEED = 10_000
EVAL_LAYOUTS = ("fixed", "fresh")
# A periodic evaluation's finished episodes, one file per task in the run directory: a run
# killed part-way through one plays only its missing episodes when it resumes.
PERIODIC_JOURNAL = "periodic_evaluation_{task}.jsonl"


@dataclass(frozen=True)
class PolicyPreset:
    """An architecture and the training budget that goes with it."""

    policy: PolicyConfig
    steps: int
    batch_size: int
    learning_rate: float
    trim_after_success: int = -1  # frames kept after each demonstration's first success (-1: all)
    augment_shift: float | None = 0.0  # translation of the training windows (m); None: see augment_shift_for
    image_batch_size: int | None = None  # the batch of a policy that reads images (None: batch_size)
    image_learning_rate: float | None = None  # the learning rate of a policy that reads images (None: learning_rate)

    def training_fields(self, policy: PolicyConfig | None = None) -> dict[str, Any]:
        """The ``TrainPolicyConfig`` fields the preset sets, for ``policy`` (default: the preset's
        own): the batch and the learning rate are the ``image_`` ones where that policy reads images."""
        policy = policy or self.policy
        image_fields = {"image_batch_size": "batch_size", "image_learning_rate": "learning_rate"}
        fields = {field.name: getattr(self, field.name) for field in dataclasses.fields(self)
                  if field.name not in image_fields}
        for image_field, field in image_fields.items():
            if policy.encoder.use_image and getattr(self, image_field) is not None:
                fields[field] = getattr(self, image_field)
        return {**fields, "policy": policy}


# The translation the ``cpu`` preset applies where it is action-safe (docs/perception.md).
DEFAULT_AUGMENT_SHIFT = 0.02

POLICY_PRESETS: dict[str, PolicyPreset] = {
    # A 2-core CPU: 64 points, the narrow preset networks, 4000 steps of batch 256 (1.0 M
    # samples, about half of MP1's released budget) at 10x DP3's learning rate: 7 minutes on
    # one thread for mp1, 11 for d2a (its second cloud encoder; `d2a bench train`). The
    # ablations behind it are in docs/perception.md.
    # Training stops 10 frames after each demonstration's first success: the expert holds still
    # after it (1/3 to 2/3 of the frames), and those frames taught the policy to stop short.
    # On Meta-World each training window is moved in the table plane by up to 2 cm along x and y.
    # An image policy (dp) trains on batches of 64 at 1e-4, Diffusion Policy's own batch and
    # learning rate for its image tasks: its ResNet-18 (a quarter of the widths) on 84-pixel
    # images costs about 10x mp1's point encoder per window (`d2a bench train`: 189 against 1813
    # samples/s, one thread), and at 1e-3 the ResNet's features stopped depending on the image
    # (docs/policies.md).
    "cpu": PolicyPreset(CPU_POLICY_PRESET, steps=4000, batch_size=256, learning_rate=1e-3, trim_after_success=10,
                        augment_shift=None, image_batch_size=64, image_learning_rate=1e-4),
    # Section IV of the paper: 1024 points (Meta-World), batch 128, 3000 epochs of 2000
    # demonstration steps (~47k steps), DP3's learning rate.
    "paper": PolicyPreset(PolicyConfig(num_points=1024), steps=47_000, batch_size=128, learning_rate=1e-4),
}


@dataclass(frozen=True)
class TrainPolicyConfig:
    """Every knob of ``d2a train-policy`` (architecture in ``policy``; defaults: the ``cpu`` preset)."""

    data: str
    out: str
    policy: PolicyConfig = POLICY_PRESETS["cpu"].policy
    world_model: str | None = None
    teacher: str | None = None  # --algo cp: the EDM teacher's policy.pt (d2a train-policy --algo edm)
    steps: int = POLICY_PRESETS["cpu"].steps
    batch_size: int = POLICY_PRESETS["cpu"].batch_size
    learning_rate: float = POLICY_PRESETS["cpu"].learning_rate
    weight_decay: float = 1e-6
    warmup_steps: int = 100
    ema_decay: float = 0.995
    demos: int | None = None  # train on the first demos episodes of each task (None: all); nested sets of one pool
    holdout_episodes: int = 0  # the last k episodes of each task: never trained on, used by the perception check
    # Keep only this many frames after an episode's first success (-1: keep all). Scripted
    # experts succeed at steps 59-71 of 200 on Hammer and then hold still: 2/3 of the frames.
    trim_after_success: int = POLICY_PRESETS["cpu"].trim_after_success
    # Each training window's clouds and end-effector position moved by one random translation in
    # the table plane, uniform in [-augment_shift, augment_shift] metres along x and y (0: off;
    # None: 2 cm where that is action-safe, else off; see augment_shift_for).
    augment_shift: float | None = POLICY_PRESETS["cpu"].augment_shift
    reliance_windows: int = 512  # windows of the perception check
    eval_every: int = 0  # 0: only at the end
    eval_episodes: int = 20  # 0: no evaluation at all
    eval_workers: int = 1
    eval_end_on_success: bool = True  # evaluations count successes only: end episodes there (same verdicts, faster)
    eval_action_draws: int = 1  # the evaluations act on the mean of this many chunks per plan (Acting.action_draws)
    # "fixed": every periodic evaluation plays the same layouts (env seeds 10000 on), so two
    # evaluations differ only by their checkpoints; "fresh": each one plays the next
    # eval_episodes layouts, as DP3's and MP1's runners do (their env draws a new layout at every
    # reset), which makes the best-5 paper protocol also select over layout draws.
    eval_layouts: str = "fixed"
    checkpoint_every: int = 200
    seed: int = 0
    device: str = "cpu"  # "cuda" trains on a GPU (evaluation and the checkpoint's policy stay on the CPU)
    threads: int = 0  # torch threads for training; 0: leave torch's setting
    # TorchRL logger that also receives the scalars (training metrics, success per task, the
    # perception check) under out/logs: "csv", "tensorboard", "wandb", "mlflow"; "" for none.
    logger: str = "csv"
    progress: bool = True

    @classmethod
    def from_preset(cls, preset: PolicyPreset, **fields: Any) -> TrainPolicyConfig:
        """The preset's networks and budget (steps, batch, learning rate, trimming, window shift);
        ``fields`` set the rest (a ``policy`` there gets the preset's batch for its kind)."""
        return cls(**{**preset.training_fields(fields.get("policy")), **fields})

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "checkpoint_every", "reliance_windows", "eval_action_draws"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, not {getattr(self, name)}")
        if self.demos is not None and self.demos < 1:
            raise ValueError(f"demos must be at least 1, not {self.demos}")
        if self.trim_after_success < -1:
            raise ValueError(f"trim_after_success must be -1 (keep all) or >= 0, not {self.trim_after_success}")
        for name in ("holdout_episodes", "eval_every", "eval_episodes", "threads"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must not be negative, not {getattr(self, name)}")
        if self.eval_workers < 1:
            raise ValueError(f"eval_workers must be at least 1, not {self.eval_workers}")
        if self.eval_layouts not in EVAL_LAYOUTS:
            raise ValueError(f"eval_layouts must be one of {EVAL_LAYOUTS}, not {self.eval_layouts!r}")
        if not self.learning_rate > 0:
            raise ValueError(f"learning_rate must be positive, not {self.learning_rate}")
        if (self.teacher is not None) != (self.policy.variant.expert == "consistency-trajectory"):
            raise ValueError("--teacher (an EDM policy.pt) goes with --algo cp, and --algo cp needs one")
        if self.augment_shift is not None and not 0 <= self.augment_shift < math.inf:
            raise ValueError(f"augment_shift must be a distance >= 0 in metres, not {self.augment_shift}")


@dataclass
class EvaluationPoint:
    """Success of one task's evaluation at one training step (a multi-task run has one per task)."""

    step: int
    success_rate: float
    episodes: int
    task: str = ""


def evaluation_seed(layouts: str, index: int, episodes: int) -> int:
    """First env seed of a task's ``index``-th periodic evaluation (0-based) of ``episodes``
    episodes: the same for every index with ``"fixed"`` layouts, consecutive blocks with ``"fresh"``."""
    return EVALUATION_SEED + (index * episodes if layouts == "fresh" else 0)


def _cosine_with_warmup(warmup: int, total: int):
    def factor(step: int) -> float:
        if step < warmup:
            return (step + 1) / warmup
        progress = (step - warmup) / max(1, total - warmup)
        return 0.5 * (1 + math.cos(math.pi * min(1.0, progress)))

    return factor


def training_frames(
    dataset: DemoDataset, config: PolicyConfig, imaginer: Imaginer | None, progress: bool
) -> TensorDict:
    """In-memory frames for the windows: the observations the policy reads (clouds
    subsampled to ``config.num_points`` by FPS, images as stored) and, for imagination variants, the world
    model's imagined cloud of every step (``d2a-oracle``'s true future cloud, one per horizon, ``d2a-present``'s own
    copy of the present), at ``config.imagined_point_count``."""
    frames = dataset.frames()
    state_key = config.encoder.state_key
    data = {state_key: torch.as_tensor(frames[state_key]).float(), "action": torch.as_tensor(frames["action"]).float(),
            "episode": torch.as_tensor(frames["episode"]), "success": torch.as_tensor(frames["success"]).bool()}
    if config.encoder.use_cloud:
        data["point_cloud"] = torch.stack(
            [subsample_cloud(c, config.num_points) for c in torch.as_tensor(frames["point_cloud"])])
    if config.encoder.use_image:
        if IMAGE_KEY not in frames.keys():
            raise ValueError(f"{config.algo} reads camera images and {dataset.directory} holds none: collect its "
                             "demonstrations with --rgb-image-size")
        data[IMAGE_KEY] = torch.as_tensor(frames[IMAGE_KEY])  # uint8: the encoder scales each batch
    if imaginer is not None:
        wm = imaginer.config
        table = WorldModelTransitions(frames, imaginer.grid, wm.horizon, wm.action_history)
        imagined = []
        for row in tqdm(range(len(table)), desc="imagining", disable=not progress):
            cloud = imaginer(frames["point_cloud"][table.rows[row]], table.past_actions(torch.tensor(row)))
            imagined.append(subsample_cloud(torch.as_tensor(cloud), config.imagined_point_count))
        data[IMAGINED_KEY] = torch.stack(imagined)
    elif IMAGINED_KEY in config.observation_keys:  # d2a-oracle, or d2a-present with a point count of its own
        count = config.imagined_point_count
        clouds = data["point_cloud"] if count == config.num_points else torch.stack(
            [subsample_cloud(c, count) for c in torch.as_tensor(frames["point_cloud"])])
        if config.variant.imagination != "oracle":
            data[IMAGINED_KEY] = clouds
        else:  # the demonstration's own clouds oracle_horizons steps ahead: (T, N, 3), or (T, K, N, 3) stacked
            futures = [clouds[future_rows(frames, horizon)] for horizon in config.oracle_horizons]
            data[IMAGINED_KEY] = futures[0] if len(futures) == 1 else torch.stack(futures, 1)
    return TensorDict(data, batch_size=[len(data["action"])])


def frames_up_to_success(frames: TensorDict, keep_after: int) -> torch.Tensor:
    """Row mask: every frame up to ``keep_after`` steps past its episode's first success
    (episodes that never succeed are kept whole)."""
    _, starts, lengths = episode_bounds(frames)
    success = torch.as_tensor(frames["success"]).reshape(-1).bool()
    keep = torch.ones(success.numel(), dtype=torch.bool)
    for start, length in zip(starts.tolist(), lengths.tolist(), strict=True):
        hits = torch.nonzero(success[start:start + length]).reshape(-1)
        if hits.numel():
            keep[start + int(hits[0]) + keep_after + 1:start + length] = False
    return keep


def split_episodes(dataset: DemoDataset, holdout: int) -> tuple[list[int], list[int]]:
    """(training, held-out) episode ids: the last ``holdout`` episodes of each task are held out."""
    train, held = [], []
    for task in sorted(dataset.metadata.tasks):
        ids = [episode.index for episode in dataset.metadata.episodes if episode.task == task]
        if not ids:
            raise ValueError(f"{dataset.directory} holds no demonstration of {task} to train a policy on (only "
                             "rollouts: kept failures or noisy runs, which world models train on)")
        if holdout >= len(ids):
            raise ValueError(f"cannot hold out {holdout} of {len(ids)} {task} episodes")
        train += ids[: len(ids) - holdout]
        held += ids[len(ids) - holdout :]
    return train, held


def fit_policy_normalizers(frames: TensorDict, config: PolicyConfig) -> dict[str, Normalizer]:
    """Min/max normalizers on the training frames: per dimension for actions and the
    low-dimensional observation, per axis over every point for the clouds (the identity
    when ``config.normalize_clouds`` is off)."""
    data = {key: frames[key] for key in normalizer_keys(config)}
    normalizers = {}
    if "point_cloud" in data:
        clouds = data.pop("point_cloud")[..., :3].reshape(-1, 3)
        normalizers["point_cloud"] = (Normalizer.fit(clouds) if config.normalize_clouds
                                      else Normalizer(-torch.ones(3), torch.ones(3)))
    return {**normalizers, **{key: Normalizer.fit(value) for key, value in data.items()}}


def shift_windows(
    observation: dict[str, torch.Tensor], max_shift: float, generator: torch.Generator | None = None
) -> dict[str, torch.Tensor]:
    """The windows moved in the table plane: one translation per window, uniform in
    [-max_shift, max_shift] metres along x and y, added to every point of its clouds (current
    and imagined, (B, T, N, >=3)) and to the end-effector position, the first three entries of
    ``agent_pos`` (B, T, >=3); heights and everything else (the gripper opening) are left as
    they are. Meta-World draws its objects' start positions across the table at fixed heights;
    a height shift would show tables at heights that never occur (docs/perception.md measures both)."""
    position = observation["agent_pos"]
    offset = (torch.rand(position.shape[0], 3, generator=generator, device=position.device) * 2 - 1) * max_shift
    offset[:, 2] = 0  # drawn in 3D, then flattened: a seed moves x and y as the 3D shift measured beside it did
    shifted = dict(observation)
    for key in ("point_cloud", IMAGINED_KEY, "agent_pos"):
        if key in shifted:
            moved = shifted[key].clone()
            moved[..., :3] += offset.view(-1, *[1] * (moved.dim() - 2), 3)
            shifted[key] = moved
    return shifted


def augment_shift_for(config: TrainPolicyConfig, tasks: list[str]) -> float:
    """The translation (m) a run applies to its training windows.

    Moving a window's clouds and end effector together calls for the same actions only where
    actions are end-effector position deltas (Meta-World) and the policy reads clouds and
    ``agent_pos`` (the state reference's object positions, or the image policy's pixels, would
    have to move too).
    ``augment_shift=None`` gives ``DEFAULT_AUGMENT_SHIFT`` there and 0 elsewhere; an explicit
    distance where it is not action-safe is refused.
    """
    others = [task for task in tasks if get_task(task).suite != "metaworld"]
    encoder = config.policy.encoder
    reads_state = encoder.state_key != "agent_pos"
    if config.augment_shift is None:
        return 0.0 if others or reads_state or not encoder.use_cloud else DEFAULT_AUGMENT_SHIFT
    if config.augment_shift > 0 and (reads_state or not encoder.use_cloud):
        seen = "the simulator state" if reads_state else "no cloud"
        raise ValueError(f"augment_shift moves clouds and agent_pos; {config.policy.algo} reads {seen}")
    if config.augment_shift > 0 and others:
        raise ValueError(f"augment_shift needs position-delta actions (Meta-World); {others} act in joint space")
    return config.augment_shift


def training_step(
    policy: Policy, optimizer: torch.optim.Optimizer, windows: DemoWindows, batch_size: int,
    generator: torch.Generator, augment_shift: float = 0.0,
) -> dict[str, float]:
    """One optimizer step on ``batch_size`` windows drawn from ``windows`` (moved by
    :func:`shift_windows` when ``augment_shift`` > 0); returns the loss figures."""
    batch = windows.sample(batch_size, generator)
    observation = {key: batch["obs", key] for key in policy.config.observation_keys}
    if augment_shift > 0:
        observation = shift_windows(observation, augment_shift, generator)
    loss, info = policy.compute_loss(observation, batch["action"], generator)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return info


def _reliance_batch(windows: DemoWindows, config: TrainPolicyConfig) -> TensorDict:
    """The fixed windows of the perception check (a seeded draw without replacement)."""
    generator = torch.Generator().manual_seed(1234)
    chosen = torch.randperm(len(windows), generator=generator)[: config.reliance_windows]
    return windows.get(chosen)


def adopt_teacher(student: Policy, path: str) -> torch.nn.Module:
    """Make ``student`` (``--algo cp``) read observations as the EDM teacher at ``path`` does: its
    normalizers and its observation encoder, frozen; return the teacher's network (frozen)."""
    teacher, _ = load_policy(path)
    if teacher.config.algo != "edm":
        raise CheckpointError(f"{path} is a {teacher.config.algo} policy; a consistency student distils an edm one")
    shapes = ("horizon", "n_obs_steps", "num_points", "encoder")
    # As checkpoints store them: a cloud policy's checkpoint drops the image encoder's settings.
    teacher_settings, student_settings = teacher.config.to_dict(), student.config.to_dict()
    mismatched = [name for name in shapes if teacher_settings[name] != student_settings[name]]
    if mismatched or (teacher.action_dim, teacher.state_dim) != (student.action_dim, student.state_dim):
        raise CheckpointError(f"the teacher {path} was trained with another {', '.join(mismatched) or 'data shape'}: "
                              "train the student with the teacher's settings")
    student.normalizers.load_state_dict(teacher.normalizers.state_dict())
    student.encoder.load_state_dict(teacher.encoder.state_dict())
    student.encoder.requires_grad_(False)
    return teacher.net.requires_grad_(False).eval()


def train_policy(config: TrainPolicyConfig) -> tuple[Policy, list[EvaluationPoint]]:
    """Train (or resume) a policy; returns the EMA policy and its evaluation history.

    The run directory is locked for the whole run: a second trainer into it is refused.
    """
    with exclusive_writer(config.out):
        return _train_policy(config)


def _train_policy(config: TrainPolicyConfig) -> tuple[Policy, list[EvaluationPoint]]:
    call_started = time.perf_counter()  # the checkpoint's wall_seconds: this call's time plus the earlier calls'
    if config.threads:
        torch.set_num_threads(config.threads)
        software_render_threads(config.threads)  # its evaluations render: before the first GL context
    device = torch.device(config.device)
    dataset = DemoDataset.open_for_training(config.data).demonstrations()  # never the rollouts of a world model
    if dataset.holds_exactly(config.demos):
        config = dataclasses.replace(config, demos=None)  # every episode: recorded as a run on the whole set
    else:
        dataset = dataset.first_episodes(config.demos)
    train_ids, held_ids = split_episodes(dataset, config.holdout_episodes)  # refuses a set without demonstrations
    if uses_imagination(config.policy.algo) and config.world_model is None:
        raise ValueError(f"algo {config.policy.algo!r} imagines the future: pass --world-model")
    # The imagined cloud at the policy's point count, as the env serves it when acting (eval_env_kwargs).
    imaginer = (Imaginer.from_checkpoint(config.world_model, num_points=config.policy.imagined_point_count,
                                         output=config.policy.variant.imagined)
                if uses_imagination(config.policy.algo) else None)
    if imaginer is not None and not set(dataset.metadata.tasks) <= set(imaginer_tasks(config.world_model)):
        raise CheckpointError(f"world model {config.world_model} was not trained on every task of {config.data}")
    augment_shift = augment_shift_for(config, sorted(dataset.metadata.tasks))
    frames = training_frames(dataset, config.policy, imaginer, config.progress)
    if config.trim_after_success >= 0:
        frames = frames[frames_up_to_success(frames, config.trim_after_success)]
    tasks = sorted(dataset.metadata.tasks)
    normalizers = fit_policy_normalizers(frames[torch.isin(frames["episode"], torch.tensor(train_ids))], config.policy)
    obs_keys = config.policy.observation_keys
    window_config = WindowConfig(config.policy.horizon, config.policy.n_obs_steps, config.policy.n_action_steps,
                                 obs_keys)
    frames = frames.to(device)
    windows = DemoWindows(frames, window_config, episodes=train_ids)
    check_windows = DemoWindows(frames, window_config, episodes=held_ids) if held_ids else windows
    check_where = "held-out" if held_ids else "training"
    check_batch = _reliance_batch(check_windows, config)
    torch.manual_seed(config.seed)
    state_dim = frames[config.policy.encoder.state_key].shape[-1]
    policy = Policy(config.policy, frames["action"].shape[-1], state_dim, normalizers).to(device)
    teacher = adopt_teacher(policy, config.teacher) if config.teacher else None
    ema = copy.deepcopy(policy).requires_grad_(False)
    if teacher is not None:
        policy.expert.teacher = teacher.to(device)  # after the EMA copy: only training needs it
    optimizer = torch.optim.AdamW(policy.parameters(), lr=config.learning_rate, weight_decay=config.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, _cosine_with_warmup(config.warmup_steps, config.steps))
    generator = torch.Generator(device=device).manual_seed(config.seed)
    out = Path(config.out)
    path = out / CHECKPOINT_NAME
    # Absolute, so the policy evaluates from any directory; hashed, so a swapped file is caught.
    world_model_path = str(Path(config.world_model).resolve()) if config.world_model else None
    world_model_hash = file_sha256(world_model_path) if world_model_path else None
    static = {
        "policy_config": config.policy.to_dict(), "action_dim": policy.action_dim, "state_dim": policy.state_dim,
        "world_model": world_model_path,
        "world_model_sha256": world_model_hash, "tasks": tasks,
        "teacher": str(policy_file(config.teacher).resolve()) if config.teacher else None,
        "teacher_sha256": file_sha256(policy_file(config.teacher)) if config.teacher else None,
        "env_kwargs": dataset.metadata.tasks,
        "data": str(config.data), "held_out_episodes": held_ids, "augment_shift": augment_shift,
        "train_config": {k: v for k, v in dataclasses.asdict(config).items() if k != "policy"},
        "run_config": {k: v for k, v in dataclasses.asdict(config).items()
                       if k not in RESUMABLE_CHANGES and k != "policy"},
    }
    start, history, metrics, reliances, earlier_seconds = 0, [], [], [], 0.0
    previous = load_for_resume(path, CHECKPOINT_KIND, static, ("policy_config", "world_model", "tasks", "run_config"),
                               upgrades={"policy_config": lambda raw: PolicyConfig.from_dict(raw).to_dict()})
    if previous is not None:
        policy.load_state_dict(previous["model"])
        ema.load_state_dict(previous["ema"])
        optimizer.load_state_dict(previous["optimizer"])
        scheduler.load_state_dict(previous["scheduler"])
        generator.set_state(previous["generator"])
        start, history = previous["step"], [EvaluationPoint(**point) for point in previous["history"]]
        metrics, reliances = previous.get("metrics", []), previous.get("reliance", [])
        earlier_seconds = previous.get("wall_seconds", 0.0)  # 0 in a checkpoint written before it was kept

    def checkpoint(step: int) -> None:
        save_checkpoint(path, CHECKPOINT_KIND, {
            **static, "model": policy.state_dict(), "ema": ema.state_dict(), "optimizer": optimizer.state_dict(),
            "scheduler": scheduler.state_dict(), "generator": generator.get_state(), "step": step,
            "history": [dataclasses.asdict(point) for point in history], "metrics": metrics, "reliance": reliances,
            "wall_seconds": earlier_seconds + time.perf_counter() - call_started,
        })

    logger = get_logger(config.logger, logger_name=str(out / "logs"), experiment_name=config.policy.algo) \
        if config.logger else None

    def log(values: dict[str, float | None], step: int) -> None:
        for name, value in values.items():
            if logger is not None and value is not None:
                logger.log_scalar(name, float(value), step=step)

    def check_perception(step: int) -> None:
        result = reliance(ema, {key: check_batch["obs", key] for key in obs_keys}, check_batch["action"])
        reliances.append({"step": step, "where": check_where, **dataclasses.asdict(result)})
        log({"reliance/clouds": result.cloud_ratio, "reliance/imagined": result.imagined_ratio,
             "reliance/state": result.state_ratio}, step)

    evaluation_seconds = 0.0

    def evaluation_due(step: int) -> bool:
        return config.eval_episodes > 0 and ((config.eval_every and step % config.eval_every == 0)
                                             or step == config.steps)

    def evaluate_now(step: int, tasks: list[str]) -> None:
        nonlocal evaluation_seconds
        started_evaluation = time.perf_counter()
        for task in tasks:
            seed = evaluation_seed(config.eval_layouts, sum(point.task == task for point in history),
                                   config.eval_episodes)
            result = evaluate_checkpoint(path, task, config.eval_episodes, seed=seed, workers=config.eval_workers,
                                         progress=False, end_on_success=config.eval_end_on_success,
                                         acting=Acting(action_draws=config.eval_action_draws),
                                         journal=out / PERIODIC_JOURNAL.format(task=task))
            history.append(EvaluationPoint(step, result.success_rate, result.episodes, task))
            log({f"success/{task}": result.success_rate}, step)
            bar.write(f"step {step}: {task} success {result.success_rate:.0%} over {result.episodes} episodes")
        evaluation_seconds += time.perf_counter() - started_evaluation

    bar = tqdm(range(start, config.steps), initial=start, total=config.steps, desc=f"{config.policy.algo} policy",
               disable=not config.progress)
    started = time.perf_counter()
    # A run killed during an evaluation resumes from the checkpoint saved just before it: run
    # the evaluations that step still lacks, or the history would silently miss them.
    evaluated = {(point.step, point.task) for point in history}
    unevaluated = [task for task in tasks if (start, task) not in evaluated]
    if start and evaluation_due(start) and unevaluated:
        evaluate_now(start, unevaluated)
        checkpoint(start)
    for step in bar:
        info = training_step(policy, optimizer, windows, config.batch_size, generator, augment_shift)
        if not math.isfinite(info["mse"]):
            raise FloatingPointError(f"the training loss became {info['mse']} at step {step + 1}; "
                                     f"{path} keeps the last finite checkpoint")
        scheduler.step()
        with torch.no_grad():
            for average, current in zip(ema.parameters(), policy.parameters(), strict=True):
                average.lerp_(current, 1 - config.ema_decay)
        # MeanFlow's adaptively weighted loss stays near 1 by design: the curve shows the MSE.
        bar.set_postfix(mse=f"{info['mse']:.4f}")
        done = step + 1
        metrics.append({"step": done, **{key: info[key] for key in LOGGED_METRICS if key in info}})
        log({f"train/{key}": value for key, value in metrics[-1].items() if key != "step"}, done)
        evaluating = evaluation_due(done)
        if evaluating or done == config.steps:
            check_perception(done)
        if evaluating or done % config.checkpoint_every == 0 or done == config.steps:
            checkpoint(done)  # evaluation workers load the policy from this file
        if evaluating:
            evaluate_now(done, tasks)
            checkpoint(done)  # again, with the evaluation in the history
    bar.close()
    if config.progress and start < config.steps:
        seconds = time.perf_counter() - started - evaluation_seconds
        samples = (config.steps - start) * config.batch_size
        moved = f", windows moved by up to {100 * augment_shift:g} cm" if augment_shift else ""
        print(f"trained {config.steps - start} steps in {seconds:.0f} s ({samples / seconds:.0f} samples/s, "
              f"{torch.get_num_threads()} thread(s), {device}{moved}; evaluations took {evaluation_seconds:.0f} s "
              f"more) -> {path}")
    if config.progress and reliances:
        print("perception check, " + Reliance.from_record(reliances[-1]).summary(reliances[-1]["where"]))
    return ema.cpu().eval(), history
