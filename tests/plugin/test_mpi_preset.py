"""``pvbatch --ranks N`` reads no whole volume: its spec is ``--structures`` or ``--preset``."""

from __future__ import annotations

import json

from dvr_perception.cli import main
from dvr_perception.structures.presets import presets_dir


def test_ranks_take_a_preset_by_name_and_refuse_to_guess(mpiexec, shared_data, tmp_path, capsys):
    volume = shared_data / "fuel.nhdr"
    out = tmp_path / "out"
    argv = ["pvbatch", str(volume), "--preset", "fuel", "--size", "24", "--no-screenshot"]
    assert main([*argv, "--ranks", "2", "--timeout", "300", "--out", str(out)]) == 0
    got = json.loads((out / "result.json").read_text(encoding="utf-8"))
    assert got["spec"] == str(presets_dir() / "fuel.json")
    assert len(got["ranks"]) == 2
    capsys.readouterr()
    argv = ["pvbatch", str(volume), "--size", "24", "--ranks", "2", "--timeout", "300"]
    assert main([*argv, "--out", str(tmp_path / "none")]) == 2
    err = capsys.readouterr().err
    assert "--ranks 2: needs --structures or --preset NAME" in err
    assert not (tmp_path / "none" / "result.json").exists()
