"""Capture JSON files that cannot be read are one-line CaptureErrors naming the file, however they are broken."""

from __future__ import annotations

import pytest

from spadscan.protocol.capture_format import read_json
from spadscan.protocol.errors import CaptureError


@pytest.mark.parametrize("text, why", [
    ('{"measurements": ' + "[" * 200_000 + "]" * 200_000 + "}", "nested too deeply"),
    ('{"measurements": [', "unreadable JSON"),
    ("[1, 2]", "expected a JSON object, got list"),
])
def test_a_broken_json_file_is_one_line_naming_it(tmp_path, text, why):
    path = tmp_path / "meta.json"
    path.write_text(text)
    with pytest.raises(CaptureError) as err:
        read_json(path)
    assert str(err.value).startswith(f"{path}: ") and why in str(err.value) and "\n" not in str(err.value)
