"""`render2spike simulate`'s start-up: no cyclic collection while it starts, what it made frozen out of the
run's collections (gc.freeze), and the collector given back as it was when the command ends. Run in child
processes: freezing is process-wide."""

import json
import subprocess
import sys

import numpy as np

CODE = """
import gc, json
from render2spike.commands.simulate import _start_up
gc.enable()
old = [[-1]]  # made before the start-up
frozen = {}
with _start_up(frozen):
    inside = gc.isenabled()
    marker = [[0]]  # made while starting
tracked = {id(o) for o in gc.get_objects()}  # the collector's generations (not the frozen objects)
res = {"inside": inside, "enabled": gc.isenabled(), "flag": frozen.get("frozen", False),
       "marker_frozen": id(marker) not in tracked, "old_frozen": id(old) not in tracked}
gc.unfreeze()
res["marker_back"] = id(marker) in {id(o) for o in gc.get_objects()}
gc.disable()  # a collector that was off: nothing frozen, and it stays off
f2 = {}
with _start_up(f2):
    pass
res["off"] = [gc.isenabled(), f2.get("frozen", False), gc.get_freeze_count()]
gc.enable()
gc.freeze()  # the process froze objects itself: left alone
n = gc.get_freeze_count()
f3 = {}
with _start_up(f3):
    x = [[1]]
res["own"] = [f3.get("frozen", False), gc.get_freeze_count() == n]
print(json.dumps(res))
"""


def _child(code):
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_start_up_collects_nothing_then_freezes_what_it_made_and_leaves_other_freezes_alone():
    r = _child(CODE)
    assert r["inside"] is False  # off while starting
    assert r["enabled"] is True and r["flag"] is True  # back on for the run, with the start-up frozen
    assert r["marker_frozen"] is True and r["old_frozen"] is True  # frozen at the end, not at the start
    assert r["marker_back"] is True  # unfreeze gives them back to the collector
    assert r["off"] == [False, False, 0]
    assert r["own"] == [False, True]


def test_the_command_in_process_gives_the_collector_back(tmp_path):
    np.save(tmp_path / "rate.npy", np.full((40, 8, 8), 3.0, np.float32))
    code = (f"import gc, json; from render2spike.cli import main; gc.enable(); "
            f"rc = main(['simulate', {str(tmp_path / 'rate.npy')!r}, '--out', {str(tmp_path / 's.npz')!r}, "
            f"'--quiet']); print(json.dumps([rc, gc.get_freeze_count(), gc.isenabled()]))")
    assert _child(code) == [0, 0, True]
