"""Write small Multi-PIE trees (exact layout) with known linear content for the preprocess tests."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from reflectmm_cli.capture.images import encode_linear, write_png
from reflectmm_cli.landmarks import write_pts
from reflectmm_cli.capture.layout import camera_code
from reflectmm_cli.capture.transfer import parse_transfer

VIEWS = ("13_0", "05_1", "08_1")
FLASHES = ("05", "07", "14")


def shot_file(root, ident, cam, shot, session="01", rec="01", ext=".png"):
    return (Path(root) / "data" / f"session{session}" / "multiview" / ident / rec / cam /
            f"{ident}_{session}_{rec}_{camera_code(cam)}_{shot}{ext}")


def make_tree(root, idents=("001",), *, views=VIEWS, flashes=FLASHES, size=(48, 32), session="01", rec="01",
              transfer="gamma1.2", bits=8, seed=0, landmarks=True, room_level=0.1):
    """Room images with a smooth linear pattern, flash images = room + a per-flash blob; returns the linear truth
    {ident: {"room": (V,H,W,3), "flash": (V,F,H,W,3)}} (values before 8-bit quantisation)."""
    rng = np.random.default_rng(seed)
    tr = parse_transfer(transfer)
    W, H = size
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64)
    truth = {}
    for ident in idents:
        rooms, flashes_lin = [], []
        for vi, cam in enumerate(views):
            room = room_level * (0.5 + 0.5 * np.stack([xx / W, yy / H, 0.5 + 0 * xx], -1)) * (1 + 0.1 * vi)
            write_png(shot_file(root, ident, cam, "00", session, rec), encode_linear(room, tr, bits))
            fl = []
            for fi, f in enumerate(flashes):
                cx, cy = rng.uniform(0.3, 0.7) * W, rng.uniform(0.3, 0.7) * H
                blob = 0.6 * np.exp(-((xx - cx) ** 2 + (yy - cy) ** 2) / (2 * (0.2 * W) ** 2))
                img = room + blob[..., None] * np.array([1.0, 0.8, 0.6])
                write_png(shot_file(root, ident, cam, f, session, rec), encode_linear(img, tr, bits))
                fl.append(img)
            if landmarks:
                pts = np.stack([np.linspace(0.3 * W, 0.7 * W, 68), np.linspace(0.25 * H, 0.75 * H, 68)], 1)
                write_pts(shot_file(root, ident, cam, "00", session, rec, ext="_lm.pts"), pts, decimals=3)
            rooms.append(room)
            flashes_lin.append(fl)
        truth[ident] = {"room": np.array(rooms), "flash": np.array(flashes_lin)}
    return truth
