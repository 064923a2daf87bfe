"""The policy: observation window -> action chunk, one algorithm flag for every variant.

Variants (``--algo``), all on the same encoders, network, data and evaluation:

| algo | action expert | observation | imagined cloud | adaptive CFG |
| --- | --- | --- | --- | --- |
| ``d2a`` | MeanFlow, 1 step | cloud + ``agent_pos`` | yes | yes |
| ``d2a-change`` | MeanFlow, 1 step | cloud + ``agent_pos`` | where it changes: the voxels it fills | yes |
| ``d2a-change-top`` | MeanFlow, 1 step | cloud + ``agent_pos`` | the likeliest of those voxels | yes |
| ``d2a-no-cfg`` | MeanFlow, 1 step | cloud + ``agent_pos`` | yes | no |
| ``d2a-no-imagination`` | MeanFlow, 1 step | cloud + ``agent_pos`` | no | yes |
| ``d2a-present`` | MeanFlow, 1 step | cloud + ``agent_pos`` | the current cloud again | yes |
| ``d2a-oracle`` | MeanFlow, 1 step | cloud + ``agent_pos`` | the true future (the expert's, from the simulator) | yes |
| ``mp1`` | MeanFlow, 1 step | cloud + ``agent_pos`` | no | no |
| ``dp3`` | diffusion, DDIM 10 steps | cloud + ``agent_pos`` | no | no |
| ``flowpolicy`` | consistency flow matching, 1 step (FlowPolicy) | cloud + ``agent_pos`` | no | no |
| ``edm`` | EDM diffusion, Heun (Consistency Policy's teacher) | cloud + ``agent_pos`` | no | no |
| ``cp`` | consistency student of an ``edm`` run, 1 step (Consistency Policy) | cloud + ``agent_pos`` | no | no |
| ``dp`` | diffusion, DDIM 10 steps (2D Diffusion Policy) | camera image + ``agent_pos`` | no | no |
| ``mp1-state`` | MeanFlow, 1 step | the simulator's ``state`` | no | no |
| ``dp3-state`` | diffusion, DDIM 10 steps | the simulator's ``state`` | no | no |

``mp1-state`` is the perception reference: the same action expert fed privileged state
(Meta-World's 39-d observation holds the object positions), i.e. what the expert does with
perfect perception at the same budget; ``dp3-state`` is the same reference for the diffusion
expert (where it imitates demonstrations that ``mp1-state`` does not, the one-step expert is
what falls short, not the demonstrations). ``d2a-present`` is the control of imagination: the
second encoder reads the current cloud in place of the imagined one (no world model), so
``d2a`` against it separates what the imagined future adds from what a second encoder adds.
``d2a-oracle`` is imagination's upper bound: it reads the cloud the scene really shows
``oracle_horizon`` steps ahead when the expert acts (the demonstrations' own in training,
the simulator's look-ahead, :class:`~collectors.expert_future.ExpertFuture`, in evaluation),
the future a world model trained on those demonstrations aims at, without its errors;
with ``stacked_horizons`` it reads the true futures at several horizons at once (one cloud
each through the imagined-cloud encoder, nearest first).

The policy owns its normalizers (min/max to [-1, 1]: actions, the low-dimensional
observation, and the clouds per axis, the imagined cloud with the current cloud's map) and
applies them the same way in :meth:`Policy.compute_loss` and :meth:`Policy.predict_action_chunk`: callers
pass raw observations and actions in env units.
"""

from __future__ import annotations

import dataclasses
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torch import nn

from collectors.dataset import Normalizer
from collectors.envs import STATE_KEY
from d2a_agents.policy.networks import EncoderConfig, ObservationEncoder, VelocityNet, VelocityNetConfig
from d2a_envs.read_steps import ReadSteps
from d2a_envs.sampling import farthest_point_indices
from d2a_envs.wrappers import IMAGE_KEY, IMAGINED_KEY

CLOUD_KEYS = ("point_cloud", IMAGINED_KEY)  # normalized with the current cloud's normalizer
IMAGE_SETTINGS = ("use_image", "image_widths")  # EncoderConfig's; recorded only for image policies


