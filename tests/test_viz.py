"""Pictures (`lgnn animate`, `lgnn plot`): rendered small and checked, frame count and content."""

import dataclasses

import numpy as np
import pytest
from PIL import Image

from lgnn import metrics
from lgnn.bench import viz
from lgnn.cli import main
from lgnn.engines.base import SimulationConfig
from lgnn.engines.lagrangian import simulate
from lgnn.errors import ConfigError
from lgnn.scene import get_scene


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A 0.1 s chain4 ground truth and a copy shifted by 0.3 (to tell the two apart)."""
    folder = tmp_path_factory.mktemp("viz")
    truth = simulate(get_scene("chain4"), SimulationConfig(duration=0.1))
    truth.save(folder / "truth.npz")
    dataclasses.replace(truth, q=truth.q + np.array([0.3, 0.0]), metadata={**truth.metadata, "model": {"name": "shifted"}}).save(folder / "model.npz")
    return folder / "truth.npz", folder / "model.npz"


def test_animate_writes_a_gif_with_one_frame_per_shown_time(capsys, files, tmp_path):
    """101 frames 1 ms apart at 50 fps and real time: every 20th frame, 6 in all. The
    second file's rods (matplotlib's second colour, orange) and the black pin are drawn."""
    out = tmp_path / "motion.gif"
    assert main(["animate", *map(str, files), "--out", str(out), "--fps", "50"]) == 0
    assert "6 frames" in capsys.readouterr().out
    image = Image.open(out)
    assert image.n_frames == 6
    pixels = np.asarray(image.convert("RGB"), np.int32)
    orange = np.abs(pixels - [255, 127, 14]).sum(-1) < 60
    black = pixels.sum(-1) < 60
    assert orange.sum() > 50 and black.sum() > 20


def test_mp4_without_ffmpeg_and_other_suffixes_are_one_line_errors(files, tmp_path, monkeypatch):
    from matplotlib import animation

    monkeypatch.setattr(animation.writers, "is_available", lambda name: False)
    with pytest.raises(ConfigError, match=r"needs ffmpeg.*\.gif"):
        viz.animate(files, tmp_path / "motion.mp4")
    with pytest.raises(ConfigError, match="a .gif or .mp4"):
        viz.animate(files, tmp_path / "motion.avi")
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_frames_shown_follow_fps_and_speed():
    t = np.arange(1001) * 1e-3
    assert viz.frame_indices(t, 1001, 30, 1.0)[:3].tolist() == [0, 33, 66]
    assert viz.frame_indices(t, 1001, 10, 0.01).tolist() == list(range(1001))  # slow motion: every frame


def test_plot_writes_a_figure(capsys, files, tmp_path):
    out = tmp_path / "error.png"
    assert main(["plot", *map(str, files), "--out", str(out)]) == 0
    image = Image.open(out)
    assert image.size == (600, 600)


@pytest.mark.parametrize("metric", ["node_rms_error", "rollout_error"])
def test_plot_draws_the_registered_metric_it_is_given(files, tmp_path, monkeypatch, metric):
    """`lgnn plot --metric`: the error axis is that metric's, its label the registry's;
    the model file is 0.3 m off at every node, so the RMS error is 0.3 at every frame."""
    import matplotlib.pyplot as plt

    drawn = []
    monkeypatch.setattr(plt, "close", lambda figure: drawn.append(figure))
    assert main(["plot", *map(str, files), "--out", str(tmp_path / "error.png"), "--metric", metric]) == 0
    (figure,) = drawn
    error_axes = figure.axes[0]
    title = metrics.METRICS[metric].title
    assert error_axes.get_ylabel().startswith(title[0].lower() + title[1:])
    if metric == "node_rms_error":
        np.testing.assert_allclose(error_axes.get_lines()[0].get_ydata(), 0.3, rtol=1e-9)


def test_drawing_is_planar_for_now():
    with pytest.raises(ConfigError, match="planar"):
        viz.planar(np.zeros((3, 4, 3)))
