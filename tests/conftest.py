"""Shared test set-up. Helpers live once each in the helper modules beside the tests, which
import them by name (this folder is put on ``sys.path`` here, whatever pytest's import mode);
no test module imports another test module.

- ``waiting``: :func:`waiting.wait_for` (wait on state, never sleep), ``ANY_PORT`` and
  ``ServedProcess`` (a daemon subprocess bound to any free port, its endpoints read back);
- ``daemon_fakes``: a scripted camera, a fake processor and sensor, ``fake_config``, ``start``
  (a ready daemon on them; the ``daemon`` fixture here wraps it) and ``status_of``;
- ``recording_fakes``: small Punyo and PNG recordings;
- ``synth_rgbd``: synthetic textures, flows and dome depths;
- ``sim_recordings``: simulated presses written as recordings;
- ``_sim_fake``: a fast fake of the simulator's physics backend.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

_HERE = str(Path(__file__).resolve().parent)
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)


@pytest.fixture
def daemon():  # type: ignore[no-untyped-def]
    """A running daemon on the fakes (``daemon_fakes.start``) and its camera; stopped after."""
    from daemon_fakes import start

    d, cam = start()
    yield d, cam
    d.stop()
