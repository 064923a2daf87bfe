"""Policy training throughput (``d2a bench train``): samples per second of one training step.

Each row times the full step (sample windows, normalize, encode, loss, backward, AdamW) of a
policy preset on in-memory windows shaped like Meta-World Hammer's (4-d ``agent_pos`` and
actions, clouds of the preset's size, 84-pixel images for the image policy); the cost of a step
does not depend on the values, so random clouds and images serve. An image policy trains on the
preset's image batch. Rows run one after the other in one process with the same thread
count, so their ratios are comparable; the last column is each row against the first.
"""

from __future__ import annotations

import dataclasses
import statistics
import time
from dataclasses import dataclass

import torch
from tensordict import TensorDict

from collectors.dataset import DemoWindows, WindowConfig
from d2a_agents.policy.agent import Policy, PolicyConfig
from d2a_agents.policy.networks import EncoderConfig, VelocityNetConfig
from d2a_agents.policy.train import POLICY_PRESETS, PolicyPreset, fit_policy_normalizers, training_step

# The cpu preset before the perception work: 256 points, batch 32, MeanFlow's adaptive
# weight p = 1 and no LayerNorm after the cloud projection (kept here as the reference row).
PREVIOUS_CPU_PRESET = PolicyPreset(
    PolicyConfig(num_points=256, adaptive_power=1.0, normalize_clouds=False,
                 encoder=EncoderConfig(point_widths=(32, 64, 128), project_norm=False),
                 network=VelocityNetConfig(hidden=128, layers=3)),
    steps=4000, batch_size=32, learning_rate=1e-3,
)


def _cpu_preset_encoder(**changes: object) -> PolicyPreset:
    """The cpu preset with its encoder changed."""
    policy = POLICY_PRESETS["cpu"].policy
    encoder = dataclasses.replace(policy.encoder, **changes)
    return dataclasses.replace(POLICY_PRESETS["cpu"], policy=dataclasses.replace(policy, encoder=encoder))


# The cpu preset with its per-point MLP in float32 (the preset runs it in bfloat16).
FLOAT32_POINTS_CPU_PRESET = _cpu_preset_encoder(point_dtype="float32")
# The cpu preset encoding the imagined cloud of both observation steps (the preset: the latest).
EVERY_IMAGINED_CPU_PRESET = _cpu_preset_encoder(imagined_steps=2)
# The cpu preset at 128 points per cloud (``--policy-points 128``, the Table I point-budget test).
CPU_PRESET_128_POINTS = dataclasses.replace(
    POLICY_PRESETS["cpu"], policy=dataclasses.replace(POLICY_PRESETS["cpu"].policy, num_points=128))


@dataclass(frozen=True)
class TrainBenchConfig:
    """What ``d2a bench train`` times: (label, preset, algo) rows."""

    rows: tuple[tuple[str, PolicyPreset, str], ...] = (
        ("previous cpu", PREVIOUS_CPU_PRESET, "mp1"),
        ("cpu, float32 point MLP", FLOAT32_POINTS_CPU_PRESET, "mp1"),
        ("cpu", POLICY_PRESETS["cpu"], "mp1"),
        ("cpu, float32 point MLP", FLOAT32_POINTS_CPU_PRESET, "d2a"),
        ("cpu, both imagined frames", EVERY_IMAGINED_CPU_PRESET, "d2a"),
        ("cpu", POLICY_PRESETS["cpu"], "d2a"),
        ("cpu, 128 points", CPU_PRESET_128_POINTS, "mp1"),
        ("cpu, 128 points", CPU_PRESET_128_POINTS, "d2a"),
        ("cpu", POLICY_PRESETS["cpu"], "dp3"),
        ("cpu, 128 points", CPU_PRESET_128_POINTS, "dp3"),
        ("cpu", POLICY_PRESETS["cpu"], "dp"),
        ("cpu", POLICY_PRESETS["cpu"], "mp1-state"),
        ("paper", POLICY_PRESETS["paper"], "mp1"),
        ("paper", POLICY_PRESETS["paper"], "d2a"),
        ("paper", POLICY_PRESETS["paper"], "dp3"),
    )
    steps: int = 30  # timed steps per row, after 3 warm-up steps
    threads: int = 1
    device: str = "cpu"
    episodes: int = 10
    episode_length: int = 200
    rgb_image_size: int = 84  # the image policy's images (DP3's Meta-World size)


