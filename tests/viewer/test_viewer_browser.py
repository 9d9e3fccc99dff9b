"""The viewer in a real browser (headless Chromium, software WebGL): its pictures against ``reflectmm render``.

Each state is given in the page's URL hash; the screenshot is compared with the renderer's image of the same state
(camera, β, light, layer), per-vertex reflectance, with the same exposure and sRGB encoding: PSNR over the face
(the render's face pixels, eroded by one pixel so that edge coverage does not count).

Chromium is installed by ``make test``; without it these tests fail (set REFLECTMM_SKIP_BROWSER=1 to skip them
knowingly).
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import binary_erosion

sys.path.insert(0, str(Path(__file__).parent))
import _browser as B  # noqa: E402
import _viewer_data as D  # noqa: E402

from reflectmm_cli.geometry import to_display  # noqa: E402
from reflectmm_cli.geometry.render_face import render_face  # noqa: E402

pytestmark = pytest.mark.slow

if os.environ.get("REFLECTMM_SKIP_BROWSER") == "1":
    pytest.skip("REFLECTMM_SKIP_BROWSER=1", allow_module_level=True)

W, H = 240, 180
CAM = (20.0, 8.0, 900.0)
FOCAL = 1100.0
BETA = [1.2, -0.8, 0.6]
POINT = (300.0, 250.0, 700.0)
MIN_PSNR = 35.0


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    assert B.chromium() is not None, "no Chromium: run `make test` (installs it) or apt-get install chromium"
    t = tmp_path_factory.mktemp("viewer")
    fm = D.face_model(t / "fm.npz")
    D.envmap(t / "env.exr")
    out = {"dir": t, "fm": t / "fm.npz", "env": t / "env.exr"}
    for k in (1, 3, 5):
        out[f"m{k}"] = D.reflectance_model(t / f"m{k}.npz", fm, k, seed=k)
    return out


def _page(world, model: str, *extra: str, name: str | None = None) -> Path:
    out = world["dir"] / (name or f"{model}.html")
    if not out.exists():
        subprocess.run([sys.executable, "-m", "reflectmm_cli", "-q", "view", str(world[model]), "--face-model",
                        str(world["fm"]), "--envmap", str(world["env"]), *extra, "-o", str(out)], check=True,
                       capture_output=True)
    return out


def _render(world, model: str, light: str, layer: str = "full", size=(W, H), rotate: float = 0.0) -> np.ndarray:
    kw = {"envmap": world["env"]} if light == "env" else {"point_light": ",".join(map(str, POINT))}
    r = render_face(world["fm"], reflectance_model=world[model], coeffs=",".join(map(str, BETA)),
                    camera=f"yaw={CAM[0]},pitch={CAM[1]},distance={CAM[2]},focal={FOCAL},size={size[0]}x{size[1]}",
                    reflectance_at="vertex", layer=layer, env_rotation=rotate, **kw)
    return r["image"]


def _exposure(img: np.ndarray) -> float:
    """render's PNG rule: the 99.5th percentile of the face maps to 0.9."""
    face = img[img.max(-1) > 0]
    return 0.9 / float(np.percentile(face.max(-1), 99.5))


def _hash(light: str, layer: str, exposure: float, size=(W, H), **extra) -> str:
    lh = "light=env:0&rot=0" if light == "env" else "light=point&lp=" + ",".join(map(str, POINT))
    h = (f"beta={','.join(map(str, BETA))}&{lh}&cam={CAM[0]},{CAM[1]},{CAM[2]}&focal={FOCAL}"
         f"&size={size[0]}x{size[1]}&layer={layer}&exposure={exposure!r}&display=srgb&ui=0&aa=0")
    for k, v in extra.items():
        h = re.sub(rf"(^|&){k}=[^&]*", rf"\g<1>{k}={v}", h) if re.search(rf"(^|&){k}=", h) else h + f"&{k}={v}"
    return h


def _psnr(shot: np.ndarray, ref_display: np.ndarray, mask: np.ndarray) -> float:
    d = shot.astype(np.float64)[mask] / 255.0 - ref_display[mask]
    return float(10 * np.log10(1.0 / max(np.mean(d ** 2), 1e-12)))


def _body(dom: str) -> str:
    m = re.search(r"<body[^>]*>", dom)
    assert m, dom[:300]
    return m.group(0)


