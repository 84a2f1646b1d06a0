"""The set-up step that compiles the spike kernels runs every fast model, reset and dark mode."""

from sensor.models.precompile import precompile


def test_precompile_runs_every_kernel():
    assert precompile() == 18  # 2 resets x 2 dark modes x 3 models, then 3 inputs x 2 outputs
