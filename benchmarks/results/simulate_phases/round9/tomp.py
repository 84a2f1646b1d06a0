import sys, shutil; sys.path.insert(0, "/work/main")
from pathlib import Path
from sensor.frames import read_frames, write_frame, read_frame
src, dst = Path(sys.argv[1]), Path(sys.argv[2]); dst.mkdir(exist_ok=True)
seq = read_frames(src)
for i, e in enumerate(seq.manifest["frames"]):
    fr = read_frame(src / e["file"])
    attrs = {k: v for k, v in fr.header.items() if k not in ("time_s", "units")}
    write_frame(dst / e["file"], fr.phi, fr.illuminance_lux, time_s=fr.time_s, attrs=attrs)
shutil.copy(src / "frames.json", dst / "frames.json")
print("done", i)
