import sys, json, shutil
sys.path.insert(0, "/work/main")
from pathlib import Path
import numpy as np
from sensor.frames import _encode_exr, read_frames, UNITS_STRING
from sensor.fileio import write_bytes_atomic
src, dst = Path(sys.argv[1]), Path(sys.argv[2]); dst.mkdir(exist_ok=True)
seq = read_frames(src)
for i, e in enumerate(seq.manifest["frames"]):
    import OpenEXR
    with OpenEXR.File(str(src / e["file"])) as f:
        phi = np.ascontiguousarray(f.channels()["Phi"].pixels, np.float32)
    buf = _encode_exr({"Phi": phi}, {"time_s": ("double", float(e["time_s"])), "units": ("string", UNITS_STRING)})
    write_bytes_atomic(dst / e["file"], buf)
shutil.copy(src / "manifest.json", dst / "manifest.json")
print("done", i)
