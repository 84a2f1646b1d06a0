"""A render that fails in a folder it made cleans the folder up while it still holds the folder lock."""

import pytest

from render2spike.render import folder as fmod
from sensor.io import lock as lmod


def test_failure_clean_up_runs_before_the_lock_is_released(tmp_path, monkeypatch):
    out = tmp_path / "frames"
    seen = []
    release = lmod.FolderLock.release

    def spy(self):
        if self.held:  # what the folder still holds when the lock goes
            seen.append(sorted(p.name for p in out.iterdir() if p.name != lmod.LOCK_NAME))
        release(self)
    monkeypatch.setattr(lmod.FolderLock, "release", spy)
    with pytest.raises(RuntimeError, match="boom"):
        with fmod.FramesFolder.locked(out, log=lambda *a: None):
            (out / fmod.STATE_NAME).write_text("{}")
            (out / fmod.JOURNAL_NAME).write_text("")
            raise RuntimeError("boom")
    assert seen == [[]]  # state and journal were gone before the lock was released
    assert not out.exists()  # and the folder it made is removed


def test_a_folder_that_existed_is_kept_and_unlocked(tmp_path):
    out = tmp_path / "frames"
    out.mkdir()
    with pytest.raises(RuntimeError):
        with fmod.FramesFolder.locked(out, log=lambda *a: None):
            raise RuntimeError("boom")
    assert out.is_dir() and not (out / lmod.LOCK_NAME).exists()
