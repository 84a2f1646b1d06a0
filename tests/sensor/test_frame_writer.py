"""write_frame's own EXR encoder: the same file as the OpenEXR binding writes, byte for byte and attribute by attribute."""

from pathlib import Path

import numpy as np
import pytest

from sensor.io import exr as F
from sensor.io.frames import read_frame, read_phi, write_frame

OpenEXR = pytest.importorskip("OpenEXR")

ATTRS = {"spp": 16, "ok": True, "no": False, "render_noise_ratio": 0.2071, "nan_ratio": float("nan"),
         "variant": "llvm_ad_spectral", "seeds": [12, 34], "made_by": '{"stage": "render"}', "np_int": np.int64(-7),
         "np_float": np.float32(1.5), "a_long_attribute_name_of_more_than_31_bytes": "x" * 5000,
         "unicode_é": "Phi ≥ 0 [e-/(s m²)]", "empty": ""}


def _binding_file(path, phi, E, time_s, attrs):
    """The same frame written through the OpenEXR binding (write_frame's fallback, the writer used before)."""
    header = {"time_s": ("double", float(time_s)), "units": ("string", F.UNITS_STRING)}
    header.update((k, F._attr_kind(v)) for k, v in attrs.items())
    F._write_frame_openexr(path, np.ascontiguousarray(phi, np.float32), np.ascontiguousarray(E, np.float32), header)


def _headers(path):
    with OpenEXR.File(str(path)) as f:
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in f.header().items()}


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (7, 1), (3, 5), (250, 400)])
def test_encoder_writes_the_bindings_file_and_reads_back_bit_exactly(tmp_path, shape):
    rng = np.random.default_rng(sum(shape))
    phi = rng.uniform(0, 1e12, shape).astype(np.float32)
    E = rng.uniform(0, 50, shape).astype(np.float32)
    special = np.array([np.nan, np.inf, -np.inf, -0.0, 1e-45, -3.0], np.float32)  # non-finite, -0, denormal
    phi.flat[:min(phi.size, special.size)] = special[:phi.size]
    E.flat[-min(E.size, 2):] = np.array([np.inf, np.nan], np.float32)[:E.size]
    new, old = tmp_path / "new.exr", tmp_path / "old.exr"
    assert F._encode_exr({"E": E, "Phi": phi}, {"time_s": ("double", 0.0123)}) is not None  # not the fallback
    write_frame(new, phi, E, time_s=0.0123, attrs=ATTRS)
    _binding_file(old, phi, E, 0.0123, ATTRS)
    assert new.read_bytes() == old.read_bytes()
    h_new, h_old = _headers(new), _headers(old)
    assert list(h_new) == list(h_old)
    for key in h_old:  # attribute by attribute (nan compares unequal: compare the reprs)
        assert repr(h_new[key]) == repr(h_old[key]), key
    assert h_new["compression"] == OpenEXR.NO_COMPRESSION and h_new["type"] == OpenEXR.scanlineimage
    fr = read_frame(new)
    assert fr.time_s == 0.0123 and fr.phi.shape == shape
    np.testing.assert_array_equal(fr.phi.view(np.uint32), phi.view(np.uint32))  # bit-exact, nan payloads too
    np.testing.assert_array_equal(fr.illuminance_lux.view(np.uint32), E.view(np.uint32))
    assert fr.header["spp"] == 16 and fr.header["ok"] == "true" and fr.header["no"] == "false"
    assert fr.header["seeds"] == "[12, 34]" and fr.header["np_int"] == -7 and fr.header["np_float"] == 1.5
    assert fr.header["a_long_attribute_name_of_more_than_31_bytes"] == "x" * 5000
    assert fr.header["unicode_é"] == "Phi ≥ 0 [e-/(s m²)]" and np.isnan(fr.header["nan_ratio"])
    t, phi2 = read_phi(new)
    assert t == 0.0123
    np.testing.assert_array_equal(phi2.view(np.uint32), phi.view(np.uint32))
    assert F._exr_channel_fast(new.read_bytes(), "Phi") is not None  # the simulator's fast reader takes it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["new.exr", "old.exr"]  # no temp file left


