"""bubble_rt.commands.recover: `bubble-rt recover` rewrites a killed recording as a finalised file."""

from __future__ import annotations

import warnings

import pytest
from bubble_rt.io.mcap import McapRecording
from recording_fakes import killed_recording

pytestmark = pytest.mark.timeout(120)


def test_recover_command_rewrites_a_killed_recording_as_a_finalised_file(tmp_path, capsys):
    from bubble_rt.cli import main
    from mcap.reader import make_reader

    p = tmp_path / "crash.mcap"
    killed_recording(p, frames=12)
    out = tmp_path / "fixed.mcap"
    assert main(["recover", str(p), "-o", str(out)]) == 0
    text = capsys.readouterr().out
    assert "was not closed" in text and f"to {out}" in text
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        n = sum(1 for _ in reader.iter_messages())
    assert n == summary.statistics.message_count >= 36
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a recovered file reads without any warning
        rec = McapRecording(out)
    assert rec.report.complete and len(rec) >= 12 and rec.frames_indexed == len(rec)
    # The output is never overwritten silently.
    assert main(["recover", str(p), "-o", str(out)]) == 1
    assert "file exists" in capsys.readouterr().err