@dataclass(frozen=True)
class Variant:
    """What an ``--algo`` name stands for (the one place it is decoded)."""

    expert: str  # "meanflow", "diffusion", "edm", "consistency-flow" or "consistency-trajectory"
    # The second cloud encoder's input: "none" (no second encoder), "world-model" (the
    # imagined cloud), "present" (the current cloud again, the control of imagination) or
    # "oracle" (the true future cloud, imagination's upper bound; Meta-World evaluation only).
    imagination: str = "none"
    cfg: bool = False
    # "cloud" (cloud + agent_pos), "image" (the camera's colour image + agent_pos) or "state"
    # (the privileged simulator state)
    observation: str = "cloud"
    imagined: str = "future"  # what the imagined cloud holds (world_model.imagine.IMAGINED_OUTPUTS)


VARIANTS: dict[str, Variant] = {
    "d2a": Variant("meanflow", imagination="world-model", cfg=True),
    "d2a-change": Variant("meanflow", imagination="world-model", cfg=True, imagined="change"),
    "d2a-change-top": Variant("meanflow", imagination="world-model", cfg=True, imagined="change-top"),
    "d2a-no-cfg": Variant("meanflow", imagination="world-model"),
    "d2a-no-imagination": Variant("meanflow", cfg=True),
    "d2a-present": Variant("meanflow", imagination="present", cfg=True),
    "d2a-oracle": Variant("meanflow", imagination="oracle", cfg=True),
    "mp1": Variant("meanflow"),
    "dp3": Variant("diffusion"),
    "flowpolicy": Variant("consistency-flow"),
    "edm": Variant("edm"),
    "cp": Variant("consistency-trajectory"),
    "dp": Variant("diffusion", observation="image"),
    "mp1-state": Variant("meanflow", observation="state"),
    "dp3-state": Variant("diffusion", observation="state"),
}
ALGORITHMS = tuple(VARIANTS)
STATE_ALGORITHMS = tuple(algo for algo, variant in VARIANTS.items() if variant.observation == "state")  # no cloud
# Steps ahead of ``d2a-oracle``'s future cloud by default: the world models' horizon (WorldModelConfig.horizon).
ORACLE_HORIZON = 4


def uses_imagination(algo: str) -> bool:
    """Whether ``algo`` reads a world model's imagined cloud (and so needs a world model)."""
    return VARIANTS[algo].imagination == "world-model"


def reads_images(algo: str) -> bool:
    """Whether ``algo`` reads the camera's colour image (and so needs data collected with images)."""
    return VARIANTS[algo].observation == "image"


