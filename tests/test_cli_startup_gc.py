"""`render2spike simulate`'s start-up: no cyclic collection while it starts, and what it made is frozen
out of the run's collections (gc.freeze). Run in a child process: freezing is process-wide."""

import subprocess
import sys

CODE = """
import gc, json
from render2spike.commands.simulate import _start_up
before = gc.get_freeze_count()
gc.enable()
with _start_up():
    inside = gc.isenabled()
    made = [[i] for i in range(5000)]  # 5001 container objects made while starting
after_enabled, frozen = gc.isenabled(), gc.get_freeze_count() - before
gc.disable()
with _start_up():
    pass
print(json.dumps([inside, after_enabled, frozen, gc.isenabled()]))
"""


def test_start_up_collects_nothing_then_freezes_what_it_made_and_restores_the_collector():
    out = subprocess.run([sys.executable, "-c", CODE], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    import json
    inside, after_enabled, frozen, stays_disabled = json.loads(out.stdout)
    assert inside is False  # off while starting
    assert after_enabled is True  # back on for the run
    assert frozen >= 5001  # the start-up's objects are out of the run's collections
    assert stays_disabled is False  # a collector that was off stays off
