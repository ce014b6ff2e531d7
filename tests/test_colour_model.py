"""bench/colour_model.py: the pixels it selects (HSV range, intensity ceiling, mask) and their (r, g, I)
statistics; a bad selection is refused with one line and a non-zero exit."""

import importlib.util
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from artrack.colour_model import colour_features

BENCH = Path(__file__).resolve().parents[1] / "bench" / "colour_model.py"


@pytest.fixture(scope="module")
def colour_model():
    spec = importlib.util.spec_from_file_location("bench_colour_model", BENCH)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _scene():
    """(40, 60) BGR: a grey room, a cyan patch (the cap) and a near-black patch (the shorts) in it,
    and a near-black stripe of the room (a treadmill) that a foreground mask leaves out."""
    rng = np.random.default_rng(0)
    img = np.full((40, 60, 3), 150, np.uint8)
    img[5:15, 5:15] = (200, 180, 30)  # BGR cyan
    img[20:30, 20:40] = np.clip(rng.normal((20, 35, 40), 3, (10, 20, 3)), 0, 255).astype(np.uint8)
    img[32:38, :] = 15  # dark room: excluded by the mask
    mask = np.zeros((40, 60), bool)
    mask[0:31, :] = True
    return img, mask


def test_dark_pixels_in_the_foreground_give_the_shorts_statistics(colour_model):
    img, mask = _scene()
    keep = colour_model.select_pixels(img, max_intensity=0.2, mask=mask)
    assert keep.sum() == 200 and keep[20:30, 20:40].all()  # the patch, not the dark stripe
    samples = colour_model.colour_samples([{"cam01": img}, {"cam01": img}], max_intensity=0.2,
                                          masks=[{"cam01": mask}] * 2)
    assert samples["cam01"].shape == (400, 3)
    np.testing.assert_allclose(samples["cam01"].mean(0), colour_features(img[20:30, 20:40]).reshape(-1, 3).mean(0),
                               atol=1e-6)
    without_mask = colour_model.colour_samples([{"cam01": img}], max_intensity=0.2)
    assert without_mask["cam01"].shape == (200 + 6 * 60, 3)  # the dark room is taken in too


def test_hsv_range_selects_the_cap(colour_model):
    img, _ = _scene()
    keep = colour_model.select_pixels(img, hsv=[84, 120, 60, 100, 255, 255])
    assert keep.sum() == 100 and keep[5:15, 5:15].all()
    f = colour_model.colour_samples([{"cam02": img}], hsv=[84, 120, 60, 100, 255, 255])["cam02"]
    np.testing.assert_allclose(f.mean(0), colour_features(np.array([200, 180, 30], np.uint8)), atol=1e-6)


@pytest.mark.parametrize("args, message", [
    (["--hsv", "84,120"], "--hsv '84,120': expected 6 integers"),
    ([], "give --hsv, --max-intensity or both"),
    (["--max-intensity", "0.2", "--first", "5", "--last", "2"], "need 0 <= first <= last"),
])
def test_bad_selection_is_one_line_and_exit_1(args, message):
    out = subprocess.run([sys.executable, str(BENCH), *args], capture_output=True, text=True, timeout=120)
    assert out.returncode == 1
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("colour_model: ") and message in lines[0]
