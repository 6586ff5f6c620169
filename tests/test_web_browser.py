"""The web page in headless Chromium: upload two photos, see the result, download, screenshot."""

import io
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not (CHROMIUM.exists() and CHROMEDRIVER.exists()),
        reason="Debian chromium/chromium-driver not installed (`make browser` installs them)",
    ),
]


@pytest.fixture()
def server():
    """The app on a free 127.0.0.1 port, served by uvicorn in a thread."""
    import uvicorn

    from pis3r.web.app import create_app

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    uvi = uvicorn.Server(uvicorn.Config(create_app(), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=uvi.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not uvi.started and time.monotonic() < deadline:
        time.sleep(0.05)
    assert uvi.started
    yield f"http://127.0.0.1:{port}"
    uvi.should_exit = True
    thread.join(timeout=30)


@pytest.fixture()
def browser(tmp_path):
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1280,1000"):
        options.add_argument(flag)
    options.add_experimental_option("prefs", {"download.default_directory": str(tmp_path / "downloads"),
                                              "download.prompt_for_download": False})
    driver = webdriver.Chrome(options=options, service=Service(str(CHROMEDRIVER)))
    yield driver
    driver.quit()


def test_upload_stitch_show_download(server, browser, small_pair, tmp_path):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    paths = []
    for index, array in enumerate(small_pair):
        paths.append(tmp_path / f"photo_{index}.png")
        Image.fromarray(array).save(paths[-1])
    from pis3r import StitchOptions

    browser.get(server + "/")
    # The form's choices and defaults are the server's StitchOptions, loaded by the page.
    for name in ("backend", "matcher", "projection", "blend"):
        WebDriverWait(browser, 30).until(
            lambda d: len(d.find_elements(By.CSS_SELECTOR, f"#{name} option")) == len(StitchOptions.choices(name)))
        offered = [o.get_attribute("value") for o in browser.find_elements(By.CSS_SELECTOR, f"#{name} option")]
        assert tuple(offered) == StitchOptions.choices(name)
        assert browser.find_element(By.ID, name).get_attribute("value") == StitchOptions.default(name)
    browser.find_element(By.ID, "files").send_keys("\n".join(str(p) for p in paths))
    browser.find_element(By.ID, "backend").send_keys("classical")
    browser.find_element(By.ID, "go").click()
    WebDriverWait(browser, 120).until(
        lambda d: d.execute_script("const i = document.getElementById('result');"
                                   "return i.complete && i.naturalWidth > 0;")
        or "Error" in d.find_element(By.ID, "message").text)
    assert "Done" in browser.find_element(By.ID, "message").text
    assert len(browser.find_elements(By.CSS_SELECTOR, "#inputs img")) == 2
    assert browser.find_element(By.ID, "parallax").text.startswith("Parallax: ")
    # Two crops of one photo: a shift, which no focal explains better than another. The page says so.
    focal = browser.find_element(By.ID, "focal").text
    assert focal.startswith("Focal 228 px (prior") and "57–1140 px fit" in focal
    assert focal.endswith("not determined by these photos")
    assert "do not determine the focal length" in browser.find_element(By.ID, "message").text
    cameras = browser.find_element(By.ID, "cameras").text
    assert cameras.startswith("Camera of ") and "rotation within ±" in cameras and "matches)" in cameras

    browser.find_element(By.ID, "download-stitched-png").click()
    target = tmp_path / "downloads" / "stitched.png"
    WebDriverWait(browser, 30).until(lambda d: target.is_file())
    downloaded = np.asarray(Image.open(target))
    width = browser.execute_script("return document.getElementById('result').naturalWidth")
    assert downloaded.shape[1] == width and downloaded.shape[0] > small_pair[0].shape[0] // 2

    shot = np.asarray(Image.open(io.BytesIO(browser.get_screenshot_as_png())).convert("RGB")).astype(float)
    assert shot.std() > 20 and len(np.unique(shot.reshape(-1, 3) // 32, axis=0)) > 20
