"""Headless Chromium driven by selenium, for the viewer's and the web export's tests.

WebGL runs on SwiftShader (the CPU), so no GPU is needed. Chromium and chromedriver
come from Debian's `chromium` and `chromium-driver` (or $CHROMIUM / $CHROMEDRIVER).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from collections.abc import Iterator

import cv2
import numpy as np


def browser_problem() -> str | None:
    """Why a browser cannot run here, or None."""
    found = _find()
    return found if isinstance(found, str) else None


def _find() -> tuple[str, str] | str:
    """(chromium, chromedriver), or why a browser cannot run here."""
    import importlib.util

    if importlib.util.find_spec("selenium") is None:
        return "selenium is not installed (pip install -e '.[dev]')"
    chrome = os.environ.get("CHROMIUM") or next(
        (p for p in map(shutil.which, ("chromium", "chromium-browser", "google-chrome")) if p), None)
    driver = os.environ.get("CHROMEDRIVER") or shutil.which("chromedriver")
    if not chrome or not driver:
        return "no Chromium and chromedriver (apt install chromium chromium-driver; .ci/run installs them)"
    return chrome, driver


@contextlib.contextmanager
def open_page(url: str, width: int, height: int, timeout_s: float = 60) -> Iterator[tuple[object, dict]]:
    """The page at `url` in a width x height viewport, open until the block ends, once its
    first frame with the scene is drawn: (the selenium driver, the page's window.splatcli)."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    found = _find()
    assert not isinstance(found, str), found
    chrome, driver = found
    opts = webdriver.ChromeOptions()
    opts.binary_location = chrome
    for a in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-angle=swiftshader",
              "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--hide-scrollbars", "--mute-audio"):
        opts.add_argument(a)
    d = webdriver.Chrome(service=Service(driver), options=opts)
    try:
        d.execute_cdp_cmd("Emulation.setDeviceMetricsOverride",
                          {"width": width, "height": height, "deviceScaleFactor": 1, "mobile": False})
        d.get(url)
        deadline = time.monotonic() + timeout_s
        st = None
        while time.monotonic() < deadline:
            st = d.execute_script("return window.splatcli || null")
            if st and (st.get("ready") or st.get("error")):
                break
            time.sleep(0.05)
        assert st and st.get("ready") and not st.get("error"), (st, d.get_log("browser")[-5:])
        yield d, st
    finally:
        d.quit()


def capture(d, width: int, height: int) -> np.ndarray:
    """The viewport now: [H, W, 3] uint8 RGB."""
    png = d.get_screenshot_as_png()
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(img[:height, :width])


def screenshot(url: str, width: int, height: int, settle_s: float = 1.5) -> tuple[np.ndarray, dict]:
    """`open_page`, then the picture once the renderer has had `settle_s` to sort."""
    with open_page(url, width, height) as (d, st):
        time.sleep(settle_s)
        return capture(d, width, height), st


def psnr_u8(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)) / 255.0 ** 2
    return 10 * np.log10(1.0 / max(mse, 1e-12))