def test_short_names_keep_the_plain_version_field(tmp_path):
    write_frame(tmp_path / "a.exr", np.ones((2, 3)), time_s=1.0, attrs={"spp": 4})
    data = (tmp_path / "a.exr").read_bytes()
    assert data[4:8] == bytes([2, 0, 0, 0])  # single-part scanline, no long-names flag
    _binding_file(tmp_path / "b.exr", np.ones((2, 3)), np.zeros((2, 3)), 1.0, {"spp": 4})
    assert data == (tmp_path / "b.exr").read_bytes()


@pytest.mark.parametrize("attrs", [{"n" * 300: "name longer than 255 bytes"}, {"big": 2 ** 40}, {"s": "a\0b"},
                                   {"type": "tiledimage"}, {"channels": "x"}, {"": "empty name"}])
def test_what_the_encoder_does_not_express_goes_through_the_binding(tmp_path, monkeypatch, attrs):
    header = {k: F._attr_kind(v) for k, v in attrs.items()}
    assert F._encode_exr({"E": np.zeros((2, 2), np.float32), "Phi": np.ones((2, 2), np.float32)}, header) is None
    calls = []
    real = F._write_frame_openexr

    def spy(*a):
        calls.append(a[0])
        return real(*a)
    monkeypatch.setattr(F, "_write_frame_openexr", spy)
    try:
        write_frame(tmp_path / "f.exr", np.ones((2, 2)), time_s=0.5, attrs=attrs)
    except Exception:  # the binding may refuse what it cannot write; then nothing is left behind
        assert not list(tmp_path.iterdir())
    else:
        assert read_frame(tmp_path / "f.exr").time_s == 0.5
    assert len(calls) == 1


def test_shape_errors_before_anything_is_written(tmp_path):
    with pytest.raises(F.FrameFileError, match="2-D"):
        write_frame(tmp_path / "a.exr", np.ones(3), time_s=0.0)
    with pytest.raises(F.FrameFileError, match="E shape"):
        write_frame(tmp_path / "a.exr", np.ones((2, 2)), np.ones((2, 3)), time_s=0.0)
    assert not list(tmp_path.iterdir())


# ------------------------------------------------------------------ write_bytes_atomic (the frames' file writer)
def test_write_bytes_atomic_names_permissions_and_sweep_pattern(tmp_path, monkeypatch):
    import os
    import re

    from sensor.io import fileio
    from sensor.io.lock import _PART_RE
    made = []
    real_open = os.open

    def spy(p, *a, **k):
        made.append(Path(p).name)
        return real_open(p, *a, **k)
    monkeypatch.setattr(fileio.os, "open", spy)
    out = fileio.write_bytes_atomic(tmp_path / "sub" / "f.exr", np.arange(5, dtype=np.uint8))  # folder made
    assert out.read_bytes() == bytes(range(5))
    umask = os.umask(0)
    os.umask(umask)
    assert out.stat().st_mode & 0o777 == 0o666 & ~umask  # what atomic_path gives
    assert re.fullmatch(rf"\.f\.part-{os.getpid()}-\d+\.exr", made[-1]) and _PART_RE.match(made[-1])
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["f.exr"] and not fileio._LIVE_TEMPS


def test_write_bytes_atomic_skips_a_taken_temp_name(tmp_path, monkeypatch):
    import os

    from sensor.io import fileio
    n = next(fileio._TMP_NUMBERS) + 1
    stale = tmp_path / f".f.part-{os.getpid()}-{n}.exr"  # a dead process of the same pid left this
    stale.write_bytes(b"old")
    fileio.write_bytes_atomic(tmp_path / "f.exr", b"new")
    assert (tmp_path / "f.exr").read_bytes() == b"new" and stale.read_bytes() == b"old"


