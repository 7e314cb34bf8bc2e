"""The shipped head is package data, found in one place by every command."""

from __future__ import annotations

import shutil
from pathlib import Path

import fae
from fae.cli import main
from fae.data import shipped_head_path

STREAM = Path(__file__).resolve().parents[1] / "fap_streams" / "expressions.fap"


def test_the_shipped_head_lies_inside_the_package():
    path = shipped_head_path()
    assert path.is_file() and path.name == "generic_head.glb"
    assert path.is_relative_to(Path(fae.__file__).parent / "data")


def test_fae_templates_names_the_folder_of_another_default_head(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("FAE_TEMPLATES", str(tmp_path))
    assert shipped_head_path() == tmp_path / "generic_head.glb"
    # Every command that falls back on the shipped head looks there, and says so when it is missing.
    for command in (["render", "-o", str(tmp_path / "a.png")], ["verify-faps"],
                    ["serve", "--port", "0"], ["play", str(STREAM), "-o", str(tmp_path / "a.mp4")]):
        assert main(command) == 2, command
        err = capsys.readouterr().err
        assert str(tmp_path / "generic_head.glb") in err and "FAE_TEMPLATES" in err, (command, err)
    shutil.copy(Path(fae.__file__).parent / "data" / "generic_head.glb", tmp_path)
    assert main(["template", "check", str(shipped_head_path())]) == 0