@dataclass(frozen=True)
class PolicyConfig:
    """Architecture and action-chunking of a policy (defaults: MP1's horizon 4 / 2 / 4).

    ``num_points`` < the data's cloud size subsamples clouds by FPS before the encoder (the
    CPU preset gives up resolution for speed); ``imagined_points`` gives the second cloud
    encoder (the imagined cloud, or ``d2a-present``'s copy of the present) a count of its own.
    """

    algo: str = "d2a"
    horizon: int = 4
    n_obs_steps: int = 2
    n_action_steps: int = 4
    num_points: int = 512
    imagined_points: int | None = None  # None: num_points
    # Steps ahead of d2a-oracle's true future cloud (other variants ignore it).
    oracle_horizon: int = ORACLE_HORIZON
    # Further horizons whose true future clouds d2a-oracle reads beside oracle_horizon's, each
    # through the imagined-cloud encoder: (1, 2) with oracle_horizon 4 stacks H = 1, 2, 4.
    stacked_horizons: tuple[int, ...] = ()
    # Map clouds per axis onto [-1, 1] with the min/max of the training clouds (DP3, MP1).
    # False feeds raw metres (an ablation: the encoder then barely sees a 10 cm move).
    normalize_clouds: bool = True
    # MeanFlow's adaptive loss weight 1 / (||delta||^2 + eps)^p (p = 0: plain squared error).
    adaptive_power: float = 1.0
    # What the diffusion baseline's network predicts: "sample" (the clean chunk, DP3's
    # Meta-World configs) or "epsilon" (the noise).
    diffusion_prediction: str = "sample"
    # (tau_l, tau_h) of eq. 7 (the paper gives no values). With tau_l = 0 an untrained null
    # branch (rho <= 0) sets w = 0 and the conditional branch first learns the unconditional
    # field: on Hammer at the demo budget, (0, 0.5) scored 0/20, (-1, 0) 1/10, no CFG 2/10.
    cfg_thresholds: tuple[float, float] = (-1.0, 0.0)
    # rho of eq. 7: "prediction" (cos(u_cond, u_null), the network's conditional velocity) or
    # "velocity" (cos(v, u_null), v the sampled A_1 - A_0, as MeanFlow's CFG target uses it); the
    # paper's v_t(. | c) admits both. On Hammer (mp1 + the CFG target, 4000 steps, 50 episodes
    # per seed): "velocity" 0 / 0 / 0 %, "prediction" 6 / 12 / 0 %, no gate (condition dropout only)
    # 20 / 22 %, mp1 18 / 20 / 24 %; see d2a_agents/policy/meanflow.py for why.
    cfg_similarity: str = "prediction"
    # "interpolate" (eq. 6 as written, w in [0, 1]) or "amplify" (mixing weight 1 + cfg_scale * w,
    # guidance away from the unconditional field as MeanFlow / MP1 guide); see meanflow.py.
    cfg_guidance: str = "interpolate"
    cfg_scale: float = 1.0
    # What a MeanFlow network outputs: "velocity" (the average velocity, as MeanFlow and MP1
    # train it) or "action" (the clean chunk, read as a velocity; see meanflow.ActionOutput).
    meanflow_output: str = "velocity"
    encoder: EncoderConfig = field(default_factory=EncoderConfig)
    network: VelocityNetConfig = field(default_factory=VelocityNetConfig)

    def __post_init__(self) -> None:
        if self.algo not in ALGORITHMS:
            raise ValueError(f"unknown algo {self.algo!r}; choose one of {ALGORITHMS}")
        if self.num_points < 1 or (self.imagined_points is not None and self.imagined_points < 1):
            raise ValueError(f"num_points and imagined_points must be at least 1, not {self.num_points} and "
                             f"{self.imagined_points}")
        if self.n_action_steps < 1:
            raise ValueError(f"n_action_steps must be at least 1, not {self.n_action_steps}")
        if min((self.oracle_horizon, *self.stacked_horizons)) < 1:
            raise ValueError(f"oracle horizons must be at least 1, not {(self.oracle_horizon, *self.stacked_horizons)}")
        if len(set(self.oracle_horizons)) != 1 + len(self.stacked_horizons):
            raise ValueError(f"stacked_horizons {self.stacked_horizons} repeat a horizon (oracle_horizon "
                             f"{self.oracle_horizon})")
        variant = self.variant
        state = variant.observation == "state"
        encoder = dataclasses.replace(
            self.encoder, n_obs_steps=self.n_obs_steps, use_imagination=variant.imagination != "none",
            use_cloud=variant.observation == "cloud", use_image=variant.observation == "image",
            state_key="state" if state else "agent_pos",
            imagined_clouds=len(self.oracle_horizons) if variant.imagination == "oracle" else 1,
        )
        object.__setattr__(self, "encoder", encoder)
        # The time scale belongs to the algorithm: DDPM's 1000 for diffusion (EDM's ln(sigma) / 4
        # spans about as much as DDPM's t in [0, 1]), 1 for flows.
        time_scale = 1000.0 if variant.expert in ("diffusion", "edm", "consistency-trajectory") else 1.0
        object.__setattr__(self, "network", dataclasses.replace(self.network, time_scale=time_scale))

    @property
    def variant(self) -> Variant:
        return VARIANTS[self.algo]

    @property
    def oracle_horizons(self) -> tuple[int, ...]:
        """Steps ahead of each true future cloud ``d2a-oracle`` reads, nearest first."""
        return tuple(sorted((self.oracle_horizon, *self.stacked_horizons)))

    @property
    def imagined_point_count(self) -> int:
        """Points of the second cloud encoder's input."""
        return self.num_points if self.imagined_points is None else self.imagined_points

    @property
    def observation_keys(self) -> tuple[str, ...]:
        """The observations the policy's windows hold, in order: ``imagined_point_cloud`` for a
        world-model variant, and for ``d2a-present`` when it samples its copy of the present
        cloud to a count of its own (otherwise that copy is the present cloud itself)."""
        own_copy = self.variant.imagination == "present" and self.imagined_points is not None
        return self.env_observation_keys + ((IMAGINED_KEY,) if own_copy else ())

    @property
    def env_observation_keys(self) -> tuple[str, ...]:
        """The observations the policy reads from its env (an imagining env adds the imagined
        cloud, an oracle's the true future one)."""
        encoder = self.encoder
        return (("point_cloud",) if encoder.use_cloud else ()) + ((IMAGE_KEY,) if encoder.use_image else ()) + (
            encoder.state_key,) + (
            (IMAGINED_KEY,) if self.variant.imagination in ("world-model", "oracle") else ())

    @property
    def executed_actions(self) -> int:
        """Actions executed per chunk: the chunk starts at the oldest observation."""
        return min(self.n_action_steps, self.horizon - (self.n_obs_steps - 1))

    @property
    def clouds_read(self) -> dict[str, int]:
        """The env's clouds the encoders read, each with how many of a window's latest
        observations they read it from (the imagined cloud: ``imagined_steps`` of them)."""
        encoder = self.encoder
        read = {"point_cloud": self.n_obs_steps} if encoder.use_cloud else {}
        if self.variant.imagination in ("world-model", "oracle"):
            read[IMAGINED_KEY] = encoder.imagined_steps
        return read

    def read_steps(self) -> dict[str, ReadSteps]:
        """The steps of an episode at which acting reads each env cloud (a plan every
        ``executed_actions`` steps, from the latest observations of :attr:`clouds_read`): what an
        evaluation env has to render or imagine (``make_env``'s ``read_steps``). A policy that
        reads no cloud reads ``point_cloud`` at no step."""
        period = self.executed_actions
        read = {"point_cloud": 0} | self.clouds_read
        return {key: ReadSteps(period, window) for key, window in read.items()}

    def to_dict(self) -> dict:
        """Every setting, less the image encoder's where the policy reads no image (there they
        do nothing, and a checkpoint written before they existed still resumes)."""
        raw = dataclasses.asdict(self)
        if not self.encoder.use_image:
            for name in IMAGE_SETTINGS:
                del raw["encoder"][name]
        return raw

    @classmethod
    def from_dict(cls, raw: dict) -> PolicyConfig:
        encoder, network = EncoderConfig(**raw["encoder"]), VelocityNetConfig(**raw["network"])
        tuples = {"cfg_thresholds": tuple(raw["cfg_thresholds"]),  # lists in a checkpoint's JSON
                  "stacked_horizons": tuple(raw.get("stacked_horizons", ()))}
        return cls(**{**raw, "encoder": encoder, "network": network, **tuples})


