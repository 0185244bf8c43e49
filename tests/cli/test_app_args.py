"""``dvr-perception app [VOLUME] [--data-dir DIR]``: which folder and file name the app opens."""

from __future__ import annotations

import argparse

import pytest

from dvr_perception.cli.app import _resolve
from dvr_perception.errors import DVRInputError


def _args(volume, data_dir=None):
    return argparse.Namespace(volume=volume, data_dir=None if data_dir is None else str(data_dir))


@pytest.fixture
def data(tmp_path):
    folder = tmp_path / "data"
    (folder / "sub").mkdir(parents=True)
    (folder / "a.nhdr").write_text("x", encoding="utf-8")
    (folder / "sub" / "b.nrrd").write_text("x", encoding="utf-8")
    (tmp_path / "elsewhere.nhdr").write_text("x", encoding="utf-8")
    return folder


def test_a_name_in_the_data_folder(data):
    assert _resolve(_args("a.nhdr", data)) == (data, "a.nhdr")
    assert _resolve(_args("sub/b.nrrd", data)) == (data, "sub/b.nrrd")


def test_a_path_to_a_file_in_the_data_folder_becomes_its_name(data, monkeypatch):
    # the README's way: the file's path, and the folder it is in as --data-dir
    assert _resolve(_args(str(data / "a.nhdr"), data)) == (data, "a.nhdr")
    assert _resolve(_args(str(data / "sub" / "b.nrrd"), data)) == (data, "sub/b.nrrd")
    monkeypatch.chdir(data.parent)
    assert _resolve(_args("data/a.nhdr", "data")) == (data.relative_to(data.parent), "a.nhdr")


def test_a_file_outside_the_data_folder_is_one_error(data):
    with pytest.raises(DVRInputError, match=r"elsewhere\.nhdr: not inside --data-dir"):
        _resolve(_args(str(data.parent / "elsewhere.nhdr"), data))
    with pytest.raises(DVRInputError, match=r"c\.nhdr: no such file in --data-dir"):
        _resolve(_args("c.nhdr", data))


def test_without_a_data_folder_the_file_s_folder_is_it(data):
    assert _resolve(_args(str(data / "a.nhdr"))) == (data, "a.nhdr")
    with pytest.raises(DVRInputError, match="no such volume file"):
        _resolve(_args(str(data / "missing.nhdr")))
