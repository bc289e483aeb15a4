"""The review page in headless Chromium (Debian's chromium + chromedriver): marks, export, escaping."""

import json
import os
import shutil

import pytest

from labrobfail_data.annotate import Annotated
from labrobfail_data.review import write_review_page

pytestmark = pytest.mark.browser

CHROMIUM, DRIVER = shutil.which("chromium"), shutil.which("chromedriver")
needs_browser = pytest.mark.skipif(
    not (CHROMIUM and DRIVER) and not os.environ.get("LABROBFAIL_REQUIRE_BROWSER"),
    reason="Debian chromium/chromium-driver not installed (make test installs them)",
)


def _item(i, task):
    from PIL import Image

    recs = [
        {
            "id": f"seen-ep{i:07d}_Q{k}",
            "image": f"images/seen-ep{i:07d}.png",
            "conversations": [
                {"from": "human", "value": f"<image>\nquestion {k} about {task}"},
                {"from": "gpt", "value": "1"},
            ],
        }
        for k in range(1, 7)
    ]
    return Annotated(
        f"seen-ep{i:07d}",
        f"seen-pair{i // 2:07d}",
        "seen",
        f"images/seen-ep{i:07d}.png",
        Image.new("RGB", (8, 4)),
        recs,
        {"task": task, "success": False},
    )


@needs_browser
def test_marks_export_and_escaping(tmp_path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    from selenium.webdriver.common.by import By

    evil = "<script>window.pwned=1</script><img src=x onerror='window.pwned=2'>"
    items = [_item(0, "pick up the beaker"), _item(1, evil), _item(2, "press the red button")]
    page = tmp_path / "review.html"
    write_review_page(items, page, n=3, seed=0)
    assert "<script>window.pwned" not in page.read_text()
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for f in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
    ):
        opts.add_argument(f)
    drv = webdriver.Chrome(service=Service(DRIVER), options=opts)
    try:
        drv.get(page.as_uri())
        cards = drv.find_elements(By.CSS_SELECTOR, ".card")
        assert len(cards) == 3
        assert drv.execute_script("return window.pwned === undefined")
        assert evil in cards[1].text  # shown as text, not run
        cards[0].find_element(By.CSS_SELECTOR, "button[data-mark=accept]").click()
        cards[1].find_element(By.CSS_SELECTOR, "button[data-mark=reject]").click()
        drv.find_element(By.ID, "export").click()
        marks = json.loads(drv.find_element(By.ID, "marks-json").get_attribute("value"))
        assert marks == {"marks": {"seen-ep0000000": "accept", "seen-ep0000001": "reject"}}
        assert drv.find_element(By.ID, "count").text == "2"
    finally:
        drv.quit()
