"""Hostile ParaView preset files (issue 11, item 10): JSON nested 100,000 deep, text that made the comment
stripper take quadratic time, XML entity bombs. Each is refused with one line, quickly, by
``read_presets`` (the viewer's listing and uploads) and by ``apmgsrn render --colormap``."""

from __future__ import annotations

import threading

import pytest

from apmgsrn.cli.main import main
from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.paraview import parse_presets, read_presets

DEEP = "[" * 100_000 + "]" * 100_000


def _refused_within(seconds: float, function, *args) -> str:
    """The ApmgsrnError message of ``function(*args)``; fails (instead of hanging) if it runs past ``seconds``."""
    outcome = {}

    def call():
        try:
            function(*args)
            outcome["error"] = None
        except ApmgsrnError as exc:
            outcome["error"] = str(exc)

    worker = threading.Thread(target=call, daemon=True)
    worker.start()
    worker.join(seconds)
    assert not worker.is_alive(), f"still parsing after {seconds} s"
    assert outcome["error"] is not None, "accepted"
    return outcome["error"]


def test_deeply_nested_json_is_refused(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text(DEEP, encoding="utf-8")
    assert "nested too deeply" in _refused_within(60, read_presets, path)
    assert "nested too deeply" in _refused_within(60, parse_presets, DEEP, "upload.json")


def test_render_refuses_a_deep_preset_in_one_line(tmp_path, test_data, capsys):
    path = tmp_path / "deep.json"
    path.write_text(DEEP, encoding="utf-8")
    out = tmp_path / "image.png"
    code = main(["render", str(test_data / "neghip_32x32x32_uint8.npy"), "--out", str(out), "--colormap", str(path),
                 "--width", "16", "--height", "16"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith("error: ") and "nested too deeply" in err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


@pytest.mark.parametrize(
    "unit",
    [
        "/* ",  # block comments that never close
        '"\\',  # a string of escapes that never closes
        '"/*',  # both
    ],
)
def test_unterminated_comments_and_strings_are_refused_quickly(tmp_path, unit):
    # 300 kB: the old comment stripper retried every position to the end (hours); now one pass.
    text = unit * (300_000 // len(unit))
    path = tmp_path / "slow.json"
    path.write_text(text, encoding="utf-8")
    _refused_within(60, read_presets, path)


def test_valid_presets_with_comments_still_read(tmp_path):
    path = tmp_path / "commented.json"
    path.write_text(
        '// exported by hand\n[ /* one map */ {"Name": "a // b /* c */", "RGBPoints": [0, 0, 0, 0, 1, 1, 1, 1],},\n]',
        encoding="utf-8",
    )
    assert [preset.name for preset in read_presets(path)] == ["a // b /* c */"]


def test_xml_entity_bombs_are_refused(tmp_path):
    laughs = "".join(f'<!ENTITY a{i} "{("&a%d;" % (i - 1) if i else "ha") * 10}">' for i in range(12))
    bomb = f'<?xml version="1.0"?><!DOCTYPE l [{laughs}]><ColorMaps><ColorMap name="&a11;"/></ColorMaps>'
    assert "not valid XML" in _refused_within(60, parse_presets, bomb, "bomb.xml")
    external = (
        '<?xml version="1.0"?><!DOCTYPE l [<!ENTITY x SYSTEM "file:///etc/passwd">]>'
        '<ColorMaps><ColorMap name="&x;"><Point x="0" r="0" g="0" b="0"/></ColorMap></ColorMaps>'
    )
    assert "not valid XML" in _refused_within(60, parse_presets, external, "external.xml")