# What fits a 2-core CPU: 64 points into the encoders (as ManiFlow on Meta-World), a
# third of DP3's encoder widths (a quarter of ResNet-18's for images), a narrower velocity
# network, the plain squared error (p = 0). See POLICY_PRESETS in train.py for the budget
# and docs/perception.md for the ablations behind it.
CPU_POLICY_PRESET = PolicyConfig(
    num_points=64, adaptive_power=0.0,
    encoder=EncoderConfig(point_widths=(32, 64, 128), point_dtype="bfloat16", image_widths=(16, 32, 64, 128)),
    network=VelocityNetConfig(hidden=128, layers=3),
)


def make_expert(config: PolicyConfig):
    """The action expert of ``config.algo`` (MeanFlow, with adaptive CFG or not, diffusion, EDM,
    consistency flow matching, or the consistency student, whose teacher is attached in training)."""
    if config.variant.expert == "consistency-trajectory":
        from d2a_agents.policy.consistency_policy import ConsistencyTrajectory

        return ConsistencyTrajectory()
    if config.variant.expert == "edm":
        from d2a_agents.policy.edm import EDM

        return EDM()
    if config.variant.expert == "diffusion":
        from d2a_agents.policy.diffusion import Diffusion, DiffusionConfig

        return Diffusion(DiffusionConfig(prediction_type=config.diffusion_prediction))
    if config.variant.expert == "consistency-flow":
        from d2a_agents.policy.consistency_flow import ConsistencyFlow

        return ConsistencyFlow()
    from d2a_agents.policy.meanflow import MeanFlow, MeanFlowConfig

    tau_l, tau_h = config.cfg_thresholds
    return MeanFlow(MeanFlowConfig(cfg_enabled=config.variant.cfg, tau_l=tau_l, tau_h=tau_h,
                                   cfg_similarity=config.cfg_similarity, adaptive_power=config.adaptive_power,
                                   cfg_guidance=config.cfg_guidance, cfg_scale=config.cfg_scale,
                                   network_output=config.meanflow_output))


def subsample_cloud(cloud: torch.Tensor, num_points: int) -> torch.Tensor:
    """FPS a (N, 3) cloud down to ``num_points`` (unchanged when it is not larger)."""
    if cloud.shape[0] <= num_points:
        return cloud
    return cloud[torch.as_tensor(farthest_point_indices(cloud.numpy(), num_points))]