def test_write_bytes_atomic_failure_leaves_nothing_and_disk_full_names_the_file(tmp_path, monkeypatch):
    import errno

    from sensor.io import fileio
    from sensor.errors import DiskFullError
    (tmp_path / "f.exr").write_bytes(b"previous")

    def full(fd, data):
        raise OSError(errno.ENOSPC, "No space left on device")
    monkeypatch.setattr(fileio.os, "write", full)
    with pytest.raises(DiskFullError, match=r"disk full while writing .*f\.exr"):
        write_frame(tmp_path / "f.exr", np.ones((4, 4)), time_s=0.0)
    assert [p.name for p in tmp_path.iterdir()] == ["f.exr"] and (tmp_path / "f.exr").read_bytes() == b"previous"
    assert not fileio._LIVE_TEMPS
    monkeypatch.undo()

    def boom(src, dst):
        raise KeyboardInterrupt
    monkeypatch.setattr(fileio.os, "replace", boom)
    with pytest.raises(KeyboardInterrupt):
        fileio.write_bytes_atomic(tmp_path / "g.exr", b"x" * 100)
    assert [p.name for p in tmp_path.iterdir()] == ["f.exr"] and not fileio._LIVE_TEMPS


def test_the_encoders_reused_header_pieces_give_each_frame_its_own_bytes(tmp_path):
    # a render's frames share most attributes and differ in time, ratio and seeds (strings of other lengths):
    # every frame, encoded after others filled the caches, is the binding's file of that frame
    rng = np.random.default_rng(3)
    frames = [(0.0, float("nan"), [4294967295, 1]), (0.0005, 0.2071, [12, 3456789]), (0.001, float("nan"), [7, 8]),
              (0.0015, 0.19, [4294967295, 1])]
    for _ in range(2):  # the second pass only hits the caches
        for i, (t, ratio, seeds) in enumerate(frames):
            attrs = {**ATTRS, "render_noise_ratio": ratio, "seeds": seeds}
            phi = rng.uniform(0, 1e12, (4, 6)).astype(np.float32)
            E = rng.uniform(0, 5, (4, 6)).astype(np.float32)
            write_frame(tmp_path / "new.exr", phi, E, time_s=t, attrs=attrs)
            _binding_file(tmp_path / "old.exr", phi, E, t, attrs)
            assert (tmp_path / "new.exr").read_bytes() == (tmp_path / "old.exr").read_bytes(), (i, t)
    # a result left to the binding is left to it again (the refusal is remembered, not the bytes)
    header = {"type": ("string", "tiledimage")}
    ch = {"E": np.zeros((2, 2), np.float32), "Phi": np.ones((2, 2), np.float32)}
    assert F._encode_exr(ch, header) is None and F._encode_exr(ch, header) is None
    assert F._encode_exr(ch, {"big": ("int", 2 ** 40)}) is None and F._encode_exr(ch, {"big": ("int", 2 ** 40)}) is None
    # the cache keys on the value's type: an int's bytes are never handed to an equal float (1.0 == 1)
    assert F._exr_attr_chunk("n", "int", 1) is not None
    with pytest.raises(Exception):
        F._exr_attr_chunk("n", "int", 1.0)  # struct refuses a float for an int, as it did before the cache
    # long strings are encoded every time, not kept
    F._encode_exr(ch, {"note": ("string", "y" * 5000)})
    assert not any(isinstance(k[3], str) and len(k[3]) > 256 for k in F._ATTR_CHUNKS)


def test_write_bytes_atomic_takes_a_trailing_separator_as_pathlib_does(tmp_path):
    import os

    from sensor.io import fileio
    out = fileio.write_bytes_atomic(str(tmp_path / "f.exr") + os.sep, b"abc")
    assert out == tmp_path / "f.exr" and (tmp_path / "f.exr").read_bytes() == b"abc"
    assert [p.name for p in tmp_path.iterdir()] == ["f.exr"] and not fileio._LIVE_TEMPS


def test_write_bytes_atomic_interrupted_right_after_creating_the_temp_file_leaves_it_findable(tmp_path, monkeypatch):
    import os

    from sensor.io import fileio
    real_open = os.open

    def open_then_interrupt(*a, **k):
        fd = real_open(*a, **k)
        os.close(fd)
        raise KeyboardInterrupt  # a signal's exception lands after the file was made
    monkeypatch.setattr(fileio.os, "open", open_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        fileio.write_bytes_atomic(tmp_path / "f.exr", b"abc")
    monkeypatch.undo()
    left = list(tmp_path.iterdir())
    assert len(left) == 1 and left[0].name.startswith(".f.part-")
    assert fileio.remove_live_temps() == [left[0]] and not list(tmp_path.iterdir())