def _face(img: np.ndarray) -> np.ndarray:
    return binary_erosion(img.max(-1) > 0, iterations=1)


@pytest.mark.parametrize("light,layer", [("env", "full"), ("env", "specular"), ("point", "full"),
                                         ("point", "specular")])
def test_viewer_matches_render(world, light, layer):
    page = _page(world, "m3")
    full = _render(world, "m3", light)
    img = full if layer == "full" else _render(world, "m3", light, layer)
    e = _exposure(full)
    shot = B.screenshot(page, _hash(light, layer, e), (W, H))
    assert shot.shape == (H, W, 3)
    mask = _face(full)
    assert mask.sum() > 0.2 * W * H
    ref = to_display(img, exposure=e, transfer="srgb")
    assert ref[mask].std() > 0.02  # a picture with content, not a flat or saturated one
    psnr = _psnr(shot, ref, mask)
    assert psnr >= MIN_PSNR, f"{light}/{layer}: PSNR {psnr:.1f} dB"


@pytest.mark.parametrize("k", [1, 5])
def test_every_lobe_count_renders(world, k):
    page = _page(world, f"m{k}")
    full = _render(world, f"m{k}", "env")
    e = _exposure(full)
    mask = _face(full)
    psnr = _psnr(B.screenshot(page, _hash("env", "full", e), (W, H)), to_display(full, exposure=e), mask)
    assert psnr >= MIN_PSNR, f"{k} lobes: PSNR {psnr:.1f} dB"
    last = f"lobe{k - 1}"  # the sharpest lobe alone, under the point light
    img = _render(world, f"m{k}", "point", last)
    e2 = _exposure(img)
    psnr = _psnr(B.screenshot(page, _hash("point", last, e2), (W, H)), to_display(img, exposure=e2), mask)
    assert psnr >= MIN_PSNR, f"{k} lobes, {last}: PSNR {psnr:.1f} dB"


@pytest.mark.parametrize("layer", ["albedo", "sumw", "weight2"])
def test_reflectance_layers(world, layer):
    page = _page(world, "m3")
    img = _render(world, "m3", "env", layer)
    mask = _face(img)
    shot = B.screenshot(page, _hash("env", layer, 1.0), (W, H))
    psnr = _psnr(shot, to_display(img, exposure=1.0), mask)
    assert psnr >= MIN_PSNR, f"{layer}: PSNR {psnr:.1f} dB"


def test_environment_rotation(world):
    """The page's rotation turns the light as render --rotate does (SH rotation in Python, a rotated lookup in
    the page): two independent routes to the same picture."""
    page = _page(world, "m3")
    img = _render(world, "m3", "env", rotate=90.0)
    e = _exposure(img)
    mask = _face(img)
    shot = B.screenshot(page, _hash("env", "full", e, rot=90), (W, H))
    assert _psnr(shot, to_display(img, exposure=e), mask) >= MIN_PSNR
    unrotated = to_display(_render(world, "m3", "env"), exposure=e)
    assert _psnr(shot, unrotated, mask) < 30  # the rotation is visible


