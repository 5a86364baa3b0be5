"""The HTML people open, in a real browser: headless Chromium loads `cadence report`'s and `cadence study
analyse`'s index.html over HTTP, and every image on them loads (a figure named but not written, or written
unreadable, fails here: checked by breaking one). Skipped, with the reason, where no Chromium is installed;
`.ci/run` installs Debian's where it can."""

from __future__ import annotations

import functools
import http.server
import json
import re
import shutil
import subprocess
import threading
from pathlib import Path

import pytest

from tests.support.sessions import write_run

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="no Chromium on this machine (apt-get install chromium)"
)

HARNESS = """<!doctype html><html><body><pre id="result">pending</pre>
<iframe id="page" src="{page}" width="1200" height="800"></iframe>
<script>
document.getElementById("page").addEventListener("load", () => {{
  const doc = document.getElementById("page").contentDocument;
  const images = [...doc.images];
  const settle = () => images.every((i) => i.complete);
  const report = () => {{
    const bad = images.filter((i) => !(i.naturalWidth > 0)).map((i) => i.getAttribute("src"));
    document.getElementById("result").textContent = JSON.stringify({{images: images.length, bad: bad}});
  }};
  if (settle()) report(); else Promise.all(images.map((i) => i.decode().catch(() => null))).then(report);
}});
</script></body></html>"""


class Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format: str, *args: object) -> None:
        pass


def images_in_chromium(root: Path, page: str) -> dict:
    """Serve ``root`` over HTTP, load ``page`` in a harness in headless Chromium, and return what the
    harness found: how many images, and which did not load."""
    (root / "check.html").write_text(HARNESS.format(page=page))
    handler = functools.partial(Quiet, directory=str(root))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        assert CHROMIUM is not None
        r = subprocess.run(
            [CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=15000",
             "--dump-dom", f"http://127.0.0.1:{server.server_address[1]}/check.html"],
            capture_output=True, text=True, timeout=120,
        )  # fmt: skip
    finally:
        server.shutdown()
    found = re.search(r'<pre id="result">(.*?)</pre>', r.stdout, re.S)
    assert found, r.stdout[-2000:] + r.stderr[-2000:]
    assert found.group(1) != "pending", r.stdout[-2000:] + r.stderr[-2000:]
    return json.loads(found.group(1))


def test_every_image_of_a_report_and_of_a_study_loads_in_chromium(tmp_path: Path) -> None:
    from cadence.lab.analysis import analyse, write_study
    from cadence.lab.report import from_mcap, write_report
    from cadence.lab.session_file import load_session
    from tests.support.sessions import info, write

    site = tmp_path / "site"
    write_report(from_mcap(write_run(tmp_path)), site / "report", 0.85)
    files = [write(tmp_path / f"s{i}_{c}.mcap", info(f"s{i}", c)) for i in (1, 2) for c in "ab"]
    write_study(analyse([load_session(f) for f in files]), site / "study")
    assert images_in_chromium(site, "report/index.html") == {"images": 3, "bad": []}
    # conditions.png and one figure per subject
    assert images_in_chromium(site, "study/index.html") == {"images": 3, "bad": []}