def synthetic_frames(num_points: int, episodes: int, length: int, seed: int = 0, image_size: int = 84) -> TensorDict:
    """Hammer-shaped frames: clouds in a 1 m box, colour images, 4-d ``agent_pos`` and actions, 39-d ``state``."""
    generator = torch.Generator().manual_seed(seed)
    n = episodes * length
    cloud = torch.rand(n, num_points, 3, generator=generator)
    images = torch.randint(0, 256, (n, image_size, image_size, 3), generator=generator, dtype=torch.uint8)
    return TensorDict({
        "point_cloud": cloud, "imagined_point_cloud": cloud.clone(), "image": images,
        "agent_pos": torch.rand(n, 4, generator=generator),
        "state": torch.rand(n, 39, generator=generator), "action": torch.rand(n, 4, generator=generator) * 2 - 1,
        "episode": torch.arange(episodes).repeat_interleave(length),
    }, batch_size=[n])


def samples_per_second(preset: PolicyPreset, algo: str, config: TrainBenchConfig) -> float:
    """Median samples/s over ``config.steps`` timed training steps (the trainer's own step)."""
    policy_config = dataclasses.replace(preset.policy, algo=algo)
    device = torch.device(config.device)
    frames = synthetic_frames(policy_config.num_points, config.episodes, config.episode_length,
                              image_size=config.rgb_image_size)
    batch_size = preset.training_fields(policy_config)["batch_size"]
    policy = Policy(policy_config, 4, frames[policy_config.encoder.state_key].shape[-1],
                    fit_policy_normalizers(frames, policy_config)).to(device)
    keys = policy_config.observation_keys
    windows = DemoWindows(frames.to(device), WindowConfig(policy_config.horizon, policy_config.n_obs_steps,
                                                          policy_config.n_action_steps, keys))
    optimizer = torch.optim.AdamW(policy.parameters(), lr=preset.learning_rate)
    generator = torch.Generator(device=device).manual_seed(0)
    timings = []
    for step in range(3 + config.steps):
        started = time.perf_counter()
        training_step(policy, optimizer, windows, batch_size, generator)
        if device.type == "cuda":
            torch.cuda.synchronize()
        if step >= 3:
            timings.append(time.perf_counter() - started)
    return batch_size / statistics.median(timings)


def run(config: TrainBenchConfig = TrainBenchConfig()) -> list[dict[str, object]]:
    """Time every row; print a markdown table (samples/s, ratio to the first row, minutes per M samples)."""
    torch.set_num_threads(config.threads)
    rows = []
    for label, preset, algo in config.rows:
        rate = samples_per_second(preset, algo, config)
        policy = dataclasses.replace(preset.policy, algo=algo)
        rows.append({"preset": label, "algo": algo, "points": preset.policy.num_points,
                     "batch": preset.training_fields(policy)["batch_size"], "samples_per_s": rate})
        print(f"{label} {algo}: {rate:.0f} samples/s", flush=True)
    first = rows[0]["samples_per_s"]
    print(f"\nTraining step, {config.threads} thread(s), {config.device}, median of {config.steps} steps:\n")
    print("| preset | algo | points | batch | samples/s | x first row | min per 1 M samples |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    for row in rows:
        rate = row["samples_per_s"]
        print(f"| {row['preset']} | {row['algo']} | {row['points']} | {row['batch']} | {rate:.0f} | "
              f"{rate / first:.2f} | {1e6 / rate / 60:.1f} |")
    return rows
