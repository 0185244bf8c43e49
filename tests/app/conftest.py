"""Shared fixtures of the app tests."""

from __future__ import annotations

import pytest

from dvr_perception.app.session import PHANTOM, Session


@pytest.fixture
def session(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    s = Session(data, tmp_path / "exports", phantom_size=40)
    s.load_volume(PHANTOM)
    return s
