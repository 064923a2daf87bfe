"""Acting on a robot: a checkpoint run at a fixed control rate against cameras and an arm
(``d2a act``).

Two small interfaces stand between the policy and the hardware; implement them for your rig:

- :class:`CameraRig`: ``frames()`` returns the current :class:`~d2a_envs.rgbd.RGBDFrame` of
  every camera, posed in the robot's base frame (an eye-in-hand camera's pose from the current
  end-effector pose: :func:`~d2a_envs.rgbd.eye_in_hand_pose`).
- :class:`Robot`: ``state()`` returns the proprioception the policy was trained on
  (``agent_pos``), ``apply(action)`` commands one action, ``stop()`` halts the arm.

:class:`DeploymentLoop` fuses the frames into the training cloud (the crop box and point count
of the checkpoint's data), imagines the future for a ``d2a`` policy (its world model, fed the
actions it applied), asks the policy for the next action (it plans a chunk when its queue is
empty) and applies it, once per control period. It logs each step's time for the observation,
the imagination and the action, and counts the late steps (a step that overran its period);
Ctrl-C stops the robot and returns the log. :class:`SimCameras` and :class:`SimRobot` put a
simulated D2A env behind the same interfaces, for tests and as an example.

Example::

    loop = DeploymentLoop("runs/hammer/d2a/policy.pt", MyCameras(), MyArm(), hz=10)
    log = loop.run(steps=300)
    print(log.summary())
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol

import gymnasium as gym
import numpy as np

import d2a_envs
from d2a_agents.policy.agent import VARIANTS
from d2a_agents.policy.checkpoints import Acting, load_policy
from d2a_agents.world_model.imagine import Imaginer
from d2a_envs.camera import camera_id
from d2a_envs.depth import make_depth_backend
from d2a_envs.rgbd import RGBDFrame, fuse_frames, mujoco_frame
from d2a_envs.sampling import CropBox
from d2a_envs.wrappers import IMAGINED_KEY


class CameraRig(Protocol):
    """Every camera's current frame, posed in the robot's base frame."""

    def frames(self) -> list[RGBDFrame]: ...


class Robot(Protocol):
    """The arm: its proprioception, one commanded action, a halt."""

    def state(self) -> np.ndarray: ...

    def apply(self, action: np.ndarray) -> None: ...

    def stop(self) -> None: ...


@dataclass
class StepTiming:
    """Seconds one control step spent on each part; ``late``: it overran its period."""

    observation: float
    imagination: float
    action: float
    total: float
    late: bool


@dataclass
class DeploymentLog:
    """What a run did: one timing per step, and whether Ctrl-C ended it."""

    period: float
    steps: list[StepTiming] = field(default_factory=list)
    interrupted: bool = False

    def summary(self) -> str:
        if not self.steps:
            return "no step ran"
        median = {name: 1000 * statistics.median(getattr(step, name) for step in self.steps)
                  for name in ("observation", "imagination", "action", "total")}
        late = sum(step.late for step in self.steps)
        return (f"{len(self.steps)} steps at {1 / self.period:g} Hz{' (interrupted)' if self.interrupted else ''}: "
                f"median ms observation {median['observation']:.1f}, imagination {median['imagination']:.1f}, "
                f"action {median['action']:.1f}, step {median['total']:.1f}; late steps {late} "
                f"({100 * late / len(self.steps):.1f} %)")


class DeploymentLoop:
    """A checkpoint acting through a :class:`CameraRig` and a :class:`Robot` at ``hz``.

    ``crop_box`` and ``num_points`` default to those of the checkpoint's training data (the
    suite's box where the data did not set one), so the fused cloud is the one it was trained
    on. ``pixel_stride`` k reads every k-th pixel of each frame in both directions: at 640x480,
    k = 4 fuses two frames in about 7 ms on one core against about 100 ms for every pixel, and
    still leaves thousands of points in the box to sample from. ``acting``: how the policy plans
    (see :class:`~d2a_agents.policy.checkpoints.Acting`). ``clock`` and ``sleep`` can be
    replaced (tests; a robot's own clock).
    """

    def __init__(
        self, checkpoint: str | Path, cameras: CameraRig, robot: Robot, hz: float = 10.0,
        crop_box: CropBox | None = None, num_points: int | None = None, seed: int = 0, pixel_stride: int = 1,
        acting: Acting | None = None, clock: Callable[[], float] = time.perf_counter,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        if not hz > 0:
            raise ValueError(f"hz must be positive, not {hz}")
        if pixel_stride < 1:
            raise ValueError(f"pixel_stride must be at least 1, not {pixel_stride}")
        self.policy, payload = load_policy(checkpoint, acting=acting or Acting())
        if self.policy.config.encoder.use_image:
            raise ValueError(f"{checkpoint} is a {self.policy.config.algo} policy, which reads a camera image: the "
                             "deployment loop feeds fused clouds (a policy that reads clouds acts here)")
        if self.policy.config.variant.imagination == "oracle":
            raise ValueError(f"{checkpoint} is a d2a-oracle policy: it reads the simulator's true future, which a "
                             "robot has not got (a d2a policy imagines it with its world model)")
        task = payload["tasks"][0]
        env_kwargs = payload["env_kwargs"][task]
        self.crop_box = crop_box or d2a_envs.env_crop_box(task, env_kwargs)
        self.num_points = num_points or env_kwargs.get("num_points") or d2a_envs.task_config(task).num_points
        self.cameras, self.robot, self.period, self.pixel_stride = cameras, robot, 1.0 / hz, pixel_stride
        self.clock, self.sleep = clock, sleep
        self.rng = np.random.default_rng(seed)
        self.imaginer = None
        if payload["world_model"] is not None:
            imagined = VARIANTS[self.policy.config.algo].imagined
            self.imaginer = Imaginer.from_checkpoint(payload["world_model"],
                                                     num_points=self.policy.config.imagined_point_count,
                                                     seed=seed, output=imagined)
            self.history = np.zeros((self.imaginer.config.action_history, self.imaginer.config.action_dim),
                                    dtype=np.float32)
        self.policy.reset(seed)

    def observe(self) -> dict[str, np.ndarray]:
        """The observation the policy reads now (without the imagined cloud)."""
        reading = fuse_frames(self.cameras.frames(), self.crop_box, self.num_points, self.rng,
                              pixel_stride=self.pixel_stride)
        return {"point_cloud": reading.points, "agent_pos": np.asarray(self.robot.state(), dtype=np.float32)}

    def step(self) -> StepTiming:
        """One control step: observe, imagine (``d2a`` policies), act; its timing."""
        start = self.clock()
        observation = self.observe()
        observed = self.clock()
        if self.imaginer is not None:
            observation[IMAGINED_KEY] = self.imaginer(observation["point_cloud"], self.history)
        imagined = self.clock()
        action = self.policy.select_action(observation)
        self.robot.apply(action)
        if self.imaginer is not None:
            self.history = np.concatenate([self.history[1:], action[None]])
        done = self.clock()
        return StepTiming(observed - start, imagined - observed, done - imagined, done - start,
                          late=done - start > self.period)

    def run(self, steps: int | None = None) -> DeploymentLog:
        """Act for ``steps`` control periods (``None``: until Ctrl-C); the robot is stopped at the end."""
        log = DeploymentLog(self.period)
        next_tick = self.clock()
        try:
            while steps is None or len(log.steps) < steps:
                log.steps.append(self.step())
                next_tick += self.period
                wait = next_tick - self.clock()
                if wait > 0:
                    self.sleep(wait)
                else:
                    next_tick = self.clock()  # late: start the next period now rather than catch up
        except KeyboardInterrupt:
            log.interrupted = True
        finally:
            self.robot.stop()
        return log


class SimRobot:
    """A D2A env as the arm: ``state`` is its ``agent_pos``, ``apply`` steps it (``info`` kept).

    Give it the bare simulator (``env.unwrapped``) where :class:`SimCameras` see the scene: the
    env's own point cloud would otherwise be drawn at every step for nothing.
    """

    def __init__(self, env: gym.Env, seed: int = 0) -> None:
        self.env = env
        self.observation, self.info = env.reset(seed=seed)
        self.successes = 0

    def state(self) -> np.ndarray:
        return self.observation["agent_pos"]

    def apply(self, action: np.ndarray) -> None:
        self.observation, _, _, _, self.info = self.env.step(action)
        self.successes += bool(self.info.get("success"))

    def stop(self) -> None:
        """A simulated arm needs no halt."""


class SimCameras:
    """A D2A env's cameras (its own, with its image size, backend and sites) as RGB-D frames in
    the world (= base) frame."""

    def __init__(self, env: gym.Env) -> None:
        config = env.get_wrapper_attr("config")
        self.env, self.cameras = env, config.cameras
        height, width = config.image_size
        self.backend = make_depth_backend(config.backend, width, height, config.show_sites)

    def frames(self) -> list[RGBDFrame]:
        base = self.env.unwrapped
        ids = [camera_id(base.model, name) for name in self.cameras]
        return [mujoco_frame(base.model, base.data, cam, self.backend.capture(base.model, base.data, cam, False).depth)
                for cam in ids]

    def close(self) -> None:
        self.backend.close()
