"""The package as installed: every package folder listed in pyproject, bundled scenes shipped, API exported, help."""

import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_every_package_folder_is_listed_in_pyproject():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    on_disk = {".".join(p.parent.relative_to(ROOT).parts) for top in ("render2spike", "sensor", "recon")
               for p in (ROOT / top).rglob("__init__.py")}
    assert on_disk <= listed, f"add to [tool.setuptools] packages: {sorted(on_disk - listed)}"
    # the bundled scenes are the package data of render2spike.scenes, taken from the top-level scenes/
    assert cfg["package-dir"]["render2spike.scenes"] == "scenes"
    data = cfg["package-data"]["render2spike.scenes"]
    assert all(any(Path(f).match(pat) for pat in data) for f in (ROOT / "scenes").iterdir() if f.is_file())


def test_bundled_scenes_resolve_by_name():
    import render2spike
    from render2spike.render.scene import resolve_scene_path
    names = render2spike.bundled_scenes()
    assert {"rotating_disk", "lambertian_plane"} <= set(names)
    assert resolve_scene_path("rotating_disk").name == "rotating_disk.yaml"


def test_python_api_is_exported_lazily():
    import subprocess
    import sys
    code = ("import sys, render2spike as r; assert 'mitsuba' not in sys.modules; "
            "fns = [r.load_scene, r.render_scene, r.run_pipeline, r.simulate_frames, r.SceneRenderer, r.Scene]; "
            "assert all(callable(f) for f in fns); print(sorted(r.__all__))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=str(ROOT),
                         env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"})
    assert res.returncode == 0, res.stderr
    with pytest.raises(AttributeError):
        import render2spike
        render2spike.no_such_thing  # noqa: B018


def test_top_level_help_lists_every_command(capsys):
    from render2spike.cli import build_parser
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    text = parser.format_help()
    for name, p in sub.choices.items():
        assert f"\n  {name} " in text, name  # one line per registered command
        h = p.format_help()
        assert "examples:" in h, f"`{name} --help` has no examples"
        assert "(default: None)" not in h and "(default: False)" not in h, name
