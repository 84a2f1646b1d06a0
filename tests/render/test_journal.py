"""The render journal: every line flushed at once (a killed process keeps it), fsync'd in batches and at close."""

import json

from render2spike.render import folder


def test_lines_are_flushed_at_once_and_fsynced_in_batches(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(folder.os, "fsync", lambda fd: synced.append(fd))
    path = tmp_path / folder.JOURNAL_NAME
    j = folder.Journal(path, fsync_every_s=3600.0)
    for i in range(5):
        j.append({"tick": i, "file": f"f{i}.exr"})
        # readable by another process (resume) before any fsync: the line is in the OS, not in our buffer
        assert [json.loads(x)["tick"] for x in path.read_text().splitlines()] == list(range(i + 1))
    assert synced == [] and j.n_fsync == 0
    j.close()
    assert len(synced) == 1 and j.n_fsync == 1
    j.close()  # idempotent
    assert len(synced) == 1


def test_fsync_once_the_interval_has_passed(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(folder.os, "fsync", lambda fd: synced.append(fd))
    clock = {"t": 100.0}
    monkeypatch.setattr(folder.time, "monotonic", lambda: clock["t"])
    with folder.Journal(tmp_path / "j.jsonl", fsync_every_s=1.0) as j:
        j.append({"tick": 0})
        clock["t"] += 0.5
        j.append({"tick": 1})
        assert j.n_fsync == 0
        clock["t"] += 0.6  # 1.1 s since the journal opened
        j.append({"tick": 2})
        assert j.n_fsync == 1
        clock["t"] += 0.2
        j.append({"tick": 3})
        assert j.n_fsync == 1
    assert j.n_fsync == 2  # the last line, at close
    assert [json.loads(x)["tick"] for x in (tmp_path / "j.jsonl").read_text().splitlines()] == [0, 1, 2, 3]


def test_a_journal_closed_on_an_error_is_fsynced(tmp_path, monkeypatch):
    synced = []
    monkeypatch.setattr(folder.os, "fsync", lambda fd: synced.append(fd))
    try:
        with folder.Journal(tmp_path / "j.jsonl", fsync_every_s=3600.0) as j:
            j.append({"tick": 0})
            raise KeyboardInterrupt
    except KeyboardInterrupt:
        pass
    assert len(synced) == 1 and (tmp_path / "j.jsonl").read_text().count("\n") == 1


def test_a_line_cut_short_by_a_kill_does_not_swallow_the_next_record(tmp_path):
    """Resuming after a kill mid-line: the journal ends the cut line before appending, and reading skips it
    (and any record that names no frame file), so the frames before and after are both kept."""
    import json

    from render2spike.render.folder import JOURNAL_NAME, STATE_NAME, Journal, load_state
    (tmp_path / STATE_NAME).write_text(json.dumps({"scene_hash": "h"}))
    path = tmp_path / JOURNAL_NAME
    path.write_text(json.dumps({"tick": 0, "file": "f0.exr", "time_s": 0.0}) + "\n" + '{"tick": 1, "fi')
    j = Journal(path)
    j.append({"tick": 2, "file": "f2.exr", "time_s": 0.002})
    j.append({"tick": 3, "time_s": 0.003})  # no file: not a frame's record
    j.close()
    assert path.read_text().count("\n") == 4
    assert sorted(load_state(tmp_path)["frames"]) == ["0", "2"]
