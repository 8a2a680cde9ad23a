"""The DAM as a matcap: every pixel is the DAM at (the camera's direction, the disk's normal)."""

from __future__ import annotations

import json
import math

import numpy as np
import torch

from damcap.appearance.dam import DamArchitecture, DeepAppearanceMap
from damcap.common.cameras import orbit_world_from_cam
from damcap.export.matcap import matcap_normals, render_matcap


def test_the_disk_holds_every_front_facing_normal():
    n, inside = matcap_normals(256)
    assert abs(inside.mean() - math.pi / 4) < 0.01
    np.testing.assert_allclose(np.linalg.norm(n[inside], axis=1), 1, atol=1e-12)
    assert (n[inside][:, 2] >= 0).all()  # facing the viewer
    assert n[0, 128, 1] > 0.99 and n[128, 255, 0] > 0.99  # top of the image: up; right: right


def test_each_pixel_is_the_dam_at_the_view_and_its_normal():
    dam = DeepAppearanceMap(DamArchitecture(), generator=torch.Generator().manual_seed(3))
    cam = orbit_world_from_cam(1, 3.0, 35.0, 60.0)[0]
    rad, cover = render_matcap(dam, 32, cam)
    n_cam, inside = matcap_normals(32)
    assert (cover == inside).all() and (rad[~inside] == 0).all()
    for i, j in ((16, 16), (3, 16), (20, 28)):
        n_world = cam[:3, :3] @ n_cam[i, j]
        v_world = cam[:3, 3] / np.linalg.norm(cam[:3, 3])  # the orbit camera looks at the origin: back along its +z
        want = dam(torch.tensor(v_world[None], dtype=torch.float32), torch.tensor(n_world[None], dtype=torch.float32))[0]
        np.testing.assert_allclose(rad[i, j], want.detach().numpy(), rtol=1e-5, atol=1e-6)


def test_export_format_matcap_writes_exr_png_and_its_view(model_file, tmp_path, capsys):
    from damcap.cli.main import main
    from damcap.common.exr import read_exr, read_image_u8

    out = tmp_path / "mc"
    assert main(["export", str(model_file), "--format", "matcap", "-o", str(out), "--resolution", "64"]) == 0
    px, channels = read_exr(out / "matcap.exr")
    assert px.shape == (64, 64, 4) and channels[-1] == "A"
    png = read_image_u8(out / "matcap.png")
    assert png.shape == (64, 64, 4) and png[0, 0, 3] == 0 and png[32, 32, 3] == 255
    view = json.loads((out / "matcap.json").read_text())
    assert abs(np.linalg.norm(view["view_dir_world"]) - 1) < 1e-9
