"""pip's cv2 (OpenCV 5, bundled libraries) and the extension linked against Debian's
OpenCV 4.6 must load and run in one process, in either import order."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

SCRIPT = """
import numpy as np
{first}
{second}
rng = np.random.default_rng(0)
img = cv2.GaussianBlur(rng.integers(0, 255, (120, 160), dtype=np.uint8), (0, 0), 2.0)
img = cv2.normalize(img, None, 0, 255, cv2.NORM_MINMAX)
shifted = np.roll(img, 2, axis=1)
pip_flow = cv2.DISOpticalFlow_create(2).calc(img, shifted, None)
rgb0 = np.ascontiguousarray(np.dstack([img] * 3))
rgb1 = np.ascontiguousarray(np.dstack([shifted] * 3))
of = _core._PixelTracker(method=1, dis_preset=2, pyr_scale=0.5, levels=3, winsize=15,
                        iterations=3, poly_n=5, poly_sigma=1.2, gaussian=False, scale=1.0,
                        forward_backward=False)
of.set_reference(rgb0, 0, 0, 160, 120)
of.compute(rgb1)
ours = of.sample(np.array([[80.0, 60.0]]), 1.0)[0][0]
print(cv2.__version__, float(np.median(pip_flow[40:80, 40:120, 0])), float(ours[0]))
"""


def run(first: str, second: str) -> list[str]:
    import bubble_rt

    # The bubble_rt this test process uses (source tree or installed), for the child too.
    package_parent = Path(bubble_rt.__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(package_parent), OPENBLAS_NUM_THREADS="1")
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT.format(first=first, second=second)],
        capture_output=True,
        text=True,
        env=env,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def check(fields: list[str]) -> None:
    version, pip_dx, our_dx = fields
    assert not version.startswith("4.6")  # really the pip build, not Debian's
    assert abs(float(pip_dx) - 2.0) < 0.2
    assert abs(float(our_dx) - 2.0) < 0.2


def test_pip_cv2_first_then_extension():
    check(run("import cv2", "from bubble_rt import _core"))


def test_extension_first_then_pip_cv2():
    check(run("from bubble_rt import _core", "import cv2"))
