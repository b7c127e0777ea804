"""`pipeline report`: the kept-to-expected density map in numbers, and the HTML page as a person sees it, in a
real headless Chromium (skipped where Debian's chromium and chromium-driver are not installed)."""
from __future__ import annotations

import io
import re
import shutil
from pathlib import Path

import laspy
import numpy as np
import pytest
from click.testing import CliRunner

import pipeline
from pipeline.apps.cli import cli
from pipeline.apps.comparison import RunOptions, compare
from pipeline.apps.report import write_report
from pipeline.apps.visual.density_map import cell_counts, density_grid, density_map
from pipeline.apps.visual.report_region import parse_region
from pipeline.apps.visual.view3d import CLASSES

RATIO = 0.1
BLANK_STD = 20.0  # grey levels: a blank area is 0, plotly's "WebGL is not supported" text 9-15, the clouds 29-52
BUILDING_RGB = tuple(int(CLASSES[6][1][i:i + 2], 16) for i in (1, 3, 5))  # class 6: the street's facades


@pytest.fixture(scope="module")
def thinned(street_scan: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The street scan through the pipeline with fps and with random, at RATIO, on one worker."""
    folder = tmp_path_factory.mktemp("report_runs")
    outputs = {}
    for method in ("fps", "random"):
        outputs[method] = folder / f"{method}.laz"
        pipeline.run(street_scan, outputs[method], ratio=RATIO, method=method, workers=1)
    return outputs


@pytest.fixture(scope="module")
def report(street_scan: Path, thinned: dict[str, Path], tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The report of both runs, coloured by classification."""
    path = tmp_path_factory.mktemp("report") / "report.html"
    return write_report(street_scan, [thinned["fps"], thinned["random"]], path, color="classification")


def test_random_thinning_density_is_flat(street_scan: Path, thinned: dict[str, Path]) -> None:
    """Uniform random thinning keeps its share everywhere: on cells holding many points the ratio is about 1."""
    grid = density_grid(street_scan, cells_long=6)
    density = density_map(street_scan, thinned["random"], grid)
    populated = density.ratio[np.isfinite(density.ratio)]
    assert density.kept_share == pytest.approx(RATIO, rel=1e-3)
    assert len(populated) >= 6
    print(f"random thinning, {len(populated)} cells: mean kept / expected {populated.mean():.3f}")
    assert 0.9 <= populated.mean() <= 1.1, populated
    full = density.ratio[cell_counts(street_scan, grid) >= 1000]  # 100 points expected: a spread of about 0.1
    assert len(full) >= 4 and full.min() > 0.7 and full.max() < 1.3, full


def test_dropped_rectangle_shows_at_zero(street_scan: Path, tmp_path: Path) -> None:
    """A thinning that drops every point of a block of cells shows those cells at 0, and every other cell at
    1 / (share kept), since it keeps all of its points there."""
    grid = density_grid(street_scan, cells_long=12)
    las = laspy.read(street_scan)
    keys = grid.keys(np.column_stack([las.x, las.y, las.z]))
    ix, iy = np.divmod(keys, grid.shape[1])
    nx, ny = grid.shape
    dropped = (ix >= nx // 3) & (ix < 2 * nx // 3) & (iy >= ny // 3) & (iy < 2 * ny // 3)
    assert 0 < dropped.sum() < len(las.points)
    kept = laspy.LasData(las.header)
    kept.points = las.points[~dropped]
    subset = tmp_path / "holed.laz"
    kept.write(subset)

    density = density_map(street_scan, subset, grid)
    share = (~dropped).sum() / len(dropped)
    assert density.kept_share == pytest.approx(share)
    hole = np.zeros((ny, nx), dtype=bool)
    hole[ny // 3:2 * ny // 3, nx // 3:2 * nx // 3] = True
    populated = np.isfinite(density.ratio)
    assert (populated & hole).sum() >= 2
    np.testing.assert_array_equal(density.ratio[populated & hole], 0.0)
    np.testing.assert_allclose(density.ratio[populated & ~hole], 1 / share)


def test_report_is_self_contained(report: Path) -> None:
    """One page with plotly's script inline (no CDN), the metrics with units, the maps' PNG beside it."""
    page = report.read_text(encoding="utf-8")
    tags = re.findall(r"<script\b[^>]*>", page)
    assert tags and not [tag for tag in tags if "src=" in tag], tags  # every script inline: nothing fetched
    assert len(page) > 3_000_000  # plotly.js itself is inlined
    for text in ("CD (metre²)", "Hausdorff (metre)", "fps.laz", "random.laz", "Kept-to-expected density",
                 "How each output was made", "coloured by classification", "street.laz"):
        assert text in page, text
    assert 'id="region-view"' in page and 'id="density-maps"' in page
    png = report.with_suffix(".density.png")
    assert png.stat().st_size > 10_000


def test_report_command_and_region(street_scan: Path, thinned: dict[str, Path], tmp_path: Path) -> None:
    """`pipeline report` with --region writes the page and names the region; a bad region is one line."""
    page = tmp_path / "one.html"
    runner = CliRunner()
    result = runner.invoke(cli, ["report", str(street_scan), str(thinned["fps"]), "-o", str(page),
                                 "--region", "630004,4833000,10", "--sample", "0"])
    assert result.exit_code == 0, result.output
    assert page.exists() and page.with_suffix(".density.png").exists()
    assert "Region 630004.00,4833000.00,10" in page.read_text(encoding="utf-8")
    bad = runner.invoke(cli, ["report", str(street_scan), str(thinned["fps"]), "-o", str(page), "--region", "1,2"])
    assert bad.exit_code == 2 and "--region must be X,Y,SIZE" in bad.output


def test_the_report_replaces_no_input_and_no_page_unasked(street_scan: Path, thinned: dict[str, Path],
                                                          tmp_path: Path) -> None:
    """`-o` naming an input (the scan itself) is refused, as a run's output is; an existing page or its PNG is
    replaced only with --overwrite (the report wrote over anything, a LAZ scan included)."""
    runner = CliRunner()
    source = tmp_path / "scan.laz"
    source.write_bytes(street_scan.read_bytes())
    before = source.read_bytes()
    over_input = runner.invoke(cli, ["report", str(source), str(thinned["fps"]), "-o", str(source), "--sample", "0"])
    assert over_input.exit_code == 2 and "unsupported output type" in over_input.output
    page = tmp_path / "page.html"
    page.write_text("my notes")
    kept = runner.invoke(cli, ["report", str(source), str(thinned["fps"]), "-o", str(page), "--sample", "0"])
    assert kept.exit_code == 2 and "already exists (pass --overwrite" in kept.output
    refused = runner.invoke(cli, ["report", str(source), str(thinned["fps"]), "-o", str(page), "--sample", "0",
                                  "--overwrite"])  # not a page this command wrote
    assert refused.exit_code == 2 and "is not a HTML file" in refused.output and page.read_text() == "my notes"
    page.unlink()
    for _ in range(2):
        result = runner.invoke(cli, ["report", str(source), str(thinned["fps"]), "-o", str(page), "--sample", "0",
                                     "--overwrite"])
        assert result.exit_code == 0, result.output
    assert source.read_bytes() == before


def test_region_parse() -> None:
    """X,Y,SIZE is a square centred on (X, Y)."""
    region = parse_region("10,20,4")
    assert (region.x0, region.y0, region.size) == (8.0, 18.0, 4.0)
    inside = region.contains(np.array([[8.0, 18.0, 0.0], [11.9, 21.9, 5.0], [12.0, 20.0, 0.0], [7.9, 20.0, 0.0]]))
    assert inside.tolist() == [True, True, False, False]


def test_the_region_of_a_scan_along_one_line_holds_its_points(tmp_path: Path) -> None:
    """A scan of one line along x (a wire, a kerb, a narrow corridor): the automatic region is a square of the
    line's scale holding points, not a cell a few micrometres wide."""
    from pipeline.apps.visual.report_region import find_region
    from pipeline.io.points import covering_grid

    grid = covering_grid(np.array([0.0, 5.0]), np.array([1000.0, 5.0]), 50)
    assert grid.side == pytest.approx(20.0) and grid.shape == (50, 1)
    x = np.linspace(0.0, 1000.0, 100_000)
    line = tmp_path / "line.las"
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales, header.offsets = [0.001] * 3, [0.0] * 3
    cloud = laspy.LasData(header)
    cloud.x, cloud.y, cloud.z = x, np.full_like(x, 5.0), np.where(x > 500, np.sin(x), 0.0)
    cloud.write(line)
    region = find_region(line)
    assert region.size == pytest.approx(200.0)
    assert region.contains(np.column_stack([x, np.full_like(x, 5.0), x])).sum() > 1_000


def test_compare_html(street_scan: Path, tmp_path: Path) -> None:
    """`pipeline compare --html` writes compare.html with a panel and a map per run, from the same code."""
    written = compare(street_scan, [0.2], ["random"], tmp_path, RunOptions(workers=1), sample=0, html=True)
    page = tmp_path / "compare.html"
    assert page in written and tmp_path / "compare.density.png" in written
    text = page.read_text(encoding="utf-8")
    assert "random 0.2" in text and 'id="density-maps"' in text


def browser() -> "selenium.webdriver.Chrome":  # noqa: F821 (selenium is imported only where installed)
    """A headless Chromium driven by Debian's chromedriver, rendering WebGL in software; or skip."""
    chromium, driver_path = shutil.which("chromium"), shutil.which("chromedriver")
    if chromium is None or driver_path is None:
        pytest.skip("Debian's chromium and chromium-driver are not installed "
                    "(apt-get install chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (pip install -e '.[test]')")
    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--use-gl=swiftshader",
                 "--enable-unsafe-swiftshader", "--window-size=1400,1600"):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(options=options, service=webdriver.ChromeService(executable_path=driver_path))


def test_report_renders_in_chromium(report: Path, tmp_path: Path) -> None:
    """Load the page in Chromium, wait until every 3-D scene has its WebGL canvas and has drawn, and check that
    each scene's plot area is not blank, that turning one scene turns the others, and that the console has no
    error."""
    from PIL import Image
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    driver = browser()
    try:
        driver.get(report.as_uri())
        view = driver.find_element(By.ID, "region-view")
        WebDriverWait(driver, 60, poll_frequency=0.5).until(lambda d: d.execute_script(
            "var gd = document.getElementById('region-view');"
            "return gd._fullLayout !== undefined && gd.querySelectorAll('canvas').length >= 3;"))
        driver.execute_script("arguments[0].scrollIntoView();", view)
        domains = driver.execute_script(
            "var l = document.getElementById('region-view')._fullLayout;"
            "return ['scene', 'scene2', 'scene3'].map(function (s) { return [l[s].domain.x, l[s].domain.y]; });")

        def scene_pixels() -> list[np.ndarray]:
            """(h, w, 3) RGB crops of the three scenes' plot areas from a fresh screenshot."""
            shot = Image.open(io.BytesIO(view.screenshot_as_png)).convert("RGB")
            shot.save(tmp_path / "region-view.png")
            pixels = np.asarray(shot, dtype=np.float64)
            height, width = pixels.shape[:2]
            return [pixels[int((1 - y1) * height):int((1 - y0) * height), int(x0 * width):int(x1 * width)]
                    for (x0, x1), (y0, y1) in domains]  # plotly's domains run bottom-up

        WebDriverWait(driver, 60, poll_frequency=1).until(
            lambda d: min(crop.mean(axis=2).std() for crop in scene_pixels()) > BLANK_STD)
        crops = scene_pixels()
        spreads = [float(crop.mean(axis=2).std()) for crop in crops]
        building = [float((np.abs(crop - BUILDING_RGB).max(axis=2) < 40).mean()) for crop in crops]
        print(f"grey-level std of the three scenes: {[round(s, 1) for s in spreads]}; "
              f"share of pixels in the building class's colour: {[round(b, 4) for b in building]}")
        assert min(spreads) > BLANK_STD
        assert min(building) > 0.001  # the points are drawn, in the report's class colours
        assert driver.execute_script("var l = document.getElementById('region-view')._fullLayout;"
                                     "return ['scene', 'scene2', 'scene3'].every(function (s) {"
                                     "  return l[s]._scene.glplot !== null && l[s]._scene.glplot !== undefined; });")
        assert "WebGL is not supported" not in driver.find_element(By.TAG_NAME, "body").text

        eye = driver.execute_async_script(
            "var done = arguments[arguments.length - 1]; var gd = document.getElementById('region-view');"
            "Plotly.relayout(gd, {'scene.camera': {eye: {x: 0.1, y: -2.0, z: 0.3}}}).then(function () {"
            "  setTimeout(function () { done(gd.layout.scene3.camera.eye); }, 500); });")
        assert eye == pytest.approx({"x": 0.1, "y": -2.0, "z": 0.3})

        log = driver.get_log("browser")
        print(f"browser console: {len(log)} entries, levels {sorted({entry['level'] for entry in log})}")
        errors = [entry for entry in log if entry["level"] == "SEVERE"]
        assert not errors, errors
        traces = driver.execute_script(
            "return ['region-view', 'density-maps'].map(function (id) {"
            "  return document.getElementById(id).data.map(function (t) { return t.type; }); });")
        assert traces == [["scatter3d"] * 3, ["heatmap"] * 2]
    finally:
        driver.quit()
