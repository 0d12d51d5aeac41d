"""`flamenerf export --web`: the page, opened from disk in headless Chromium (software
WebGL), draws what the reference rasteriser draws for the same camera and expression."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
from cdp import INSTALL_HINT, Browser, find_chromium  # noqa: E402

from flamenerf.cli import main  # noqa: E402
from flamenerf.errors import UserError  # noqa: E402
from flamenerf.evaluation.metrics import psnr  # noqa: E402
from flamenerf.splats.avatar import load_avatar  # noqa: E402
from flamenerf.splats.rasterise import render_avatar  # noqa: E402
from flamenerf.viewer.web_export import export_web  # noqa: E402
from flamenerf.workflows.bake import bake_views  # noqa: E402

pytestmark = pytest.mark.slow  # a bake, an export and a browser, end to end


@pytest.fixture(scope="module")
def site(toy_run, tmp_path_factory):
    """A copy of the toy run exported (baked on the way) with a two-frame track."""
    root = tmp_path_factory.mktemp("web")
    run = root / "run"
    shutil.copytree(toy_run, run)
    track = root / "track.json"
    track.write_text('{"names": ["jawOpen"], "frames": [[0.0], [1.0]], "fps": 2}')
    assert main(["export", str(run), "--web", str(root / "site"), "--views", "3",
                 "--track", str(track)]) == 0
    return run, root / "site"


def test_the_export_is_a_folder_of_three_files_and_is_not_overwritten(site, capsys):
    run, folder = site
    assert {p.name for p in folder.iterdir()} == {"index.html", "player.js", "avatar.js"}
    assert (run / "baked.npz").is_file()  # baked on the way
    assert '"track": {"fps"' in (folder / "avatar.js").read_text()
    with pytest.raises(UserError, match="already"):
        export_web(load_avatar(run / "baked.npz"), folder)
    (folder.parent / "other").mkdir()
    (folder.parent / "other" / "notes.txt").write_text("mine")
    assert main(["export", str(run), "--web", str(folder.parent / "other")]) == 2
    assert "other files" in capsys.readouterr().err


def test_the_page_draws_what_the_reference_rasteriser_draws(site):
    exe = find_chromium()
    if exe is None:
        where = os.environ.get("FLAMENERF_CHROMIUM")
        pytest.fail("the web export's test needs headless Chromium and "
                    + (f"FLAMENERF_CHROMIUM={where} is not an executable" if where
                       else f"found none on PATH ({INSTALL_HINT})"))
    run, folder = site
    avatar = load_avatar(run / "baked.npz")
    from flamenerf.training.run import load_run

    r = load_run(run, "cpu")
    ds = r.dataset()
    c2w = bake_views(ds, 2)[1]
    beta = avatar.high.copy()
    w = h = 64
    intr = r.train_intrinsics(ds).scaled(w / r.train_intrinsics(ds).w)
    query = ("bare=1&w=64&h=64&c2w=" + ",".join(f"{x:.9g}" for x in np.asarray(c2w).ravel())
             + "&beta=" + ",".join(f"{b:.9g}" for b in beta))
    with Browser(exe, width=400, height=400) as b:
        b.goto((folder / "index.html").absolute().as_uri() + "?" + query)
        b.wait_for("document.title === 'drawn'")
        shot = b.screenshot()[:h, :w].astype(np.float32) / 255
    ref = render_avatar(avatar, beta, c2w, intr)["rgb"].numpy()
    assert ref.std() > 0.02  # something to compare: not an empty view
    assert psnr(shot, ref) > 30
