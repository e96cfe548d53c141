"""The documentation's browser check (docs/check_site.py) sees what a reader would: on a small
site of its own, each kind of fault is reported on its page, and a sound page passes."""

from __future__ import annotations

import importlib.util
import os
import shutil
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HAVE_BROWSER = any(Path(p).is_file() for p in ("/usr/bin/chromium", "/usr/bin/chromium-browser")) or bool(
    shutil.which("chromium")
)
pytestmark = pytest.mark.skipif(
    not HAVE_BROWSER and not os.environ.get("CI"), reason="no Chromium here (CI installs it: .ci/run)"
)

PNG = bytes.fromhex(  # a 1×1 pixel
    "89504e470d0a1a0a0000000d4948445200000001000000010806000000"
    "1f15c4890000000d49444154789c6360000002000154a24f5d0000000049454e44ae426082"
)


def checker():
    spec = importlib.util.spec_from_file_location("check_site", ROOT / "docs" / "check_site.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.slow
def test_the_browser_check_reports_each_fault_on_its_page(tmp_path):
    site = tmp_path / "html"
    site.mkdir()
    (site / "picture.png").write_bytes(PNG)
    pages = {
        "index.html": '<h1 id="top">ok</h1><img src="picture.png"><a href="other.html#part">other</a>',
        "other.html": '<h2 id="part">part</h2><a href="index.html#top">back</a>',
        "image.html": '<img src="missing.png">',
        "anchor.html": '<a href="other.html#nowhere">x</a><a href="gone.html">y</a>',
        "script.html": "<script>console.error('boom'); notDefined();</script>",
    }
    for name, body in pages.items():
        (site / name).write_text(f"<!doctype html><html><body>{body}</body></html>")
    problems = checker().check(site, tmp_path / "shots")
    assert set(problems) == {"image.html", "anchor.html", "script.html"}
    assert any("missing.png" in p for p in problems["image.html"])
    assert any("missing anchor" in p and "#nowhere" in p for p in problems["anchor.html"])
    assert any("missing file" in p and "gone.html" in p for p in problems["anchor.html"])
    assert any("boom" in p for p in problems["script.html"]) and any("notDefined" in p for p in problems["script.html"])
    assert (tmp_path / "shots" / "index.png").stat().st_size > 0