def normalizer_keys(config: PolicyConfig) -> tuple[str, ...]:
    """The normalizers a policy needs: actions, its low-dimensional observation, its clouds."""
    return ("action", config.encoder.state_key) + (("point_cloud",) if config.encoder.use_cloud else ())


class Policy(nn.Module):
    """Encoders + velocity network + expert + normalizers: everything a checkpoint holds, and
    the acting interface.

    Training: :meth:`compute_loss` on a batch of raw windows. Acting: :meth:`reset` at every
    episode start, then :meth:`select_action` on each raw env observation; the policy keeps
    the last ``n_obs_steps`` observations and a queue of planned actions, and plans a new
    chunk (:meth:`predict_action_chunk`) when the queue is empty.

    Example:
        >>> policy, _ = load_policy("runs/hammer/mp1/policy.pt")   # d2a_agents.policy.checkpoints
        >>> observation, _ = env.reset(seed=0); policy.reset(seed=0)
        >>> action = policy.select_action(observation)           # (A,) float32, env units
        >>> window = {"point_cloud": clouds, "agent_pos": positions}  # (B, n_obs, N, 3), (B, n_obs, 4)
        >>> policy.predict_action_chunk(window).shape               # env units
        torch.Size([B, 4, 4])
    """

    def __init__(
        self, config: PolicyConfig, action_dim: int, state_dim: int, normalizers: dict[str, Normalizer]
    ) -> None:
        super().__init__()
        missing = [key for key in normalizer_keys(config) if key not in normalizers]
        if missing:
            raise ValueError(f"a {config.algo} policy needs normalizers for {missing}")
        self.config = config
        self.action_dim, self.state_dim = action_dim, state_dim
        self.encoder = ObservationEncoder(config.encoder, state_dim)
        self.net = VelocityNet(config.network, config.horizon, action_dim, self.encoder.out_dim)
        self.expert = make_expert(config)
        self.normalizers = nn.ModuleDict(normalizers)  # their statistics are buffers: in the state dict
        # Chunks drawn per plan, acted on as their mean (1: one draw, as trained and as the papers
        # act); acting only, set by load_policy. More draws average out the sampler's spread.
        self.action_draws = 1
        self.sample_steps: int | None = None  # network evaluations per chunk (None: the expert's own)
        self.reset()

    def normalize_observation(self, observation: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """A raw observation window mapped onto [-1, 1] (clouds per axis), as the encoders read it.

        ``d2a-present`` reads the current cloud as its imagined one, unless the window holds an
        ``imagined_point_cloud`` (the perception check shuffles that copy alone).
        """
        keys = self.config.observation_keys
        if self.config.variant.imagination == "present" and IMAGINED_KEY not in keys:
            observation = {IMAGINED_KEY: observation["point_cloud"], **observation}
            keys = (*keys, IMAGINED_KEY)
        normalized = {}
        for key in keys:
            if key == IMAGE_KEY:  # raw pixels: the image encoder maps [0, 255] onto [-1, 1] itself
                normalized[key] = observation[key]
                continue
            normalizer = self.normalizers["point_cloud" if key in CLOUD_KEYS else key]
            normalized[key] = normalizer.normalize(observation[key][..., :3] if key in CLOUD_KEYS else observation[key])
        return normalized

    def condition(self, observation: dict[str, torch.Tensor]) -> torch.Tensor:
        """f_c from a raw observation window."""
        return self.encoder(self.normalize_observation(observation))

    def compute_loss(
        self, observation: dict[str, torch.Tensor], actions: torch.Tensor, generator: torch.Generator | None = None
    ) -> tuple[torch.Tensor, dict[str, float]]:
        """Training loss and logged figures on a batch of raw windows (observations and action
        chunks (B, horizon, A) in env units)."""
        normalized = self.normalizers["action"].normalize(actions)
        return self.expert.loss(self.net, normalized, self.condition(observation), generator=generator)

    @torch.no_grad()
    def sample_normalized(
        self, observation: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Action chunks (B, horizon, A) in the normalized action space, from a raw window: the
        mean of ``action_draws`` chunks drawn from independent noise (the encoders run once), each
        in ``sample_steps`` network evaluations."""
        condition = self.condition(observation)
        if self.action_draws == 1:
            return self.expert.sample(self.net, condition, generator=generator, steps=self.sample_steps)
        draws = self.expert.sample(self.net, condition.repeat_interleave(self.action_draws, 0), generator=generator,
                                   steps=self.sample_steps)
        return draws.unflatten(0, (condition.shape[0], self.action_draws)).mean(1)

    @torch.no_grad()
    def predict_action_chunk(self, observation: dict[str, torch.Tensor], generator: torch.Generator | None = None):
        """Action chunk (B, horizon, A) in env units from a raw observation window."""
        return self.normalizers["action"].unnormalize(self.sample_normalized(observation, generator))

    def reset(self, seed: int = 0) -> None:
        """Start an episode: forget the observations and planned actions, reseed the sampler
        (an episode's actions then depend on its seed only, not on what ran before)."""
        self._history: deque[dict[str, torch.Tensor]] = deque(maxlen=self.config.n_obs_steps)
        self._queue: deque[np.ndarray] = deque()
        self._generator = torch.Generator().manual_seed(int(seed))

    def _observe(self, observation: dict[str, np.ndarray]) -> None:
        frame = {}
        for key in self.config.observation_keys:
            source = "point_cloud" if key == IMAGINED_KEY and self.config.variant.imagination == "present" else key
            value = torch.as_tensor(np.asarray(observation[source]), dtype=torch.float32)
            points = self.config.imagined_point_count if key == IMAGINED_KEY else self.config.num_points
            if value.ndim == 2 and value.isnan().all():  # a step the env skipped (ReadSteps): kept as NaN
                value = value[:points, :3]
            frame[key] = subsample_cloud(value[:, :3], points) if value.ndim == 2 else value
        if not self._history:
            self._history.extend([frame] * self.config.n_obs_steps)  # repeat the first frame, as in training
        else:
            self._history.append(frame)

    def _window(self) -> dict[str, torch.Tensor]:
        """The planning window (batch of 1): each observation over the latest frames the encoders
        read of it (an imagined cloud over ``imagined_steps``, the others over all); a cloud the env
        skipped there is refused (the env was not made with this policy's read steps)."""
        frames, read, window = list(self._history), self.config.clouds_read, {}
        for key in self.config.observation_keys:
            window[key] = torch.stack([frame[key] for frame in frames[-read.get(key, len(frames)):]])
            if key in CLOUD_KEYS and window[key].isnan().any():
                raise ValueError(f"the env skipped a {key} this policy reads: make it with the policy's "
                                 f"read steps ({self.config.read_steps()[key]}) or with none")
        return {key: value[None] for key, value in window.items()}

    @torch.no_grad()
    def select_action(self, observation: dict[str, np.ndarray]) -> np.ndarray:
        """The next action (A,) float32 for one raw env observation (keys as the env names them)."""
        self._observe(observation)
        if not self._queue:
            window = self._window()
            was_training = self.training
            chunk = self.eval().predict_action_chunk(window, self._generator)[0].numpy()
            self.train(was_training)
            start = self.config.n_obs_steps - 1
            self._queue.extend(chunk[start : start + self.config.executed_actions])
        action = self._queue.popleft().astype(np.float32)
        if not np.all(np.isfinite(action)):
            raise ValueError(f"the policy produced a non-finite action {action}")
        return action


# TorchRL's GymWrapper renames the env's ``state`` observation; the others keep their names.
TORCHRL_KEYS = {"state": STATE_KEY}


class TorchRLPolicy(TensorDictModuleBase):
    """A :class:`Policy` as a TorchRL policy: reads the env's observation keys, writes
    ``action``. On the first step of an episode (``is_init``, from an ``InitTracker``) it
    resets the policy with the episode's seed, so results do not depend on how episodes are
    spread over workers.
    """

    def __init__(self, policy: Policy) -> None:
        super().__init__()
        self.policy = policy.eval()
        self.observation_keys = {key: TORCHRL_KEYS.get(key, key) for key in policy.config.env_observation_keys}
        self.in_keys = [*self.observation_keys.values(), "is_init", "episode_seed"]
        self.out_keys = ["action"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        if bool(tensordict.get("is_init", torch.ones(1, dtype=torch.bool)).any()):
            self.policy.reset(seed=int(tensordict.get("episode_seed", torch.zeros(())).reshape(-1)[0]))
        observation = {key: tensordict.get(name).numpy() for key, name in self.observation_keys.items()}
        tensordict.set("action", torch.as_tensor(self.policy.select_action(observation)))
        return tensordict