def test_compare_side_by_side(world):
    """With --compare, each half shows one model at the same state: each equals a render of half the width."""
    page = _page(world, "m3", "--compare", str(world["m1"]), name="cmp.html")
    half = (W // 2, H)
    left, right = _render(world, "m3", "env", size=half), _render(world, "m1", "env", size=half)
    e = _exposure(left)
    shot = B.screenshot(page, _hash("env", "full", e, split=1), (W, H))
    for img, part in ((left, shot[:, :W // 2]), (right, shot[:, W // 2:])):
        assert _psnr(part, to_display(img, exposure=e), _face(img)) >= MIN_PSNR
    # and one of them alone fills the canvas
    only = B.screenshot(page, _hash("env", "full", e, split=0, model=1), (W, H))
    full1 = _render(world, "m1", "env")
    assert _psnr(only, to_display(full1, exposure=e), _face(full1)) >= MIN_PSNR


def test_state_round_trips_through_the_hash(world):
    """The page reads its state from the hash and writes it back in canonical form (data-hash mirrors it)."""
    page = _page(world, "m3")
    dom = B.dom(page, "beta=0.5,-1&light=point&lp=1,2,300&cam=10,5,800&layer=lobe1&ev=1.5&display=gamma1.2")
    m = re.search(r'data-hash="#([^"]*)"', dom)
    assert m, dom[:500]
    state = dict(kv.split("=", 1) for kv in m.group(1).replace("&amp;", "&").split("&"))
    assert state["beta"].split(",")[:3] == ["0.5", "-1", "0"]
    assert state["light"] == "point" and state["lp"] == "1,2,300"
    assert state["cam"] == "10,5,800" and state["layer"] == "lobe1"
    assert state["ev"] == "1.5" and state["display"] == "gamma1.2"
    assert 'data-ready="1"' in _body(dom) and "data-error" not in _body(dom)
    bad = B.dom(page, "layer=nonsense&light=env:99&beta=x,2")  # unknown values fall back to the defaults
    s2 = dict(kv.split("=", 1) for kv in re.search(r'data-hash="#([^"]*)"', bad).group(1).replace("&amp;", "&").split("&"))
    assert s2["layer"] == "full" and s2["light"] == "env:0" and s2["beta"].split(",")[0] == "2"


def test_page_loads_offline_with_no_external_reference(world):
    page = _page(world, "m3")
    text = page.read_text()
    from reflectmm_cli.viewer import EXTERNAL_URL

    assert not EXTERNAL_URL.search(text)
    assert "default-src 'none'" in text and "connect-src 'none'" in text
    dom = B.dom(page, offline=True)  # every host unresolvable, every request proxied into a closed port
    assert 'data-ready="1"' in _body(dom) and "data-error" not in _body(dom)


def test_readme_screenshot(world, tmp_path):
    """The picture in the README: the viewer with its panel (written to docs/ when REFLECTMM_WRITE_SCREENSHOT=1)."""
    page = _page(world, "m3", "--compare", str(world["m1"]), "--names", "3 lobes,1 lobe",
                 "--title", "two test models", name="shot.html")
    shot = B.screenshot(page, "beta=1.2,-0.8,0.6&light=point&lp=450,250,600&cam=-15,5,900&layer=full&split=1",
                        (1000, 520))
    assert shot.shape == (520, 1000, 3) and shot[:, :600].std() > 10
    if os.environ.get("REFLECTMM_WRITE_SCREENSHOT") == "1":
        from PIL import Image

        Image.fromarray(shot).save(Path(__file__).parents[2] / "docs" / "img" / "viewer.png", optimize=True)


def test_light_model_gamma(world):
    """The γ sliders: the page's light-model lighting at γ equals render with the SH of light_from_coeffs at the
    data's mean level (an independent route: numpy on the Python side, the page's own sum in JavaScript)."""
    from reflectmm_cli.artifacts import write_artifact
    from reflectmm_cli.model.light import build_light_model, light_from_coeffs, light_model_arrays

    t = world["dir"]
    lm_path = t / "light.npz"
    if not lm_path.exists():
        env = D.envmap(t / "env2.exr", width=64)
        lm, _ = build_light_model([world["env"], env], order=4, rotations=4, components=3)
        write_artifact(lm_path, "light-model", light_model_arrays(lm))
    page = _page(world, "m3", "--light-model", str(lm_path), name="lm.html")
    from reflectmm_cli.artifacts import read_artifact

    art = read_artifact(lm_path, "light-model")
    gamma = [1.5, -1.0, 0.5]
    K = light_from_coeffs(art.arrays, np.array(gamma), z=art["dc_mean"])
    np.save(t / "k.npy", K)
    r = render_face(world["fm"], reflectance_model=world["m3"], coeffs=",".join(map(str, BETA)), sh=t / "k.npy",
                    camera=f"yaw={CAM[0]},pitch={CAM[1]},distance={CAM[2]},focal={FOCAL},size={W}x{H}",
                    reflectance_at="vertex")["image"]
    e = _exposure(r)
    h = _hash("env", "full", e).replace("light=env:0", "light=model") + "&gamma=" + ",".join(map(str, gamma))
    shot = B.screenshot(page, h, (W, H))
    assert _psnr(shot, to_display(r, exposure=e), _face(r)) >= MIN_PSNR
    mean_only = B.screenshot(page, _hash("env", "full", e).replace("light=env:0", "light=model"), (W, H))
    assert _psnr(mean_only, to_display(r, exposure=e), _face(r)) < 30  # γ changes the picture
