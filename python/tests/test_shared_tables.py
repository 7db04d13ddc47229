"""Tables Python shares with the Rust side come from one source: the QAT slot table from `muir info
--json` (never from a Markdown report; a wrong file is a ValueError naming it), and the presets
checked against the fixture the Rust tests read."""
from __future__ import annotations

import json
import os

import pytest

from muir import qat

REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "../.."))


def test_shipped_formats_give_every_simulated_slot():
    u8 = qat.read_report_formats(os.path.join(REPO, "models", "muir-slim.formats.json"))
    wide = qat.read_report_formats(os.path.join(REPO, "models", "muir-slim-wide.formats.json"))
    assert set(u8) == set(wide) == set(qat.ENCODER_SLOT_NAMES)
    # the trunk is u8 in one blob, i16 in the other; the feature head is the same
    assert u8["c1"][0] == 8 and wide["c1"][0] == 16
    assert u8["fmap"][0] == wide["fmap"][0] == 8
    storage = qat.encoder_storage()
    assert storage["c1"] == (8, True) and storage["fmap"] == (8, False) and storage["fmap_raw1"] == (16, False)
    aq = qat.ActQuant(qat.read_report(os.path.join(REPO, "models", "muir-slim.formats.json")))
    assert aq.grid["c1"][1:] == (0, 255) and aq.grid["fmap"][1:] == (-128, 127)


def test_wrong_files_are_named(tmp_path):
    md = os.path.join(REPO, "models", "muir-slim.calib.md")
    with pytest.raises(ValueError, match="muir-slim.calib.md"):
        qat.read_formats(md)
    j = json.load(open(os.path.join(REPO, "models", "muir-slim.formats.json")))
    j["slots"] = [s for s in j["slots"] if s["name"] != "fmap"]
    short = tmp_path / "short.json"
    short.write_text(json.dumps(j))
    with pytest.raises(ValueError, match="short.json.*fmap"):
        qat.read_formats(str(short))
    other = tmp_path / "float.json"
    other.write_text(json.dumps({"kind": "safetensors"}))
    with pytest.raises(ValueError, match="float.json"):
        qat.read_formats(str(other))


def test_presets_fixture_is_what_config_py_writes():
    """host-tests/model_files.rs checks host-tests/fixtures/python-presets.json against the Rust
    presets; this closes the chain: the fixture is what python/muir/config.py writes today."""
    from muir import config

    fixture = json.load(open(os.path.join(REPO, "host-tests", "fixtures", "python-presets.json")))
    assert set(fixture) == set(config.PRESETS)
    for name, c in config.PRESETS.items():
        assert json.loads(c.to_json()) == fixture[name], f"{name}: regenerate host-tests/fixtures/python-presets.json"
