"""Fixtures of the dashboard tests: a real uvicorn server (tests/server/conftest.py) and
headless Chromium driven by Playwright.

Chromium is the Debian ``chromium`` package (``.ci/run`` installs it when missing);
``CSA_CHROMIUM`` names another binary. Without it, or without Playwright, the browser tests
are skipped with the reason. Screenshots of every page go to ``tests/ui/screenshots/``
(ignored by git), or to ``CSA_UI_SCREENSHOTS``.
"""

from __future__ import annotations

import os
import tarfile
from pathlib import Path

import pytest

CHROMIUM = Path(os.environ.get("CSA_CHROMIUM", "/usr/bin/chromium"))
SCREENSHOTS = Path(os.environ.get("CSA_UI_SCREENSHOTS", Path(__file__).parent / "screenshots"))
# Headless, and nothing that reaches out to the network on its own.
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]


def scene_archive(folder: Path, dest: Path) -> Path:
    """A scene folder packed as .tar.gz (the folder at the archive's top)."""
    with tarfile.open(dest, "w:gz") as tar:
        tar.add(folder, arcname=folder.name)
    return dest


@pytest.fixture(scope="session")
def browser():
    """One headless Chromium for the whole run (each test module opens its own context)."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
    if not CHROMIUM.is_file():
        pytest.skip(
            f"no Chromium at {CHROMIUM} (install the Debian package chromium, or set CSA_CHROMIUM)"
        )
    with sync_api.sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_FLAGS)
        yield browser
        browser.close()


@pytest.fixture(scope="session")
def screenshots() -> Path:
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    return SCREENSHOTS
