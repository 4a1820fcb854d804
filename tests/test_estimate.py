"""`bubble-rt estimate` command."""

from __future__ import annotations

import pytest
from bubble_rt.commands.estimate import parse_frames


def test_parse_frames_ranges_and_lists():
    assert parse_frames("0-4", 20) == [0, 1, 2, 3, 4]
    assert parse_frames("3", 20) == [3]
    assert parse_frames("0-1, 5,7-8", 20) == [0, 1, 5, 7, 8]


def test_parse_frames_errors():
    with pytest.raises(ValueError, match="out of range"):
        parse_frames("18-20", 20)
    with pytest.raises(ValueError, match="empty frame range"):
        parse_frames("4-2", 20)
    with pytest.raises(ValueError, match="no frames"):
        parse_frames(" , ", 20)
