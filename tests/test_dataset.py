"""Policy-training windows and normalizers, on handmade frames whose values encode (episode, step)."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from torch.utils.data import DataLoader

from collectors.dataset import DemoWindows, Normalizer, WindowConfig, episode_bounds
from collectors.storage import DemoDataset, EpisodeRecord

EPISODES = {3: 5, 7: 1, 5: 7}  # episode id -> length, stored in this order; ids deliberately not 0, 1, 2


def code(episode: int, step: int) -> float:
    return 100.0 * episode + step


def make_frames(episodes: dict[int, int] = EPISODES, points: int = 4) -> TensorDict:
    """Rows of every episode in order; every value of a row is derived from ``code(episode, step)``."""
    ids = torch.cat([torch.full((length,), episode) for episode, length in episodes.items()])
    steps = torch.cat([torch.arange(length) for length in episodes.values()])
    codes = 100.0 * ids + steps
    rows = len(ids)
    return TensorDict(
        {
            "point_cloud": codes[:, None, None].expand(rows, points, 3).float().clone(),
            "agent_pos": torch.stack([codes, -codes], 1).float(),
            "state": codes[:, None].expand(rows, 39).double().clone(),
            "action": torch.stack([codes, codes + 0.25, torch.full_like(codes, 7.0)], 1).float(),
            "reward": torch.zeros(rows),
            "success": torch.zeros(rows, dtype=torch.bool),
            "episode": ids,
            "step": steps,
        },
        batch_size=[rows],
    )


def decode(values: torch.Tensor) -> list[tuple[int, int]]:
    """(episode, step) of each leading entry of a window's obs or action tensor."""
    codes = values.reshape(values.shape[0], -1)[:, 0].round().long()
    return [(int(c) // 100, int(c) % 100) for c in codes]


def window_codes(window: TensorDict) -> dict[str, list[tuple[int, int]]]:
    return {
        "point_cloud": decode(window["obs", "point_cloud"]),
        "agent_pos": decode(window["obs", "agent_pos"]),
        "action": decode(window["action"]),
    }


def dp3_windows(lengths: list[int], horizon: int, pad_before: int, pad_after: int) -> list[tuple[list[int], int, int]]:
    """DP3's SequenceSampler (create_indices, then edge padding) written as its loops:
    (row indices, start step in the episode, episode length) of every window."""
    windows, start = [], 0
    for length in lengths:
        for idx in range(-pad_before, length - horizon + pad_after + 1):
            windows.append(([start + min(max(idx + k, 0), length - 1) for k in range(horizon)], idx, length))
        start += length
    return windows


# --- windows ------------------------------------------------------------------------------


def test_every_step_is_the_current_step_of_one_window():
    frames = make_frames()
    windows = DemoWindows(frames, WindowConfig())
    assert len(windows) == frames.shape[0] == sum(EPISODES.values())
    batch = windows.get(torch.arange(len(windows)))
    assert list(zip(batch["episode"].tolist(), batch["step"].tolist(), strict=True)) == list(
        zip(frames["episode"].tolist(), frames["step"].tolist(), strict=True)
    )
    # the current step is the last observation
    assert decode(batch["obs", "agent_pos"][:, -1]) == list(
        zip(batch["episode"].tolist(), batch["step"].tolist(), strict=True)
    )


def test_windows_never_mix_episodes():
    windows = DemoWindows(make_frames(), WindowConfig(horizon=8, n_obs_steps=3, n_action_steps=6))
    for i in range(len(windows)):
        window = windows[i]
        episodes = {episode for codes in window_codes(window).values() for episode, _ in codes}
        assert episodes == {int(window["episode"])}


@pytest.mark.parametrize(
    ("episode", "step", "obs_steps", "action_steps"),
    [
        (3, 0, [0, 0], [0, 0, 1, 2]),  # first step: the missing earlier frame repeats frame 0
        (3, 1, [0, 1], [0, 1, 2, 3]),  # no padding
        (3, 4, [3, 4], [3, 4, 4, 4]),  # last step: actions past the end repeat the last one
        (7, 0, [0, 0], [0, 0, 0, 0]),  # a 1-step episode is all padding around its only frame
        (5, 0, [0, 0], [0, 0, 1, 2]),
        (5, 3, [2, 3], [2, 3, 4, 5]),
        (5, 5, [4, 5], [4, 5, 6, 6]),
        (5, 6, [5, 6], [5, 6, 6, 6]),
    ],
)
def test_edge_padding_repeats_first_and_last_frames(episode, step, obs_steps, action_steps):
    windows = DemoWindows(make_frames(), WindowConfig())
    batch = windows.get(torch.arange(len(windows)))
    (index,) = torch.nonzero((batch["episode"] == episode) & (batch["step"] == step)).flatten().tolist()
    codes = window_codes(windows[index])
    assert codes["point_cloud"] == codes["agent_pos"] == [(episode, s) for s in obs_steps]
    assert codes["action"] == [(episode, s) for s in action_steps]
    assert windows[index]["action"][:, 2].eq(7.0).all()


@pytest.mark.parametrize(
    ("horizon", "n_obs_steps", "n_action_steps"),
    [(4, 2, 4), (16, 2, 8), (6, 2, 2), (3, 3, 1), (1, 1, 1), (5, 1, 3)],
)
def test_windows_are_dp3_windows_whose_current_step_exists(horizon, n_obs_steps, n_action_steps):
    lengths = [5, 1, 7, 20]
    config = WindowConfig(horizon=horizon, n_obs_steps=n_obs_steps, n_action_steps=n_action_steps)
    windows = DemoWindows(make_frames(dict(enumerate(lengths))), config)
    expected = [
        rows
        for rows, start, length in dp3_windows(lengths, horizon, config.pad_before, config.pad_after)
        if start + n_obs_steps - 1 < length  # DP3 also makes windows whose current step is past the end
    ]
    assert windows.action_rows.tolist() == expected
    assert windows.obs_rows.tolist() == [rows[:n_obs_steps] for rows in expected]


def test_short_episodes_yield_no_window_under_long_horizons():
    with pytest.raises(ValueError, match="no windows"):
        DemoWindows(make_frames(), WindowConfig(horizon=16, n_obs_steps=2, n_action_steps=8))


def test_sampling_is_reproducible_for_a_seed():
    windows = DemoWindows(make_frames())
    first = windows.sample(32, torch.Generator().manual_seed(0))
    again = windows.sample(32, torch.Generator().manual_seed(0))
    other = windows.sample(32, torch.Generator().manual_seed(1))
    assert first.batch_size == torch.Size([32])
    assert first["obs", "point_cloud"].shape == (32, 2, 4, 3) and first["action"].shape == (32, 4, 3)
    assert (first == again).all()
    assert not (first == other).all()


def test_held_out_episodes_are_excluded():
    frames = make_frames()
    train = DemoWindows(frames, episodes=[3, 5])
    held_out = DemoWindows(frames, episodes=[7])
    assert train.episode_ids.tolist() == [3, 5] and len(train) == 12
    assert len(held_out) == 1
    seen = {episode for i in range(len(train)) for codes in window_codes(train[i]).values() for episode, _ in codes}
    assert seen == {3, 5}
    assert set(train.sample(200, torch.Generator().manual_seed(0))["episode"].tolist()) == {3, 5}
    with pytest.raises(ValueError, match=r"\[4\]"):
        DemoWindows(frames, episodes=[3, 4])


def test_non_contiguous_episodes_are_refused():
    frames = make_frames()
    frames["episode"][1] = 7
    with pytest.raises(ValueError, match="contiguous"):
        episode_bounds(frames)


def test_data_loader_batches_with_torch_stack():
    windows = DemoWindows(make_frames())
    loader = DataLoader(windows, batch_size=4, shuffle=True, collate_fn=torch.stack,
                        generator=torch.Generator().manual_seed(0))
    batch = next(iter(loader))
    assert batch["obs", "agent_pos"].shape == (4, 2, 2) and batch["action"].shape == (4, 4, 3)


def test_windows_read_a_stored_demo_dataset(tmp_path):
    frames = make_frames()
    dataset = DemoDataset.create(tmp_path / "demos", capacity=4)
    for episode, length in EPISODES.items():
        rows = frames[frames["episode"] == episode]
        dataset.add_episode(rows, EpisodeRecord(episode, "hammer", 0, length, True, 0.0, 0, 0, 0))
    stored = DemoDataset.open(tmp_path / "demos").frames()
    windows, reference = DemoWindows(stored), DemoWindows(frames)
    batch = windows.sample(16, torch.Generator().manual_seed(0))
    assert type(batch["action"]) is torch.Tensor
    assert (batch == reference.sample(16, torch.Generator().manual_seed(0))).all()


# --- normalizers --------------------------------------------------------------------------


def varied_data() -> torch.Tensor:
    data = torch.randn(200, 5, generator=torch.Generator().manual_seed(0)) * torch.tensor([1.0, 10.0, 0.01, 3.0, 1.0])
    data[:, 3] = 2.5  # a constant dimension
    data[:, 4] += 100.0  # far from zero
    return data


def test_normalizer_maps_data_onto_minus_one_one_and_back():
    data = varied_data()
    normalizer = Normalizer.fit(data)
    normalized = normalizer.normalize(data)
    varying = [0, 1, 2, 4]
    assert normalized.min() >= -1 and normalized.max() <= 1
    assert torch.allclose(normalized[:, varying].amin(0), torch.full((4,), -1.0), atol=1e-6)
    assert torch.allclose(normalized[:, varying].amax(0), torch.full((4,), 1.0), atol=1e-6)
    assert normalized.dtype == data.dtype
    # float32 keeps about 7 significant digits, so the round trip holds to 1e-6 relative (|x| is up to ~100 here)
    assert torch.allclose(normalizer.unnormalize(normalized), data, atol=1e-6, rtol=1e-6)
    data64 = data.double()
    assert torch.allclose(normalizer.unnormalize(normalizer.normalize(data64)), data64, atol=1e-12, rtol=0)


def test_constant_dimensions_map_to_zero_and_back_exactly():
    data = varied_data()
    normalizer = Normalizer.fit(data)
    assert torch.equal(normalizer.normalize(data)[:, 3], torch.zeros(200))
    assert torch.equal(normalizer.unnormalize(torch.zeros(7, 5))[:, 3], torch.full((7,), 2.5))
    assert torch.isfinite(Normalizer.fit(torch.zeros(3, 2)).normalize(torch.ones(2))).all()


def test_a_normalizer_s_statistics_travel_in_its_state_dict():
    """A placeholder of the same shape becomes the fitted map by load_state_dict alone."""
    data = varied_data()
    fitted = Normalizer.fit(data)
    restored = Normalizer.placeholder(data.shape[1])
    assert not torch.equal(restored.normalize(data), fitted.normalize(data))
    restored.load_state_dict(fitted.state_dict())
    assert set(fitted.state_dict()) == {"low", "high", "centre", "half_range"}
    assert torch.equal(restored.normalize(data), fitted.normalize(data))
    assert torch.equal(restored.unnormalize(data), fitted.unnormalize(data))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_data_is_refused(bad):
    data = varied_data()
    data[17, 1] = bad
    with pytest.raises(ValueError, match="NaN or inf"):
        Normalizer.fit(data)
    with pytest.raises(ValueError, match="NaN or inf"):
        Normalizer.fit(varied_data()).normalize(data)


def test_shape_mismatch_is_refused():
    normalizer = Normalizer.fit(varied_data())
    with pytest.raises(ValueError, match="shape"):
        normalizer.normalize(torch.zeros(3, 4))
    with pytest.raises(ValueError, match="shape"):
        normalizer.unnormalize(torch.zeros(5, 1))


def test_the_first_episodes_of_a_data_set_are_a_prefix_of_its_storage(tmp_path):
    from collectors.collect import CollectConfig, collect
    from collectors.storage import DatasetError, DemoDataset

    out = tmp_path / "two_tasks"
    collect(CollectConfig(tasks=("reach", "reach-wall"), out=str(out), episodes=2,
                          env_kwargs={"image_size": 32, "num_points": 32}, progress=False))
    dataset = DemoDataset.open(out)
    assert dataset.episode_counts() == {"reach": 2, "reach-wall": 2}
    assert dataset.holds_exactly(2) and dataset.holds_exactly(None) and not dataset.holds_exactly(1)
    # Episodes 0-1 are Reach, 2-3 Reach-Wall: the first of each (0 and 2) do not lead the storage.
    with pytest.raises(DatasetError, match="not the first in the storage"):
        dataset.first_episodes(1)
    with pytest.raises(DatasetError, match="fewer than 3 episodes"):
        dataset.first_episodes(3)
    dataset.metadata.episodes = dataset.metadata.episodes[:2]  # a Reach-only view of the same storage
    dataset.metadata.tasks.pop("reach-wall")
    view = dataset.first_episodes(1)
    assert [episode.index for episode in view.metadata.episodes] == [0]
    assert torch.equal(view.frames()["action"], dataset.episode(0)["action"])
    assert len(dataset.metadata.episodes) == 2  # the view leaves the data set's own record alone
