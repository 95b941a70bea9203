"""`f2l report`: a self-contained HTML page per evaluation or build folder. Hostile names and EXIF
stay text; in a real browser (headless Chromium, where installed) the page loads without console
errors, every image resolves and the metric table holds the CSV's numbers."""

from __future__ import annotations

import csv
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from f2l.report.build import write_report

HOSTILE = "<img src=x onerror=alert(1)>"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")


class Tags(HTMLParser):
    """Start tags with their attributes, and the page's text."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict]] = []
        self.text: list[str] = []
        self.cells: list[list[str]] = []
        self._table = None

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))
        if tag == "tr" and dict(attrs).get("id", "").startswith("metrics-"):
            self._table = []
            self.cells.append(self._table)

    def handle_endtag(self, tag):
        if tag == "tr":
            self._table = None

    def handle_data(self, data):
        self.text.append(data)
        if self._table is not None and data.strip():
            self._table.append(data.strip())


def parse(path: Path) -> Tags:
    p = Tags()
    p.feed(path.read_text(encoding="utf-8"))
    return p


def assert_safe(page: Path) -> Tags:
    tags = parse(page)
    assert not [t for t, _ in tags.tags if t in ("script", "iframe", "object", "embed", "link", "base", "form")]
    assert not [(t, a) for t, attrs in tags.tags for a in attrs if a.startswith("on")]
    for tag, attrs in tags.tags:
        for key in ("src", "href"):
            url = attrs.get(key)
            if url is not None and tag != "meta":
                assert not re.match(r"^[a-z][a-z0-9+.-]*:", url, re.I), url  # relative only: no http:, javascript:
    csp = [a for t, a in tags.tags if t == "meta" and a.get("http-equiv") == "Content-Security-Policy"]
    assert csp and "default-src 'none'" in csp[0]["content"]
    return tags


def image_sources(page: Path, tags: Tags) -> list[Path]:
    from urllib.parse import unquote

    return [page.parent / unquote(a["src"]) for t, a in tags.tags if t == "img"]


@pytest.fixture(scope="module")
def evaluation(tmp_path_factory):
    """A small demo-like evaluation folder: 3 synthetic faces, two models, metrics, report."""
    from f2l.estimate.runner import run_estimates
    from f2l.lighting.grid import LatLongGrid
    from f2l.metrics.evaluate import evaluate_estimates
    from f2l.synth.dataset import write_synthetic_shards

    out = tmp_path_factory.mktemp("evaluation")
    write_synthetic_shards(out / "shards", n=3, seed=2, grid=LatLongGrid(), image_size=96)
    run_estimates([out / "shards"], models=["sunsky", "sh9"], out_dir=out / "estimates")
    evaluate_estimates(out / "estimates", [out / "shards"])
    summary = write_report(out, page_size=2)
    return out, summary


def test_evaluation_report(evaluation):
    out, summary = evaluation
    assert summary.faces == 3 and len(summary.pages) == 2  # paginated: 2 faces, then 1
    page = out / "report.html"
    tags = assert_safe(page)
    sources = image_sources(page, tags)
    assert len(sources) >= 2 * (1 + 1 + 2 + 1 + 2) and all(p.is_file() for p in sources)
    assert all(t[1].get("loading") == "lazy" for t in tags.tags if t[0] == "img")
    again = write_report(out, page_size=2)  # thumbnails are cached
    assert again.thumbnails_written == 0 and again.thumbnails_reused == summary.thumbnails_written + summary.thumbnails_reused
    assert (out / "report-2.html").is_file() and "Faces 3–3 of 3" in (out / "report-2.html").read_text()


def _hostile_tree(root: Path) -> None:
    import skimage.data

    faces = root / f"site {HOSTILE}" / "faces"
    faces.mkdir(parents=True)
    exif = Image.Exif()
    exif[0x010F] = "<script>alert(2)</script>"  # Make
    exif[0x0110] = '"><img src=y onerror=alert(3)>'  # Model
    exif[0x013B] = "<b onclick=alert(4)>artist</b>"  # Artist
    exif[0x9286] = "<iframe src=//evil.example>"  # UserComment
    face = Image.fromarray(skimage.data.astronaut()).crop((64, 0, 384, 320)).resize((256, 256))
    face.save(faces / f"{HOSTILE}.png", exif=exif)
    (faces / "broken<script>.png").write_bytes(b"\x89PNG\r\n\x1a\n<script>alert(5)</script>")


def test_hostile_names_and_exif_stay_text(tmp_path):
    from f2l.pipeline import build_dataset
    from tests.test_build_dataset import PIPELINE

    root, work, out = tmp_path / "raw", tmp_path / "work", tmp_path / "out"
    _hostile_tree(root)
    (tmp_path / "pipeline.toml").write_text(PIPELINE)
    build_dataset(root, work, out, tmp_path / "pipeline.toml")
    write_report(out, work=work)
    page = out / "report.html"
    tags = assert_safe(page)
    text = "".join(tags.text)
    for injected in (HOSTILE, "<script>alert(2)</script>", '"><img src=y onerror=alert(3)>', "broken<script>.png"):
        assert injected in text  # shown, as text
    assert all(p.is_file() for p in image_sources(page, tags))
    assert str(tmp_path) not in page.read_text()  # no machine path: messages are relative to the tree
    assert "fit overlay" in text and "chart ΔE2000" in text
    if CHROMIUM:
        dom, console = _chromium(page)
        live = Tags()
        live.feed(dom)  # the DOM the browser built: no injected element or handler survived
        assert not [t for t, _ in live.tags if t in ("script", "iframe", "b")]
        assert not [(t, a) for t, attrs in live.tags for a in attrs if a.startswith("on")]
        assert console == [], console


def _chromium(page: Path, *extra: str) -> tuple[str, list[str]]:
    """(serialised DOM after load, console messages) of headless Chromium on ``page``."""
    res = subprocess.run([CHROMIUM, "--headless=new", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
                          "--v=1", "--virtual-time-budget=5000", *extra, "--dump-dom", page.as_uri()],
                         capture_output=True, text=True, timeout=120)
    console = [line for line in res.stderr.splitlines() if ":CONSOLE" in line]
    return res.stdout, console


@pytest.mark.skipif(CHROMIUM is None, reason="Chromium is not installed (make test installs Debian's chromium "
                                              "where the machine allows: root and apt)")
def test_report_in_a_real_browser(evaluation, tmp_path):
    out, _ = evaluation
    page = out / "report.html"
    dom, console = _chromium(page)
    assert console == [], console  # no CSP violation, no error
    # every image resolves: the same page with a checker appended (CSP and lazy loading off)
    check = out / "check.html"
    html = page.read_text(encoding="utf-8")
    html = re.sub(r'<meta http-equiv="Content-Security-Policy"[^>]*>', "", html).replace(' loading="lazy"', "")
    html = html.replace("</body>", "<script>window.addEventListener('load',()=>{const i=[...document.images];"
                        "document.title='IMAGES '+i.filter(x=>x.complete&&x.naturalWidth>0).length+'/'+i.length;});"
                        "</script></body>")
    check.write_text(html, encoding="utf-8")
    checked, _ = _chromium(check)
    found = re.search(r"<title>IMAGES (\d+)/(\d+)</title>", checked)
    assert found and found.group(1) == found.group(2) and int(found.group(2)) > 10, found
    # the metric table in the browser holds the CSV's numbers
    tags = Tags()
    tags.feed(dom)
    with open(out / "estimates" / "metrics_summary.csv", newline="") as fh:
        rows = {r["model"]: r for r in csv.DictReader(fh)}
    from f2l.metrics import METRIC_NAMES

    assert {c[0] for c in tags.cells} == set(rows)
    for cells in tags.cells:
        r = rows[cells[0]]
        expected = [float(r[f"{m} mean"]) for m in METRIC_NAMES] + [float(r["runtime_s mean"])]
        np.testing.assert_allclose([float(v) for v in cells[2:]], expected, rtol=5e-4)
