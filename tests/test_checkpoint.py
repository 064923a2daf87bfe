"""Checkpoint files are read without running code from them."""

from __future__ import annotations

import os

import pytest
import torch

from d2a_agents.checkpoint import CheckpointError, load_checkpoint, load_for_resume, save_checkpoint


class _Payload:
    """Unpickling this would create ``path`` (the classic pickle exploit)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self):
        return os.mknod, (self.path,)


def test_a_pickle_that_runs_code_is_refused_without_running_it(tmp_path):
    marker = tmp_path / "created_by_the_payload"
    torch.save({"format": "d2a-checkpoint", "payload": _Payload(str(marker))}, tmp_path / "evil.pt")
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(tmp_path / "evil.pt", "policy")
    assert not marker.exists()


def test_a_saved_checkpoint_loads_back(tmp_path):
    save_checkpoint(tmp_path / "ok.pt", "policy", {"model": {"w": torch.ones(2)}, "history": [{"step": 1}]})
    payload = load_checkpoint(tmp_path / "ok.pt", "policy")
    assert torch.equal(payload["model"]["w"], torch.ones(2)) and payload["history"] == [{"step": 1}]


@pytest.mark.parametrize("added, resumes", [(None, True), (False, True), (True, False), (0, False), ("x", False)])
def test_a_setting_added_after_the_checkpoint_resumes_only_when_off(tmp_path, added, resumes):
    """An older checkpoint lacks a newer setting: resuming is safe only if the setting is off (None/False)."""
    save_checkpoint(tmp_path / "old.pt", "policy", {"run_config": {"seed": 0}})
    expected = {"run_config": {"seed": 0, "new_setting": added}}
    if resumes:
        assert load_for_resume(tmp_path / "old.pt", "policy", expected, ("run_config",)) is not None
    else:
        with pytest.raises(CheckpointError, match="new_setting: None ->"):
            load_for_resume(tmp_path / "old.pt", "policy", expected, ("run_config",))
