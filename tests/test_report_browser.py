"""The report in a real browser (scripts/report_screenshot.py: Playwright driving Chromium) at 1366 x 768: the
first screen shows the verdict cards, the navigation is not cut off, nothing is fetched from outside the
page's folder. Skipped where playwright or a Chromium is missing."""
import importlib.util
import json
from pathlib import Path

import pandas as pd
import pytest

from cloudpbf.studies.page import build_report

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "report_screenshot.py"


def _script():
    spec = importlib.util.spec_from_file_location("report_screenshot", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_first_screen_at_1366_shows_the_verdicts_and_the_whole_navigation(tmp_path):
    pytest.importorskip("playwright.sync_api", reason="playwright is not installed (the report-check extra)")
    shots = _script()
    chromium = shots.find_chromium()
    if chromium is None:
        pytest.skip("no Chromium found (apt-get install chromium, or playwright install chromium)")
    data = tmp_path / "data"
    data.mkdir()
    (data / "environment.json").write_text(json.dumps({"device": "cpu", "commit": "abc1234", "scale": "cpu-smoke"}))
    pd.DataFrame({"example": ["growing", "growing"], "mode": ["non-adaptive", "adaptive"], "max_particles": [343, 2744],
                  "total_ms": [30.0, 20.0], "device": "cpu", "commit": "abc1234"}).to_csv(data / "table1.csv",
                                                                                     index=False)
    pd.DataFrame({"parameter": "dt", "value": [1.0, 2.0, 8.0], "stable": [True, True, False],
                  "device": "cpu", "commit": "abc1234"}).to_csv(data / "stress.csv", index=False)
    page = build_report(tmp_path)
    facts = shots.inspect(page, tmp_path / "shots", 1366, 768, chromium=chromium)
    assert facts["nav_links"] >= 16 and facts["nav_cut_off"] == [] and not facts["horizontal_scroll"]
    assert facts["cards"][:4] == ["card-table1", "card-adaptive_front", "card-compare", "card-stress"]
    assert facts["cards_on_first_screen"] >= 4
    assert facts["outside_requests"] == []
    assert Path(facts["screenshots"][0]).stat().st_size > 10_000
